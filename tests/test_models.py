"""The model interface (talkmesh.models.base) and the family registry, for every family."""

from __future__ import annotations

import inspect
import subprocess
import sys

import pytest
import torch

from talkmesh.config import to_dict
from talkmesh.errors import TalkmeshError
from talkmesh.models.base import FrameStream, MotionModel
from talkmesh.models.registry import FAMILIES
from talkmesh.models.release import load_model, save_model

V = 30
SR = 16_000
ALL = sorted(FAMILIES)


def build(family: str) -> MotionModel:
    cls = FAMILIES[family]
    torch.manual_seed(0)
    model = cls(cls.tiny_config(num_vertices=V)).eval()
    with torch.no_grad():  # random weights everywhere, so zero-initialised maps move the mesh
        for p in model.parameters():
            p.add_(torch.randn(p.shape) * 0.05)
    return model


def test_the_four_papers_are_registered():
    assert set(FAMILIES) == {"codetalker", "faceformer", "voca", "meshtalk"}


def test_a_family_is_imported_when_asked_for(tmp_path):
    """The registry names each family's folder; loading a release imports that folder alone."""
    path = save_model(build("voca"), tmp_path / "voca.safetensors")
    code = (
        "import sys\n"
        "from talkmesh.models.release import load_model\n"
        "from talkmesh.models.registry import FAMILIES\n"
        "assert 'codetalker' in FAMILIES and len(FAMILIES) == 4\n"
        "assert not [m for m in sys.modules if m.startswith('talkmesh.models.voca')]\n"
        f"load_model({str(path)!r})\n"
        "loaded = {m.split('.')[2] for m in sys.modules if m.count('.') >= 2\n"
        "          and m.startswith('talkmesh.models.') and m.split('.')[2] in FAMILIES}\n"
        "assert loaded == {'voca'}, loaded\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize("family", ALL)
def test_every_family_implements_the_interface(family):
    cls = FAMILIES[family]
    assert issubclass(cls, MotionModel) and cls.family == family
    assert not inspect.isabstract(cls), inspect.getmembers(cls)
    model = build(family)
    assert isinstance(model.cfg, cls.config_class)
    assert model.num_vertices == V and model.motion_fps > 0
    assert isinstance(model.styles, tuple)
    assert model.generation_modes and model.generation_modes[0] == "fast"
    # generate: (B, S) audio + (B, V, 3) template -> (B, T, V, 3), T from the audio's duration
    audio = torch.randn(2, SR) * 0.1
    template = torch.randn(2, V, 3)
    K = len(model.styles)
    weights = torch.full((2, K), 1.0 / K) if K else None
    out = model.generate(audio, template, style_weights=weights, seed=0)
    assert out.shape == (2, round(model.motion_fps), V, 3)
    assert torch.isfinite(out).all()
    assert not torch.allclose(out, template[:, None].expand_as(out))  # the face moves
    for mode in model.generation_modes:
        again = model.generate(audio, template, style_weights=weights, num_frames=7, mode=mode)
        assert again.shape == (2, 7, V, 3)
    with pytest.raises(TalkmeshError, match="mode"):
        model.generate(audio, template, style_weights=weights, mode="no-such-mode")


@pytest.mark.parametrize("family", ALL)
def test_release_round_trip_through_the_registry(family, tmp_path):
    model = build(family)
    path = save_model(model, tmp_path / f"{family}.safetensors")
    loaded = load_model(path, family=family)
    assert type(loaded) is type(model)
    assert to_dict(loaded.cfg) == to_dict(model.cfg)
    a, b = model.state_dict(), loaded.state_dict()
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)
    audio, template = torch.randn(1, SR // 2) * 0.1, torch.randn(1, V, 3)
    K = len(model.styles)
    weights = torch.full((1, K), 1.0 / K) if K else None
    torch.testing.assert_close(
        loaded.generate(audio, template, style_weights=weights, seed=3),
        model.generate(audio, template, style_weights=weights, seed=3),
    )


@pytest.mark.parametrize("family", ALL)
def test_optional_verbs_work_or_say_what_is_missing_in_one_line(family):
    model = build(family)
    vertices, template = torch.randn(1, 6, V, 3), torch.randn(1, V, 3)
    for verb in (
        lambda: model.reconstruct(vertices, template),
        lambda: model.motion_codes(vertices, template),
        lambda: model.int8_copy("all"),
    ):
        try:
            verb()
        except TalkmeshError as e:
            assert "\n" not in str(e) and family in str(e)
    try:
        stream = model.open_frame_stream(None, None)
    except TalkmeshError as e:
        assert "cannot stream" in str(e)
    else:
        assert isinstance(stream, FrameStream)


def test_codetalker_reconstructs_and_codes_through_its_vq_vae():
    model = build("codetalker")
    vertices, template = torch.randn(1, 6, V, 3), torch.randn(1, V, 3)
    with torch.no_grad():
        recon = model.reconstruct(vertices, template)
        codes = model.motion_codes(vertices, template)
        expected = model.vqvae((vertices - template[:, None]).flatten(2))
    assert recon.shape == vertices.shape
    torch.testing.assert_close(recon, expected.motion.reshape(1, 6, V, 3) + template[:, None])
    assert torch.equal(codes, expected.codes)
    assert int(codes.max()) < model.codebook_size


def test_only_registered_families_are_released(tmp_path):
    with pytest.raises(TalkmeshError, match="cannot release"):
        save_model(torch.nn.Linear(2, 2), tmp_path / "x.safetensors")


def test_attention_bias_rows_are_aligned_for_cuda_kernels():
    """A generation step's bias row is a slice that starts anywhere in memory; CUDA's
    memory-efficient attention fails on it ("misaligned address"), so it is re-laid out."""
    import torch.nn.functional as F

    from talkmesh.models.layers import aligned_mask, padded_rows

    full = torch.randn(1, 4, 13, 13)
    row = full[:, :, 5:6, :6]  # step 5's row, 6 keys
    assert row.storage_offset() % 8 != 0
    out = padded_rows(row)
    assert torch.equal(out, row)
    assert out.storage_offset() == 0 and out.data_ptr() % 16 == 0
    assert out.stride(-1) == 1 and out.stride(-2) % 8 == 0
    q, k, v = torch.randn(1, 4, 1, 8), torch.randn(1, 4, 6, 8), torch.randn(1, 4, 6, 8)
    assert torch.allclose(
        F.scaled_dot_product_attention(q, k, v, attn_mask=out),
        F.scaled_dot_product_attention(q, k, v, attn_mask=row),
    )
    assert aligned_mask(row) is row  # the CPU kernels read any layout
    assert aligned_mask(None) is None


def test_no_random_init_leaves_the_draws_out_and_puts_them_back():
    """load_model builds a model without torch.nn.init's random draws (its weights are loaded
    next, strict): inside, a fresh tensor is not drawn; after, even on an error, the draws are
    torch's own again."""
    from torch import nn

    from talkmesh.models.release import RANDOM_INITS, no_random_init

    before = {name: getattr(nn.init, name) for name in RANDOM_INITS}
    with pytest.raises(RuntimeError, match="in the middle"):
        with no_random_init():
            zeros = torch.zeros(64)
            assert nn.init.uniform_(zeros, 1.0, 2.0) is zeros and not zeros.any()
            raise RuntimeError("in the middle")
    assert {name: getattr(nn.init, name) for name in RANDOM_INITS} == before
    assert nn.init.uniform_(torch.zeros(64), 1.0, 2.0).min() >= 1.0
