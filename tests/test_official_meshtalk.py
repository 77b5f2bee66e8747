"""MeshTalk imported from its released files computes what the official code computes.

The fixture (tests/fixtures/official/meshtalk/) is the official MeshTalk at a tiny size with
random weights, saved as its ``Net.save`` does, and the official outputs of ``animate_face.py``'s
steps on speech.wav (argmax codes, and Gumbel draws under ``torch.manual_seed``); it is made by
``scripts/make_official_fixtures.py --official PATH`` from a local checkout of the official code.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from talkmesh.audio.loading import load_audio
from talkmesh.cli import main
from talkmesh.errors import TalkmeshError
from talkmesh.models.mel import MelAudioEncoder, MelConfig
from talkmesh.models.official import import_checkpoint
from talkmesh.models.release import load_model

OFFICIAL = Path(__file__).parent / "fixtures" / "official"
FIXTURE = OFFICIAL / "meshtalk"
TOLERANCE = 1e-4  # of the motion's scale
RELEASE = [FIXTURE / f"{n}.pkl" for n in ("encoder", "context_model", "vertex_unet")]
MASKS = [FIXTURE / "forehead_mask.txt", FIXTURE / "neck_mask.txt"]


@pytest.fixture(scope="module")
def fx() -> dict[str, np.ndarray]:
    with np.load(FIXTURE / "meshtalk.npz", allow_pickle=False) as f:
        return {k: f[k] for k in f.files}


@pytest.fixture(scope="module")
def model():
    return import_checkpoint([FIXTURE], "meshtalk", "meshtalk")


@pytest.fixture(scope="module")
def audio() -> torch.Tensor:
    return torch.from_numpy(load_audio(OFFICIAL / "speech.wav"))[None]


@pytest.mark.parametrize("mode", ["argmax", "gumbel"])
def test_generation_equals_the_official_demo(model, fx, audio, mode):
    template = torch.from_numpy(fx["template"])[None]
    seed = int(fx["sample_seed"])
    codes = model.sample_codes(audio, seed=seed, argmax=mode == "argmax")[0].numpy()
    np.testing.assert_array_equal(codes, fx[f"{mode}_codes"])  # the same categorical draws
    out = model.generate(audio, template, seed=seed, argmax=mode == "argmax")[0].numpy()
    ref = fx[f"{mode}_smoothed"]
    assert out.shape == ref.shape  # same frame count
    scale = np.abs(ref - fx["template"]).max()
    assert np.ptp(ref, axis=0).max() > 0.1 * scale  # the official output moves over time
    assert np.abs(out - ref).max() / scale <= TOLERANCE


def test_prior_encoder_and_cached_sampling_equal_the_official(model, fx, audio):
    with torch.no_grad():
        features = model.audio_features(audio, None, len(fx["audio_code"]))
        np.testing.assert_allclose(features[0].numpy(), fx["audio_code"], atol=1e-4)
        codes = torch.from_numpy(fx["gumbel_codes"])[None].long()
        logprobs = torch.log_softmax(model.prior(codes, features), -1)[0].numpy()
        np.testing.assert_allclose(logprobs, fx["prior_logprobs"], atol=1e-4)
        template = torch.from_numpy(fx["template"])[None]
        vertices = torch.from_numpy(fx["gumbel_vertices"])[None]
        quantized = model.model.encode(vertices, template, audio, sample=False)
        encoder = torch.log_softmax(quantized.logits, -1)[0].numpy()
        np.testing.assert_allclose(encoder, fx["encoder_logprobs"], atol=1e-4)
        seed = torch.Generator().manual_seed(5)
        fast = model.prior.sample(features, gumbel=True, generator=seed)
        seed = torch.Generator().manual_seed(5)
        slow = model.prior.sample_uncached(features, gumbel=True, generator=seed)
    assert torch.equal(fast, slow)


def test_cli_import_writes_a_release_that_generates_the_same(tmp_path, fx, audio, model):
    out = tmp_path / "meshtalk.safetensors"
    files = [str(p) for p in RELEASE + MASKS]
    assert (
        main(
            [
                "import-checkpoint",
                *files,
                "--family",
                "meshtalk",
                "--dataset",
                "meshtalk",
                "-o",
                str(out),
                "-q",
            ]
        )
        == 0
    )
    loaded = load_model(out)
    template = torch.from_numpy(fx["template"])[None]
    a = loaded.generate(audio, template, seed=2)
    b = model.generate(audio, template, seed=2)
    assert torch.equal(a, b)
    assert loaded.cfg.smoothing == 2 and loaded.cfg.sampling.gumbel


def test_release_parts_are_checked(tmp_path):
    with pytest.raises(TalkmeshError, match="context_model.pkl, vertex_unet.pkl missing"):
        import_checkpoint([RELEASE[0]], "meshtalk", "meshtalk")
    with pytest.raises(TalkmeshError, match="pass both or neither"):
        import_checkpoint([*RELEASE, MASKS[0]], "meshtalk", "meshtalk")
    short = tmp_path / "neck_mask.txt"
    np.savetxt(short, np.ones(5))
    with pytest.raises(TalkmeshError, match="5 values, the model has 24 vertices"):
        import_checkpoint([*RELEASE, MASKS[0], short], "meshtalk", "meshtalk")
    state = torch.load(RELEASE[2], weights_only=True)
    state["decoder.2.weight"] = state["decoder.2.weight"][:, :3]
    bad = tmp_path / "vertex_unet.pkl"
    torch.save(state, bad)
    with pytest.raises(TalkmeshError, match="'model.decoder.output.weight' has shape"):
        import_checkpoint([*RELEASE[:2], bad], "meshtalk", "meshtalk")
    state = torch.load(RELEASE[1], weights_only=True)
    state["extra"] = torch.zeros(1)
    bad = tmp_path / "context_model.pkl"
    torch.save(state, bad)
    with pytest.raises(TalkmeshError, match="unexpected tensor 'extra'"):
        import_checkpoint([RELEASE[0], bad, RELEASE[2]], "meshtalk", "meshtalk")
    with pytest.raises(TalkmeshError, match="MeshTalk's own mesh"):
        import_checkpoint([OFFICIAL / "faceformer_vocaset.pth"], "faceformer", "meshtalk")


@pytest.mark.parametrize("samples", [534, 535, 1067, 16000, 20774, 48000])
@pytest.mark.parametrize("fps", [30, 25])
def test_window_frames_are_the_official_chunk_count(samples, fps):
    """``audio_chunking``: anchors range(8000, padded - 8000, 16000 // fps)."""
    hop = 16000 // fps
    pad = (16000 - hop) // 2
    official = len(range(8000, samples + 2 * pad - 8000, hop))
    encoder = MelAudioEncoder(MelConfig(windows=True), fps)
    assert encoder.window_frames(samples) == official


class Payload:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_a_malicious_release_file_never_runs(tmp_path):
    marker = tmp_path / "pwned"
    folder = tmp_path / "pretrained_models"
    folder.mkdir()
    torch.save({"vertex_bias": torch.zeros(3), "x": Payload(marker)}, folder / "vertex_unet.pkl")
    with pytest.raises(TalkmeshError, match="refused"):
        import_checkpoint([folder], "meshtalk", "meshtalk")
    assert not marker.exists()
