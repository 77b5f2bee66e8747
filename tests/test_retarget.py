"""`talkmesh retarget` and `talkmesh dub` on a tiny MeshTalk over the bundled topology."""

from __future__ import annotations

import numpy as np
import pytest
import soundfile as sf
import torch

from talkmesh.assets import load_head
from talkmesh.cli import main
from talkmesh.models.meshtalk import MelConfig, MeshTalkConfig, MeshTalkModel, MeshTalkModelConfig
from talkmesh.models.release import save_model

SR = 16_000


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("retarget")
    head = load_head()
    V = head.num_vertices
    torch.manual_seed(0)
    cfg = MeshTalkConfig(num_vertices=V, num_heads=4, num_classes=8,
                         audio=MelConfig(width=16, out_dim=16), expression_widths=(32, 16, 16),
                         fusion_width=32, decoder_widths=(32, 16, 16))  # fmt: skip
    system = MeshTalkModel(MeshTalkModelConfig(cfg)).eval()
    torch.nn.init.normal_(system.model.decoder.output.weight, std=0.01)  # not the bare template
    torch.nn.init.normal_(system.model.audio_encoder.output.weight, std=3.0)  # audio matters
    save_model(system, tmp / "mt.safetensors")
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
    assert main(["retarget", "--model", str(tmp / "mt.safetensors"), "--anim", str(tmp / "src.npy"),
                 "--audio", str(tmp / "src.wav"), "--template", str(tmp / "target.npy"),
                 "-o", str(out), "-q"]) == 0  # fmt: skip
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
    base = ["retarget", "--model", str(tmp / "mt.safetensors"), "--anim", str(tmp / "src.npy"),
            "--audio", str(tmp / "src.wav"), "-o", str(tmp / "x.npy")]  # fmt: skip
    assert main([*base, "--template", str(tmp / "small.npy")]) != 0
    assert "100 vertices" in capsys.readouterr().err
    assert main([*base, "--template", str(tmp / "missing.obj")]) != 0
    assert "missing.obj" in capsys.readouterr().err
    (tmp / "bad.safetensors").write_bytes(b"garbage")
    bad = ["dub", "--model", str(tmp / "bad.safetensors"), "--anim", str(tmp / "src.npy"),
           "--audio", str(tmp / "new.wav"), "-o", str(tmp / "y.npy")]  # fmt: skip
    assert main(bad) != 0
    assert "bad.safetensors" in capsys.readouterr().err
    (tmp / "exists.npy").write_bytes(b"keep")
    dub = ["dub", "--model", str(tmp / "mt.safetensors"), "--anim", str(tmp / "src.npy"),
           "--audio", str(tmp / "new.wav"), "-o", str(tmp / "exists.npy")]  # fmt: skip
    assert main(dub) != 0 and (tmp / "exists.npy").read_bytes() == b"keep"
    assert "already exists" in capsys.readouterr().err
