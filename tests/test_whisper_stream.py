"""The bundled CodeTalker (Whisper speech encoder, causal VQ decoder) streams: its Whisper
features a block of frames at a time (talkmesh.models.whisper_stream)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from talkmesh.audio.loading import SAMPLE_RATE, load_audio
from talkmesh.errors import TalkmeshError
from talkmesh.face.assets import lip_opening, load_head
from talkmesh.models.codetalker.generate import generate_streamed
from talkmesh.models.release import load_model
from talkmesh.models.whisper import ENCODER_HOP
from talkmesh.models.whisper_stream import WhisperFeatureStream, streamed_features
from talkmesh.pipeline import available_models
from talkmesh.serve.stream import open_stream, push_together

CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)  # 3.0 s, "he was not an ill disposed young man"

pytestmark = pytest.mark.skipif(
    "codetalker-synth" not in available_models(), reason="the bundled CodeTalker is not installed"
)


@pytest.fixture(scope="module")
def model():
    return load_model("codetalker-synth").eval()


@pytest.fixture(scope="module")
def wave() -> np.ndarray:
    return load_audio(CLIP)


def _stream(wave: np.ndarray, pushes: list[int], lookahead_ms: float | None) -> tuple:
    """(lip openings (T,) in mm, vertex offsets (T, V, 3), the streamer) of ``wave`` pushed in
    pieces of the given sizes (cycled), then flushed."""
    head = load_head()
    stream = open_stream(
        "codetalker-synth", lookahead_ms=lookahead_ms, head=head, offsets=True, blinks=False
    )
    frames, i, k = [], 0, 0
    while i < len(wave):
        n = pushes[k % len(pushes)]
        got = stream.push(wave[i : i + n])
        i, k = i + n, k + 1
        for f in got:  # no frame before the audio its block reads has arrived
            assert stream.stream.audio_needed(f.index) <= min(i, len(wave))
        frames += got
    frames += stream.flush()
    assert [f.index for f in frames] == list(range(len(frames)))
    offsets = np.stack([f.offsets for f in frames])
    return lip_opening(head.template + offsets, head.regions) * 1000.0, offsets, stream


def test_the_stream_is_its_offline_features_whatever_the_pushes(model, wave):
    """20 ms pushes and uneven ones give the same frames, and they are generate_streamed's:
    the model's steps on the features of streamed_features."""
    small, offsets, stream = _stream(wave, [320], 200.0)
    uneven, _, _ = _stream(wave, [5000, 17, 2400, 800], 200.0)
    np.testing.assert_allclose(small, uneven, atol=1e-4)
    head = load_head()
    offline = generate_streamed(model, wave, head.template, 200.0)
    assert offline.shape[0] == len(offsets) == round(len(wave) / SAMPLE_RATE * 30)
    np.testing.assert_allclose(small, lip_opening(offline, head.regions) * 1000.0, atol=1e-3)
    # the mouth moves with the speech: opens by several millimetres, and more than at rest
    assert small.max() - small.min() > 5.0
    # what a client is told it waits for: the look-ahead and the rest of a 3-frame block
    assert stream.lookahead_ms == pytest.approx(200.0 + 2000.0 / 30)


def test_with_enough_look_ahead_the_stream_follows_the_offline_model(model, wave):
    """The features of a 300 ms look-ahead move the lips as the whole-audio features do:
    within a millimetre over most frames (the default look-ahead)."""
    streamed, _, stream = _stream(wave, [320], None)
    assert stream.lookahead_ms == pytest.approx(300.0 + 2000.0 / 30)
    head = load_head()
    with torch.inference_mode():
        uniform = torch.full((1, len(model.styles)), 1.0 / len(model.styles))
        whole = model.generate(
            torch.from_numpy(wave)[None],
            torch.from_numpy(head.template)[None],
            style_weights=uniform,
        )[0].numpy()
    offline = lip_opening(whole, head.regions) * 1000.0
    assert np.median(np.abs(streamed - offline)) < 1.0
    assert np.corrcoef(streamed, offline)[0, 1] > 0.9


