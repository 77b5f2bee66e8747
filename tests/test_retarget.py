"""`talkmesh retarget` and `talkmesh dub` on a tiny MeshTalk over the bundled topology."""

from __future__ import annotations

import numpy as np
import pytest
import soundfile as sf
import torch

from talkmesh.cli import main
from talkmesh.face.assets import load_head
from talkmesh.models.mel import MelConfig
from talkmesh.models.meshtalk.model import MeshTalkConfig, MeshTalkModel, MeshTalkModelConfig
from talkmesh.models.meshtalk.prior import PriorConfig
from talkmesh.models.release import save_model

SR = 16_000


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("retarget")
    head = load_head()
    V = head.num_vertices
    torch.manual_seed(0)
    cfg = MeshTalkConfig(
        num_vertices=V,
        num_heads=4,
        num_classes=8,
        audio=MelConfig(width=16, out_dim=16),
        expression_widths=(32, 16, 16),
        fusion_width=32,
        decoder_widths=(32, 16, 16),
    )
    system = MeshTalkModel(MeshTalkModelConfig(cfg)).eval()
    torch.nn.init.normal_(system.model.decoder.output.weight, std=0.01)  # not the bare template
    torch.nn.init.normal_(system.model.audio_encoder.output.weight, std=3.0)  # audio matters
    save_model(system, tmp / "mt.safetensors")
    prior = PriorConfig(
        num_heads=4, num_classes=8, width=8, audio=cfg.audio, audio_source="expression"
    )
    animator = MeshTalkModel(MeshTalkModelConfig(cfg, prior)).eval()
    animator.model.load_state_dict(system.model.state_dict())
    save_model(animator, tmp / "mt_prior.safetensors")
    rng = np.random.default_rng(0)
    T = 30
    anim = head.template[None] + 0.002 * rng.standard_normal((T, V, 3)).astype(np.float32)
    np.save(tmp / "src.npy", anim.reshape(T, -1))
    t = np.arange(SR) / SR
    sf.write(tmp / "src.wav", (0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32), SR)
    sf.write(tmp / "new.wav", rng.normal(0, 0.3, SR).astype(np.float32), SR)
    target = load_head("bo").template
    np.save(tmp / "target.npy", target)
    np.save(tmp / "small.npy", target[:100])
    return tmp, head, target


def test_retarget_puts_the_motion_on_the_target_face(files):
    tmp, head, target = files
    out = tmp / "retargeted.npy"
    assert (
        main(
            [
                "retarget",
                "--model",
                str(tmp / "mt.safetensors"),
                "--anim",
                str(tmp / "src.npy"),
                "--audio",
                str(tmp / "src.wav"),
                "--template",
                str(tmp / "target.npy"),
                "-o",
                str(out),
                "-q",
            ]
        )
        == 0
    )
    verts = np.load(out).reshape(-1, head.num_vertices, 3)
    assert verts.shape[0] == 30
    # decoded on the target's neutral mesh: close to it, far from the source's
    assert np.abs(verts - target).mean() < np.abs(verts - head.template).mean()


def test_dub_keeps_the_animation_and_follows_the_new_audio(files):
    tmp, head, _ = files
    args = ["dub", "--model", str(tmp / "mt.safetensors"), "--anim", str(tmp / "src.npy"), "-q"]
    assert main([*args, "--audio", str(tmp / "src.wav"), "-o", str(tmp / "same.npy")]) == 0
    assert main([*args, "--audio", str(tmp / "new.wav"), "-o", str(tmp / "dubbed.npy")]) == 0
    same, dubbed = np.load(tmp / "same.npy"), np.load(tmp / "dubbed.npy")
    assert same.shape == dubbed.shape == (30, head.num_vertices * 3)
    assert not np.allclose(same, dubbed)  # the new audio changed the motion


def test_retarget_and_dub_errors(files, capsys):
    tmp, _, _ = files
    base = [
        "retarget",
        "--model",
        str(tmp / "mt.safetensors"),
        "--anim",
        str(tmp / "src.npy"),
        "--audio",
        str(tmp / "src.wav"),
        "-o",
        str(tmp / "x.npy"),
    ]
    assert main([*base, "--template", str(tmp / "small.npy")]) != 0
    assert "100 vertices" in capsys.readouterr().err
    assert main([*base, "--template", str(tmp / "missing.obj")]) != 0
    assert "missing.obj" in capsys.readouterr().err
    (tmp / "bad.safetensors").write_bytes(b"garbage")
    bad = [
        "dub",
        "--model",
        str(tmp / "bad.safetensors"),
        "--anim",
        str(tmp / "src.npy"),
        "--audio",
        str(tmp / "new.wav"),
        "-o",
        str(tmp / "y.npy"),
    ]
    assert main(bad) != 0
    assert "bad.safetensors" in capsys.readouterr().err
    (tmp / "exists.npy").write_bytes(b"keep")
    dub = [
        "dub",
        "--model",
        str(tmp / "mt.safetensors"),
        "--anim",
        str(tmp / "src.npy"),
        "--audio",
        str(tmp / "new.wav"),
        "-o",
        str(tmp / "exists.npy"),
    ]
    assert main(dub) != 0 and (tmp / "exists.npy").read_bytes() == b"keep"
    assert "already exists" in capsys.readouterr().err


def test_animate_with_a_meshtalk_release_samples_by_seed(files, capsys):
    tmp, head, _ = files
    base = [
        "animate",
        str(tmp / "src.wav"),
        "--model",
        str(tmp / "mt_prior.safetensors"),
        "--no-blinks",
        "-q",
    ]
    assert main([*base, "--seed", "1", "-o", str(tmp / "a1.npy")]) == 0
    assert main([*base, "--seed", "1", "-o", str(tmp / "a1b.npy")]) == 0
    assert main([*base, "--seed", "2", "-o", str(tmp / "a2.npy")]) == 0
    a1, a1b, a2 = (np.load(tmp / f) for f in ("a1.npy", "a1b.npy", "a2.npy"))
    assert a1.shape == (30, head.num_vertices * 3)  # 1 s of audio at 30 fps, on the bundled face
    assert np.array_equal(a1, a1b) and not np.array_equal(a1, a2)
    # the expression space alone cannot animate audio; MeshTalk has no speaker styles
    assert main([*base[:2], "--model", str(tmp / "mt.safetensors"), "-o", str(tmp / "x.npy")]) != 0
    assert "no prior" in capsys.readouterr().err
    assert main([*base, "--style", "A:1", "-o", str(tmp / "y.npy")]) != 0
    assert "no speaker styles" in capsys.readouterr().err
