"""No code runs from a file: a pickle that would write a marker is refused by every reader.

Also the resume rules: newest complete checkpoint by stored step, recipe/shape checks before any
write, warnings for changed settings and skipped (truncated) files.
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from talkmesh.errors import TalkmeshError, TalkmeshWarning  # noqa: E402
from talkmesh.training import checkpoints  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "tests" / "recipes" / "meshtalk_expression.yaml"


class Planted:
    """Unpickling this creates ``marker``: the proof that code from the file ran."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def plant(path: Path, marker: Path) -> Path:
    """A checkpoint-looking pickle with a payload, as an attacker would hand one over."""
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"epoch": 3, "global_step": 99, "payload": Planted(marker)}, path)
    return path


def assert_refused(message: str, path: Path, marker: Path) -> None:
    assert not marker.exists(), "code from the file ran"
    assert str(path) in message, message
    assert "\n" not in message.strip() and "Traceback" not in message, message


def talkmesh(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, HF_HUB_OFFLINE="1", PYTHONWARNINGS="ignore")
    return subprocess.run(
        [sys.executable, "-m", "talkmesh", *args], capture_output=True, text=True, env=env, cwd=cwd
    )


def test_read_checkpoint_refuses_a_planted_pickle(tmp_path):
    path = plant(tmp_path / "last.ckpt", tmp_path / "marker")
    with pytest.raises(
        TalkmeshError, match="last.ckpt: refused: the file tries to load io.open, which is code"
    ) as e:
        checkpoints.read_checkpoint(path)
    assert_refused(str(e.value), path, tmp_path / "marker")


def test_recipe_from_checkpoint_refuses_a_planted_pickle(tmp_path):
    from talkmesh.training.trainer import recipe_from_checkpoint

    path = plant(tmp_path / "run" / "last.ckpt", tmp_path / "marker")
    with pytest.raises(TalkmeshError) as e:
        recipe_from_checkpoint(path)
    assert_refused(str(e.value), path, tmp_path / "marker")


def test_benchmark_stage_resume_refuses_a_planted_pickle(tmp_path):
    from talkmesh.evaluation.benchmark import steps

    path = plant(tmp_path / "stage" / "last.ckpt", tmp_path / "marker")
    with pytest.raises(TalkmeshError) as e:
        steps._checkpoint_epochs(path)
    assert_refused(str(e.value), path, tmp_path / "marker")