def test_each_block_reads_its_window_of_audio_and_keeps_a_bounded_buffer(model, wave):
    """A block's window ends at its last frame plus the look-ahead, starts the context before,
    and the streamer keeps only the audio a later frame still reads."""
    features = WhisperFeatureStream(model.speech, 30.0, 100.0, context_s=1.0, block=3)
    # block 10 is frames 30-32: its window ends 100 ms after frame 32, on a whole feature
    assert features.window_end(10) == (32 * SAMPLE_RATE // 30 + 1600) // ENCODER_HOP * ENCODER_HOP
    assert features.window_start(10) == features.window_end(10) - SAMPLE_RATE
    assert features.first_sample(0) == 0 and features.audio_needed(2) == features.audio_needed(0)
    # a feature depends on its window only: audio before the window changes nothing
    loud = wave.copy()
    loud[: features.first_sample(40)] = 0.5
    a = streamed_features(model.speech, wave, 45, 30.0, 100.0, context_s=1.0)
    b = streamed_features(model.speech, loud, 45, 30.0, 100.0, context_s=1.0)
    torch.testing.assert_close(a[40:], b[40:])
    assert not torch.allclose(a[:3], b[:3])
    _, _, stream = _stream(np.tile(wave, 3), [320], 100.0)  # 9 s
    assert len(stream.buffer) <= 2.2 * SAMPLE_RATE  # context 2 s, a block and a push


def test_bad_look_aheads_get_one_line(model):
    with pytest.raises(TalkmeshError, match="out of range"):
        open_stream("codetalker-synth", lookahead_ms=301.0)
    with pytest.raises(TalkmeshError, match="out of range"):
        WhisperFeatureStream(model.speech, 30.0, -5.0)
    with pytest.raises(TalkmeshError, match="out of range"):
        WhisperFeatureStream(model.speech, 30.0, 100.0, block=0)
    with pytest.raises(TalkmeshError, match="unknown streaming model"):
        open_stream("no-such-model")


def test_streams_pushed_together_encode_their_windows_together(model, wave, monkeypatch):
    """Three streams of one model in the same ticks (what the server does): each gets the frames
    it gets alone, and the Whisper windows that start in the same step go to the encoder in one
    call, not one call per stream."""
    head = load_head()
    voices = [wave, 0.5 * wave[::-1].copy(), np.concatenate([np.zeros(4000, np.float32), wave])]
    alone = [_stream(v, [320], 300.0)[1] for v in voices]
    streams = [
        open_stream("codetalker-synth", lookahead_ms=300.0, head=head, offsets=True, blinks=False)
        for _ in voices
    ]
    features = streams[0].stream.features.features  # the model's WhisperFeatures
    calls: list[int] = []
    encode = features.features
    monkeypatch.setattr(
        features,
        "features",
        lambda audio, lengths=None: calls.append(len(audio)) or encode(audio, lengths),
    )
    got: list[list] = [[] for _ in voices]
    longest = max(len(v) for v in voices)
    for i in range(0, longest, 640):  # ticks of two 20 ms chunks
        work = [
            (s, [v[i : i + 320], v[i + 320 : i + 640]], i + 640 >= len(v))
            for s, v in zip(streams, voices)
            if i < len(v)
        ]
        active = [j for j, v in enumerate(voices) if i < len(v)]
        for j, frames in zip(active, push_together(work)):
            assert not isinstance(frames, TalkmeshError), frames
            got[j] += frames
    for frames, offsets in zip(got, alone):
        together = np.stack([f.offsets for f in frames])
        assert together.shape == offsets.shape
        np.testing.assert_allclose(together, offsets, atol=1e-5)
    windows = sum(-(-len(o) // 3) for o in alone)  # one encoder window a block of 3 frames
    assert sum(calls) == windows and len(calls) < 0.6 * windows, (len(calls), windows)


def test_the_export_streams_what_the_release_streams(model, wave, tmp_path):
    """The bundled model exported to ONNX (its head term and the VQ decoder's face input
    included) streams on ONNX Runtime the frames the release streams (generate_streamed), and
    its frames step together in one batch as they do alone."""
    from talkmesh.models.framestream import FrameRequest, next_frames
    from talkmesh.models.onnx import OnnxModel, export_onnx

    export_onnx(model, tmp_path / "ct.onnx")
    net = OnnxModel(tmp_path / "ct.onnx")
    assert net.has_face
    head = load_head()
    want = generate_streamed(model, wave, head.template, 300.0) - head.template
    # two streams, the second a second behind, stepped together whenever both have a frame due
    streams = [net.open_frame_stream(None, 300.0, head.template) for _ in range(2)]
    late = round(30 * 1.0)
    got: list[list[np.ndarray]] = [[], []]
    for t in range(len(want) + late):
        requests = [
            FrameRequest(s, wave, 0, t - k * late)
            for k, s in enumerate(streams)
            if 0 <= t - k * late < len(want)
        ]
        for r, motion in zip(requests, next_frames(requests)):
            got[streams.index(r.stream)].append(motion.reshape(-1, 3))
    scale = np.abs(want).max()
    for frames in got:
        assert np.abs(np.stack(frames) - want).max() <= 1e-4 * scale
