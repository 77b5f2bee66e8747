from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from talkmesh.audio.voices import available_voices
from talkmesh.cli import main
from talkmesh.datasets.synth import make_corpus
from talkmesh.evaluation.evaluate import evaluate, find_predictions, write_baseline

pytestmark = pytest.mark.skipif(not shutil.which("mbrola"), reason="mbrola not installed")


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    root = tmp_path_factory.mktemp("ev") / "c"
    make_corpus(root, subjects=3, sentences=2, seed=1, workers=1, progress=False)
    return root


def test_find_predictions_parses_conditions(tmp_path):
    for stem in ("A_B_s01", "A_B_s01_condition_X_Y", "A_B_s02_condition_Z", "other"):
        np.save(tmp_path / f"{stem}.npy", np.zeros(1))
    found = find_predictions(tmp_path, ["A_B_s01", "A_B_s02"])
    assert [c for c, _ in found["A_B_s01"]] == [None, "X_Y"]
    assert [c for c, _ in found["A_B_s02"]] == ["Z"]


def test_baselines_end_to_end_via_cli(corpus, tmp_path, capsys):
    static, proc = tmp_path / "static", tmp_path / "proc"
    assert (
        main(
            [
                "baseline",
                "--dataset",
                "synth",
                "--data",
                str(corpus),
                "--method",
                "static",
                "-o",
                str(static),
                "-q",
            ]
        )
        == 0
    )
    assert write_baseline("synth", corpus, proc, method="procedural", progress=False) == 1
    out = tmp_path / "s.json"
    assert (
        main(
            [
                "evaluate",
                "--dataset",
                "synth",
                "--data",
                str(corpus),
                "--pred",
                str(static),
                "--json",
                str(out),
            ]
        )
        == 0
    )
    table = capsys.readouterr().out
    assert "LVE (x1e-4, squared)" in table and "static" in table
    doc = json.loads(out.read_text())
    assert {"lve", "fdd", "mve", "rows"} <= set(doc) and doc["rows"][0]["name"].startswith(
        "Synth_03"
    )
    s = evaluate("synth", corpus, static, protocol="physical")
    p = evaluate("synth", corpus, proc, protocol="physical")
    assert p.lve < s.lve  # recognised-phone lip sync beats a still face
    assert p.lip_sync > 0.3 and np.isnan(s.lip_sync)


def test_wrong_vertex_count_prediction(corpus, tmp_path, capsys):
    np.save(tmp_path / "Synth_03_chidi_sentence02.npy", np.zeros((5, 30), np.float32))
    assert (
        main(["evaluate", "--dataset", "synth", "--data", str(corpus), "--pred", str(tmp_path)])
        == 2
    )
    err = capsys.readouterr().err
    assert "Synth_03_chidi_sentence02.npy" in err and "4766" in err
    assert (
        main(
            [
                "evaluate",
                "--dataset",
                "synth",
                "--data",
                str(corpus),
                "--pred",
                str(tmp_path / "none"),
            ]
        )
        == 2
    )
    assert len(available_voices()) >= 3


def tiny_release(path, causal: bool | None = None):
    import torch

    from talkmesh.models.codetalker.model import CodeTalker
    from talkmesh.models.release import save_model
    from talkmesh.training.codetalker import build_config
    from talkmesh.training.trainer import DatasetInfo

    tiny = {
        "preset": "small",
        "vq": {
            "hidden": 32,
            "layers": 1,
            "heads": 2,
            "ff": 64,
            "components": 4,
            "code_dim": 8,
            "codebook_size": 16,
        },
        "stage2": {"d_model": 32, "heads": 2, "ff": 64, "layers": 1, "speech": {"dim": 16}},
    }
    if causal is not None:
        tiny["vq"]["causal"] = causal
    info = DatasetInfo(
        num_vertices=4766, motion_fps=30.0, train_subjects=("Synth_01_ada", "Synth_02_bo")
    )
    torch.manual_seed(0)
    net = CodeTalker(build_config(tiny, info))
    torch.nn.init.normal_(net.feat_map.weight, std=0.5)  # zero-initialised: every frame alike
    return save_model(net, path)


