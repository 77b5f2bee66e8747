"""Training machinery: recipes, exact resume after a kill, DDP on two CPU processes."""

from __future__ import annotations

import csv
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from talkmesh.datasets.synth import make_corpus
from talkmesh.errors import TalkmeshError
from talkmesh.training.trainer import crop_window, load_recipe

pytest.importorskip("lightning")
pytestmark = pytest.mark.skipif(not shutil.which("mbrola"), reason="mbrola not installed")
ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "tests" / "recipes" / "meshtalk_expression.yaml"


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("train") / "c"
    make_corpus(root, subjects=3, sentences=2, seed=3, workers=1, progress=False)
    return root


def train_cli(*args: str) -> subprocess.Popen:
    env = dict(os.environ, HF_HUB_OFFLINE="1", PYTHONWARNINGS="ignore")
    return subprocess.Popen(
        [sys.executable, "-m", "talkmesh", "train", str(RECIPE), *args, "-q"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def losses(out: Path) -> dict[int, float]:
    rows = csv.DictReader((out / "logs" / "metrics.csv").open())
    return {int(r["step"]): float(r["train/loss"]) for r in rows if r.get("train/loss")}


def common(corpus: Path, out: Path, epochs: int) -> list[str]:
    return [
        f"data.root={corpus}",
        f"train.out_dir={out}",
        f"train.epochs={epochs}",
        "data.batch_size=1",
        "data.max_seconds=1.0",
        "train.log_every=1",
        "train.accelerator=cpu",
        "model.expression_widths=[32,32]",
        "model.decoder_widths=[32,32]",
        "model.fusion_width=32",
    ]


def test_recipe_overrides_and_errors():
    recipe = load_recipe(RECIPE, ["train.lr=3e-4", "data.batch_size=2"])
    assert recipe.train.lr == pytest.approx(3e-4) and recipe.data.batch_size == 2
    with pytest.raises(TalkmeshError, match="unknown config key train.lrate"):
        load_recipe(RECIPE, ["train.lrate=1"])
    with pytest.raises(TalkmeshError, match="unknown task"):
        load_recipe(RECIPE, ["task=nothing"])


def test_crops_depend_only_on_seed_epoch_index():
    assert crop_window(100, 30, 0, 1, 5) == crop_window(100, 30, 0, 1, 5)
    starts = {crop_window(100, 30, 0, e, 5)[0] for e in range(10)}
    assert len(starts) > 3
    assert crop_window(20, 30, 0, 0, 0) == (0, 20)


@pytest.mark.slow  # minutes on 2 cores: `make test-slow`
def test_resume_after_kill_continues_the_same_loss_curve(corpus, tmp_path):
    ref = tmp_path / "ref"
    proc = train_cli(*common(corpus, ref, 6))
    assert proc.wait(timeout=600) == 0, proc.stderr.read()
    assert (ref / "model.safetensors").is_file()

    run = tmp_path / "run"
    proc = train_cli(*common(corpus, run, 6))
    deadline = time.time() + 300
    while not (run / "epoch001.ckpt").exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)  # killed somewhere after the second epoch's checkpoint
    proc.wait()
    assert (run / "last.ckpt").exists() and not (run / "model.safetensors").exists()
    again = train_cli(*common(corpus, run, 6), "--resume")
    assert again.wait(timeout=600) == 0, again.stderr.read()
    expected, got = losses(ref), losses(run)
    resumed = sorted(set(got) & set(expected))
    assert max(expected) in resumed and len(resumed) >= 4
    for step in resumed:
        assert got[step] == pytest.approx(expected[step], rel=1e-4, abs=1e-6), step


def test_ddp_two_processes_see_different_batches_and_agree(corpus, tmp_path):
    out = tmp_path / "ddp"
    proc = train_cli(*common(corpus, out, 2), "train.record_batches=true", "--devices", "2")
    assert proc.wait(timeout=600) == 0, proc.stderr.read()
    seen = [(out / f"batches_rank{r}.txt").read_text().split() for r in (0, 1)]
    assert seen[0] and seen[1]
    for epoch in range(2):  # within an epoch the two shards are disjoint
        a = seen[0][epoch * len(seen[0]) // 2 : (epoch + 1) * len(seen[0]) // 2]
        b = seen[1][epoch * len(seen[1]) // 2 : (epoch + 1) * len(seen[1]) // 2]
        assert not set(a) & set(b)
    w = [(out / f"weights_rank{r}.sha256").read_text() for r in (0, 1)]
    assert w[0] == w[1]


def test_refuses_to_clobber_a_run(corpus, tmp_path):
    out = tmp_path / "x"
    out.mkdir()
    (out / "last.ckpt").write_bytes(b"mine")
    proc = train_cli(*common(corpus, out, 1))
    assert proc.wait(timeout=300) == 2
    assert "--resume" in proc.stderr.read()
    assert (out / "last.ckpt").read_bytes() == b"mine"


@pytest.mark.slow  # most of a minute on 2 cores: `make test-slow`
def test_resume_takes_the_newest_checkpoint_and_checks_the_recipe_first(corpus, tmp_path):
    from talkmesh.training.checkpoints import newest_checkpoint

    a, b = tmp_path / "a", tmp_path / "b"
    for out, epochs in ((a, 1), (b, 2)):
        proc = train_cli(*common(corpus, out, epochs))
        assert proc.wait(timeout=600) == 0, proc.stderr.read()
    # a moved run folder: Lightning's versioned name holds the newest work, and a truncated copy
    (a / "last-v1.ckpt").write_bytes((b / "last.ckpt").read_bytes())
    whole = (b / "last.ckpt").read_bytes()
    (a / "last-v2.ckpt").write_bytes(whole[: len(whole) // 2])
    recipe_json = (a / "recipe.json").read_bytes()
    done = newest_checkpoint(b)

    bad = train_cli(*common(corpus, a, 3), "model.fusion_width=16", "--resume")
    assert bad.wait(timeout=600) == 2
    errors = [line for line in bad.stderr.read().splitlines() if "error" in line]
    assert len(errors) == 1 and "model.fusion_width (32 -> 16)" in errors[0], errors
    assert (a / "recipe.json").read_bytes() == recipe_json

    again = train_cli(*common(corpus, a, 3), "train.lr=1.0e-4", "--resume")
    assert again.wait(timeout=600) == 0
    err = again.stderr.read()
    assert f"resuming from {a / 'last-v1.ckpt'}" in err, err
    assert "last-v2.ckpt: truncated or corrupt" in err
    assert "train.lr 0.0005 -> 0.0001" in err and "train.epochs 2 -> 3" in err
    final = newest_checkpoint(a)
    assert final.epoch == 2 and final.step == done.step * 3 // 2  # one more epoch, not two
