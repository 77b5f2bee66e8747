"""The bundled model on ONNX Runtime by default (talkmesh.models.runtime): exported once into the
cache folder, then run without importing torch, with the motion PyTorch makes; a damaged cache
entry is exported again; a cache that cannot be written falls back to torch (or, asked for ONNX
Runtime, is one line)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from talkmesh.audio.loading import load_audio
from talkmesh.cli import main
from talkmesh.errors import TalkmeshError
from talkmesh.models.onnx import OnnxModel
from talkmesh.models.runtime import cached_graphs, graphs_folder, open_model
from talkmesh.pipeline import animate

CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0870.wav"
)
TOLERANCE = 1e-4  # of the motion's scale (its largest offset from the mean frame)
BUNDLED = "codetalker-synth"


@pytest.fixture()
def cache(tmp_path, monkeypatch) -> Path:
    folder = tmp_path / "cache"
    monkeypatch.setenv("TALKMESH_CACHE", str(folder))
    return folder


def test_the_default_runs_the_cached_graphs_as_torch_does_and_never_imports_torch(cache, tmp_path):
    wave = load_audio(CLIP)[: 3 * 16000]
    net = open_model(BUNDLED)  # the first use exports into the cache
    assert isinstance(net, OnnxModel)
    assert open_model(BUNDLED) is net  # opened once per process
    folder = graphs_folder(BUNDLED)
    assert folder.parent == cache / "onnx" and (folder / "model.speech.onnx").is_file()
    assert sorted(p.name for p in (cache / "onnx").iterdir()) == [folder.name]  # no leftovers
    options = {"model": BUNDLED, "head_motion": 0.0}
    want = animate(wave, runtime="torch", **options).vertices
    got = animate(wave, **options).vertices
    scale = np.abs(want - want.mean(0)).max()
    assert scale > 1e-3 and np.abs(got - want).max() <= TOLERANCE * scale
    # the CLI in a fresh process: the cached graphs, no torch import, the same motion
    out = tmp_path / "cli.npy"
    code = (
        "import sys\nfrom talkmesh.cli import main\n"
        f"rc = main(['animate', {str(CLIP)!r}, '-o', {str(out)!r}, '-q', '--head-motion', '0'])\n"
        "print(rc, 'torch' in sys.modules)\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.stdout.split() == ["0", "False"], res.stderr
    cli = np.load(out)
    whole = animate(load_audio(CLIP), runtime="torch", **options).vertices.reshape(len(cli), -1)
    assert np.abs(cli - whole).max() <= TOLERANCE * np.abs(whole - whole.mean(0)).max()


def test_a_damaged_cache_entry_is_exported_again(cache):
    path = cached_graphs(BUNDLED)
    size = path.stat().st_size
    path.write_bytes(path.read_bytes()[:1000])  # truncated
    again = open_model(BUNDLED)
    assert isinstance(again, OnnxModel) and again is open_model(BUNDLED)
    assert path.stat().st_size == size


def test_a_cache_that_cannot_be_written_falls_back_to_torch(tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("TALKMESH_CACHE", str(blocker))
    assert not isinstance(open_model(BUNDLED), OnnxModel)  # auto: torch, as before
    with pytest.raises(TalkmeshError, match="TALKMESH_CACHE"):
        open_model(BUNDLED, "onnxruntime")
    assert blocker.read_text() == "not a folder"


def test_runtime_options_that_cannot_work_are_one_line(tmp_path, capsys):
    out = tmp_path / "x.npy"
    cases = [
        (["--runtime", "onnxruntime", "--int8", "all"], "--int8 runs on PyTorch"),
        (["--runtime", "onnxruntime", "--model", "procedural"], "procedural is not one"),
        (["--runtime", "torch", "--model", str(tmp_path / "m.onnx")], "runs releases"),
    ]
    for extra, fragment in cases:
        assert main(["animate", str(CLIP), "-o", str(out), "-q", *extra]) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("talkmesh: error:") and fragment in err[0], err
    assert not out.exists()
    with pytest.raises(TalkmeshError, match="--runtime fast"):
        open_model(BUNDLED, "fast")


def test_numpy_log_mel_and_interpolation_equal_torchs():
    """The ONNX path's features without torch: Whisper's log-mel and the frames' interpolation
    as torch computes them (talkmesh.models.whisper.log_mel, F.interpolate)."""
    import torch

    from talkmesh.audio.logmel import interpolate_rows, log_mel
    from talkmesh.models.frames import interpolate_frames
    from talkmesh.models.whisper import log_mel as torch_log_mel

    rng = np.random.default_rng(0)
    for n in (401, 1600, 3 * 16000 + 77):
        wave = (0.1 * rng.standard_normal(n)).astype(np.float32)
        want = torch_log_mel(torch.from_numpy(wave)[None])[0].numpy()
        got = log_mel(wave)
        assert got.shape == want.shape and np.abs(got - want).max() < 1e-5
    rows = rng.standard_normal((50, 7)).astype(np.float32)
    for frames in (1, 2, 37, 50, 415):
        want = interpolate_frames(torch.from_numpy(rows)[None], frames)[0].numpy()
        assert np.abs(interpolate_rows(rows, frames) - want).max() < 1e-6
    with pytest.raises(TalkmeshError, match="too short"):
        log_mel(np.zeros(100, np.float32))


def test_a_release_without_torch_installed_is_one_line(monkeypatch):
    import talkmesh.models.runtime as runtime

    real = runtime.find_spec
    monkeypatch.setattr(runtime, "find_spec", lambda name: None if name == "torch" else real(name))
    with pytest.raises(TalkmeshError, match="learned models need torch"):
        open_model(BUNDLED, "torch")