def test_train_resume_refuses_a_planted_pickle_and_writes_nothing(tmp_path):
    run = tmp_path / "run"
    path = plant(run / "last.ckpt", tmp_path / "marker")
    proc = talkmesh("train", str(RECIPE), f"train.out_dir={run}", "--resume", "-q", cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert_refused(proc.stderr, path, tmp_path / "marker")
    assert "internal error" not in proc.stderr and "weights_only" not in proc.stderr
    assert sorted(p.name for p in run.iterdir()) == ["last.ckpt"]


@pytest.mark.parametrize(
    "family, names",
    [("faceformer", ["vocaset.pth"]), ("codetalker", ["stage1.pth.tar", "stage2.pth.tar"])],
)
def test_official_checkpoint_import_refuses_a_planted_pickle(tmp_path, family, names):
    paths = [plant(tmp_path / name, tmp_path / "marker") for name in names]
    path = paths[0]  # read first
    args = ["import-checkpoint", *map(str, paths), "--family", family, "--dataset", "vocaset"]
    proc = talkmesh(*args, "-o", "out.safetensors", cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert_refused(proc.stderr, path, tmp_path / "marker")
    assert "internal error" not in proc.stderr and not (tmp_path / "out.safetensors").exists()


def test_wav2vec2_folder_with_a_planted_pickle_is_refused(tmp_path):
    transformers = pytest.importorskip("transformers")
    from talkmesh.models.speech import SpeechEncoderConfig, Wav2Vec2Encoder

    folder = tmp_path / "w2v"
    transformers.Wav2Vec2Config(
        hidden_size=16,
        num_hidden_layers=1,
        num_attention_heads=2,
        intermediate_size=8,
        conv_dim=(8, 8),
        conv_stride=(5, 2),
        conv_kernel=(10, 3),
    ).save_pretrained(folder)
    path = plant(folder / "pytorch_model.bin", tmp_path / "marker")
    with pytest.raises(TalkmeshError, match="refusing") as e:
        Wav2Vec2Encoder(SpeechEncoderConfig(kind="wav2vec2", source=str(folder)))
    assert_refused(str(e.value), path, tmp_path / "marker")


def test_whisper_folder_with_planted_pickles_is_refused(tmp_path):
    transformers = pytest.importorskip("transformers")
    from talkmesh.models.whisper import load_whisper_encoder

    folder = tmp_path / "whisper"
    transformers.WhisperConfig(
        d_model=16, encoder_layers=1, encoder_attention_heads=2
    ).save_pretrained(folder)
    plant(folder / "pytorch_model.bin", tmp_path / "marker")  # never read
    plant(folder / "model.safetensors", tmp_path / "marker")  # read, as safetensors: refused
    with pytest.raises(TalkmeshError) as e:
        load_whisper_encoder(folder)
    assert_refused(str(e.value), folder, tmp_path / "marker")


# --------------------------------------------------------------------------- resume rules


def fake_checkpoint(path: Path, step: int, epoch: int, recipe: dict, width: int = 4) -> Path:
    state = {"model.w": torch.zeros(width, 3)}
    torch.save(
        {"global_step": step, "epoch": epoch, "talkmesh_recipe": recipe, "state_dict": state}, path
    )
    return path


RECIPE_DICT = {
    "task": "meshtalk",
    "model": {"width": 4},
    "data": {"kind": "synth", "regions": None, "num_workers": 0},
    "train": {"lr": 1e-3, "epochs": 4, "out_dir": "a"},
}


def test_newest_checkpoint_is_chosen_by_stored_step_not_name(tmp_path):
    fake_checkpoint(tmp_path / "last.ckpt", 10, 1, RECIPE_DICT)
    fake_checkpoint(tmp_path / "last-v1.ckpt", 30, 2, RECIPE_DICT)
    fake_checkpoint(tmp_path / "last-v2.ckpt", 20, 1, RECIPE_DICT)
    os.utime(tmp_path / "last.ckpt")  # newest on disk, oldest in training
    assert checkpoints.newest_checkpoint(tmp_path).path.name == "last-v1.ckpt"


def test_truncated_checkpoint_falls_back_to_the_newest_loadable_with_a_warning(tmp_path):
    fake_checkpoint(tmp_path / "epoch001.ckpt", 10, 1, RECIPE_DICT)
    good = fake_checkpoint(tmp_path / "last.ckpt", 20, 2, RECIPE_DICT).read_bytes()
    (tmp_path / "last.ckpt").write_bytes(good[: len(good) // 2])  # killed while writing
    with pytest.warns(TalkmeshWarning, match="last.ckpt: truncated or corrupt") as caught:
        chosen = checkpoints.newest_checkpoint(tmp_path)
    assert chosen.path.name == "epoch001.ckpt" and chosen.step == 10
    assert all("\n" not in str(w.message) for w in caught)


def test_no_loadable_checkpoint_is_one_line_naming_each(tmp_path):
    (tmp_path / "last.ckpt").write_bytes(b"PK\x03\x04 not really")
    with pytest.raises(TalkmeshError, match="nothing to resume") as e:
        checkpoints.newest_checkpoint(tmp_path)
    assert str(tmp_path / "last.ckpt") in str(e.value) and "\n" not in str(e.value)


def test_recipe_that_changes_shapes_is_refused_listing_the_keys(tmp_path):
    ckpt = checkpoints.Checkpoint(tmp_path / "last.ckpt", 5, 0, {"talkmesh_recipe": RECIPE_DICT})
    other = {**RECIPE_DICT, "model": {"width": 8}}
    with pytest.raises(TalkmeshError, match=r"model.width \(4 -> 8\)") as e:
        checkpoints.check_resume(ckpt, other)
    assert "\n" not in str(e.value)
    stored = {"state_dict": {"model.w": torch.zeros(4, 3)}}
    with pytest.raises(TalkmeshError, match=r"model.w \(4, 3\) -> \(8, 3\)"):
        checkpoints.check_state_shapes(ckpt._replace(data=stored), {"model.w": torch.zeros(8, 3)})


def test_changed_lr_and_epochs_are_warned_with_old_and_new(tmp_path):
    ckpt = checkpoints.Checkpoint(tmp_path / "last.ckpt", 5, 0, {"talkmesh_recipe": RECIPE_DICT})
    new = {**RECIPE_DICT, "train": {"lr": 1e-4, "epochs": 6, "out_dir": "moved"}}
    with pytest.warns(TalkmeshWarning) as caught:
        checkpoints.check_resume(ckpt, new)
    (message,) = [str(w.message) for w in caught]
    assert "train.lr 0.001 -> 0.0001" in message and "train.epochs 4 -> 6" in message
    assert "out_dir" not in message
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        checkpoints.check_resume(
            ckpt, {**RECIPE_DICT, "train": {**RECIPE_DICT["train"], "out_dir": "b"}}
        )
