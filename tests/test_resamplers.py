"""The official codes' resamplers (talkmesh.audio.resamplers) against the official libraries
themselves: tests/fixtures/resample_reference.npz holds torchaudio's ``resample`` (MeshTalk) and
``librosa.load(sr=16000, res_type="kaiser_best")`` (FaceFormer, CodeTalker: resampy), made by
scripts/make_resample_fixtures.py from the signal below; imported official models read audio
through them, our own models through the polyphase filter."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from talkmesh.audio.loading import load_audio, resample, save_wav
from talkmesh.audio.resamplers import KAISER_BEST, RESAMPLERS, SINC_HANN, resample_with
from talkmesh.errors import TalkmeshError

REFERENCE = Path(__file__).parent / "fixtures" / "resample_reference.npz"
RATES = (22050, 44100, 48000)
SECONDS = 0.15  # scripts/make_resample_fixtures.py: SECONDS


def signal_for(sr: int, seconds: float = SECONDS) -> np.ndarray:
    """scripts/make_resample_fixtures.py's signal_for: a tone, a tone near 8 kHz and a chirp to
    the input's Nyquist frequency."""
    t = np.arange(round(sr * seconds)) / sr
    chirp = np.sin(2 * np.pi * (100 * t + (sr / 2 - 100) / (2 * seconds) * t**2))
    return 0.4 * np.sin(2 * np.pi * 440 * t) + 0.2 * np.sin(2 * np.pi * 7600 * t) + 0.3 * chirp


def _wav(tmp_path: Path, sr: int) -> Path:
    path = tmp_path / f"{sr}.wav"
    save_wav(path, signal_for(sr).astype(np.float32), sr)
    return path


@pytest.mark.parametrize("sr", RATES)
@pytest.mark.parametrize("method", [SINC_HANN, KAISER_BEST])
def test_official_resamplers_equal_the_official_libraries(tmp_path, sr, method):
    reference = np.load(REFERENCE)[f"{method}_{sr}"]
    ours = load_audio(_wav(tmp_path, sr), resampler=method)
    assert ours.shape == reference.shape
    np.testing.assert_allclose(ours, reference, atol=1e-4, rtol=0)
    # the polyphase filter is a different filter: the check can tell them apart
    other = load_audio(_wav(tmp_path, sr))
    assert other.shape == reference.shape and np.abs(other - reference).max() > 1e-3


def test_resample_takes_every_method_and_refuses_others():
    x = signal_for(44100).astype(np.float32)
    for method in RESAMPLERS:
        assert resample(x, 44100, 16000, method).shape == (2400,)
    assert np.array_equal(resample_with(x, 16000, 16000, SINC_HANN), x)
    with pytest.raises(ValueError, match="unknown resampler"):
        resample(x, 44100, 16000, "linear")
    with pytest.raises(ValueError, match="unknown resampler"):
        load_audio(REFERENCE, resampler="linear")  # checked before anything is read


def test_upsampling_and_odd_lengths_follow_the_formulas():
    """8 kHz up to 16 kHz (both wings over 1 input sample per zero crossing) keeps a tone."""
    t = np.arange(801) / 8000
    x = (0.5 * np.sin(2 * np.pi * 300 * t)).astype(np.float32)
    want = 0.5 * np.sin(2 * np.pi * 300 * np.arange(1602) / 16000)
    for method in (SINC_HANN, KAISER_BEST):
        y = resample_with(x, 8000, 16000, method)
        assert y.shape == (1602,)
        np.testing.assert_allclose(y[400:1200], want[400:1200], atol=2e-3)


def _imported_like(tiny_codetalker, family_resample: str):
    from talkmesh.models.speech import SpeechEncoderConfig
    from tests.fixtures import TINY_WAV2VEC2

    speech = SpeechEncoderConfig(
        kind="wav2vec2", dim=16, hf_config=TINY_WAV2VEC2, resample=family_resample
    )
    return tiny_codetalker(speech=speech)


def test_models_name_their_resampler(tiny_codetalker):
    from dataclasses import replace

    from talkmesh.models.faceformer import FaceFormer
    from talkmesh.models.meshtalk.model import MeshTalkModel
    from tests.fixtures import TINY_WAV2VEC2

    assert tiny_codetalker().resampler == "polyphase"  # our own models: the fast filter
    assert _imported_like(tiny_codetalker, "cnn").resampler == KAISER_BEST
    cfg = FaceFormer.tiny_config()
    assert FaceFormer(cfg).resampler == "polyphase"
    speech = replace(cfg.speech, resample="cnn", kind="wav2vec2", hf_config=TINY_WAV2VEC2)
    official = replace(cfg, speech=speech)
    assert FaceFormer(official).resampler == KAISER_BEST
    cfg = MeshTalkModel.tiny_config()
    assert MeshTalkModel(cfg).resampler == "polyphase"
    official = replace(cfg, model=replace(cfg.model, official_decoder=True))
    assert MeshTalkModel(official).resampler == SINC_HANN


def test_animate_reads_a_file_with_an_imported_models_resampler(tmp_path, tiny_codetalker):
    from talkmesh.face.assets import plain_head
    from talkmesh.pipeline import animate

    net = _imported_like(tiny_codetalker, "cnn")
    rng = np.random.default_rng(0)
    head = plain_head(rng.normal(size=(net.num_vertices, 3)), np.array([[0, 1, 2]]), "tiny")
    path = tmp_path / "speech.wav"
    sr = 44100
    save_wav(path, (signal_for(sr, 0.6) * 0.8).astype(np.float32), sr)
    with torch.inference_mode():
        from_file = animate(path, model=net, head=head, blinks=False).vertices
        official = animate(load_audio(path, resampler=KAISER_BEST), model=net, head=head).vertices
        polyphase = animate(load_audio(path), model=net, head=head).vertices
    np.testing.assert_array_equal(from_file, official)
    assert np.abs(from_file - polyphase).max() > 0


def test_a_missing_file_is_a_one_line_error_whatever_the_resampler(tmp_path):
    with pytest.raises(TalkmeshError, match="not found"):
        load_audio(tmp_path / "none.wav", resampler=KAISER_BEST)