def test_learned_model_predictions_named_like_the_anchors(corpus, tmp_path):
    release = tiny_release(tmp_path / "m.safetensors")
    out = tmp_path / "pred"
    assert (
        main(
            [
                "predict",
                "--model",
                str(release),
                "--dataset",
                "synth",
                "--data",
                str(corpus),
                "--conditions",
                "-o",
                str(out),
                "-q",
            ]
        )
        == 0
    )
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        "Synth_03_chidi_sentence02_condition_Synth_01_ada.npy",
        "Synth_03_chidi_sentence02_condition_Synth_02_bo.npy",
    ]
    scores = evaluate("synth", corpus, out)
    assert scores.n_sequences == 2 and {r.condition for r in scores.rows} == {
        "Synth_01_ada",
        "Synth_02_bo",
    }


def test_predict_points_to_exact_mode_for_a_bidirectional_vq_decoder(corpus, tmp_path, capsys):
    release = tiny_release(tmp_path / "m.safetensors", causal=False)
    args = ["predict", "--model", str(release), "--dataset", "synth", "--data", str(corpus)]
    assert main([*args, "-o", str(tmp_path / "fast")]) == 0
    assert "--mode exact" in capsys.readouterr().err
    assert main([*args, "--mode", "exact", "-o", str(tmp_path / "exact")]) == 0
    assert "--mode exact" not in capsys.readouterr().err
    causal = tiny_release(tmp_path / "c.safetensors", causal=True)
    assert (
        main(
            [
                "predict",
                "--model",
                str(causal),
                "--dataset",
                "synth",
                "--data",
                str(corpus),
                "-o",
                str(tmp_path / "causal"),
            ]
        )
        == 0
    )
    assert "--mode exact" not in capsys.readouterr().err


def test_stage1_reconstructions_are_scored_like_predictions(corpus, tmp_path):
    release = tiny_release(tmp_path / "m.safetensors")
    out = tmp_path / "recon"
    assert (
        main(
            [
                "predict",
                "--model",
                str(release),
                "--dataset",
                "synth",
                "--data",
                str(corpus),
                "--mode",
                "reconstruct",
                "-o",
                str(out),
                "-q",
            ]
        )
        == 0
    )
    assert sorted(p.name for p in out.iterdir()) == ["Synth_03_chidi_sentence02.npy"]
    assert evaluate("synth", corpus, out).n_sequences == 1


def test_learned_models_get_procedural_blinks_only_around_the_eyes(tmp_path):
    from talkmesh.face.assets import load_head
    from talkmesh.pipeline import animate

    release = tiny_release(tmp_path / "m.safetensors")
    wave = np.random.default_rng(0).standard_normal(16_000 * 6).astype(np.float32) * 0.1
    plain = animate(wave, model=str(release), blinks=False)
    eyes = animate(wave, model=str(release), seed=1)
    assert plain.vertices.shape == eyes.vertices.shape == (180, 4766, 3)
    moved = np.abs(eyes.vertices - plain.vertices).max(axis=(0, 2)) > 1e-5
    head = load_head()
    blink = np.abs(
        head.blendshapes[[i for i, n in enumerate(head.blendshape_names) if "Blink" in n]]
    )
    assert moved.any() and not moved[np.abs(head.blendshapes).max(axis=(0, 2)) == 0].any()
    assert moved[blink.max(axis=(0, 2)) > 1e-3].mean() > 0.5  # the eyelids move
    assert eyes.weights.shape == (180, 52) and 0 <= eyes.weights.min() <= eyes.weights.max() <= 1
    assert eyes.basis is not None and len(eyes.weight_names) == 52  # ARKit exports work
