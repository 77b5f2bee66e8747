"""``--cluster``: a library animated on a Ray cluster started on loopback for these tests (``ray
start --head`` on 127.0.0.1, two CPUs, stopped at the end) gives the frames of a local run, and a
bad file or a dead address are one line each."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ray", reason="the cluster extra (pip install 'talkmesh[cluster]') is needed")

from talkmesh.batch import AnimateSettings, animate_batch  # noqa: E402
from talkmesh.cli import main  # noqa: E402

LIBRIVOX = Path("/usr/share/pocketsphinx/test/data/librivox")
CLIPS = sorted(LIBRIVOX.glob("sense_and_sensibility_01_austen_64kb-08*.wav"))[:2]
SRC = Path(__file__).resolve().parents[1] / "src"

pytestmark = pytest.mark.skipif(len(CLIPS) < 2, reason="pocketsphinx-testdata not installed")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def head(tmp_path_factory) -> str:
    """The address of a two-CPU Ray head on 127.0.0.1 whose workers import this source tree."""
    ray_cli = Path(sys.executable).with_name("ray")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")]))
    env["RAY_USAGE_STATS_ENABLED"] = "0"
    temp = tmp_path_factory.mktemp("ray")
    port = free_port()
    start = [str(ray_cli), "start", "--head", "--node-ip-address=127.0.0.1", f"--port={port}"]
    start += [
        "--num-cpus=2",
        "--include-dashboard=false",
        f"--temp-dir={temp}",
        "--disable-usage-stats",
    ]
    subprocess.run(start, env=env, check=True, capture_output=True, timeout=180)
    try:
        yield f"127.0.0.1:{port}"
    finally:
        subprocess.run([str(ray_cli), "stop", "--force"], env=env, capture_output=True, timeout=120)


@pytest.fixture
def library(tmp_path) -> Path:
    lib = tmp_path / "lib"
    lib.mkdir()
    for k, clip in enumerate(CLIPS):
        (lib / f"line{k}.wav").write_bytes(clip.read_bytes())
    (lib / "zz_broken.flac").write_bytes(b"fLaC not really")
    return lib


def test_library_on_the_cluster_equals_a_local_run(head, library, tmp_path, capsys):
    out = tmp_path / "out"
    args = ["animate", str(library), "-o", f"{out}/{{stem}}.npy", "--model", "procedural", "-q"]
    assert main([*args, "--cluster", head]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and "1 of 3 files failed" in err and "zz_broken.flac" in err
    audio = sorted(library.glob("line*.wav"))
    local = animate_batch(
        audio,
        [[tmp_path / "local" / a.with_suffix(".npy").name] for a in audio],
        AnimateSettings(model="procedural"),
    )
    assert [r.status for r in local.rows] == ["ok", "ok"]
    for a in audio:
        name = a.with_suffix(".npy").name
        # equal to float32 rounding: a Ray worker runs one BLAS thread, which may sum in
        # another order than the test process (1e-9 m apart on numpy 2.4 / scipy 1.17)
        np.testing.assert_allclose(
            np.load(out / name), np.load(tmp_path / "local" / name), rtol=0, atol=1e-7
        )
    assert main([*args, "--cluster", head]) == 1  # resumed: only the broken file is tried again
    assert "1 of 3 files failed (0 animated, 2 already done)" in capsys.readouterr().err


def test_unreachable_or_malformed_cluster_is_one_line(library, tmp_path, capsys):
    out = f"{tmp_path}/out/"
    for address, fragment in (
        (f"127.0.0.1:{free_port()}", "cannot reach a Ray head"),
        ("nowhere", "give HOST:PORT"),
    ):
        rc = main(
            ["animate", str(library), "-o", out, "--model", "procedural", "--cluster", address]
        )
        err = capsys.readouterr().err
        assert rc == 2 and "Traceback" not in err
        lines = [ln for ln in err.splitlines() if ln.startswith("talkmesh: error:")]
        assert len(lines) == 1 and fragment in lines[0] and address in lines[0], err
    assert not Path(out).exists()


VOCA = """\
task: voca
model:
  preset: small
  speech: {kind: mel, dim: 16}
  conv_channels: [8, 8]
  hidden: 16
  latent: 4
data: {kind: synth, root: not/the/benchmark/corpus, batch_size: 2, max_seconds: 1.0}
train: {lr: 1.0e-3, epochs: 1, accelerator: cpu, out_dir: runs/tiny_voca}
"""


@pytest.mark.slow  # minutes on 2 cores: `make test-slow`
def test_benchmark_cells_on_the_cluster_then_nothing_left_locally(head, tmp_path):
    from talkmesh.datasets.synth import make_corpus
    from talkmesh.evaluation.benchmark import run_benchmark

    make_corpus(tmp_path / "corpus", subjects=3, sentences=3, seed=3, workers=1, progress=False)
    (tmp_path / "voca.yaml").write_text(VOCA)
    config = tmp_path / "bench.yaml"
    config.write_text(
        f"name: tiny\ndata: {{kind: synth, root: {tmp_path / 'corpus'}, split: test}}\n"
        f"seeds: [0, 1]\nwork_dir: {tmp_path / 'work'}\ndocs_dir: {tmp_path / 'docs'}\n"
        f"baselines: [static]\nmethods:\n  voca: {{recipe: {tmp_path / 'voca.yaml'}}}\n"
        "speed: {seconds: [1], repeats: 1}\nsamples: 1\nvideo: false\n"
    )
    lines: list[str] = []
    result = run_benchmark(config, cluster=head, log=lines.append, progress=False)
    assert sorted(p.parent.name for p in result.trained) == ["seed0", "seed1"]
    where = [ln for ln in lines if ": ran on " in ln]
    assert len(where) == 2
    assert all(int(ln.rsplit("pid ", 1)[1]) != os.getpid() for ln in where)  # Ray workers did it
    assert result.json.exists() and "voca" in result.markdown.read_text()
    again = run_benchmark(config, quiet=True)  # a local run finds every cell done
    assert again.trained == [] and again.predicted == []
