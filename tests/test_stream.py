"""Streaming: chunked audio in, frames out, equal to offline generation where it claims to be."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
import torch

from talkmesh.audio.loading import load_audio
from talkmesh.audio.phonemes import recognize_phones
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.face.assets import Head, load_head
from talkmesh.face.lipsync import phones_to_weights
from talkmesh.serve.stream import open_stream, push_together

SR = 16_000
V = 20
JAW = list(ARKIT_NAMES).index("jawOpen")


def tiny_head() -> Head:
    rng = np.random.default_rng(0)
    return Head(
        name="tiny",
        template=rng.normal(size=(V, 3)).astype(np.float32),
        faces=np.array([[0, 1, 2]], np.int32),
        blendshapes=(rng.normal(size=(52, V, 3)) * 0.01).astype(np.float32),
        blendshape_names=tuple(ARKIT_NAMES),
        regions=None,  # the streamers do not read regions
    )


def stream_all(streamer, audio: np.ndarray, chunks: list[int]):
    frames, i, k = [], 0, 0
    while i < len(audio):
        n = chunks[k % len(chunks)]
        frames += streamer.push(audio[i : i + n])
        i, k = i + n, k + 1
    return frames + streamer.flush()


@pytest.mark.parametrize("lookahead", [0.0, 50.0, 200.0])
def test_codetalker_stream_equals_offline_generation(tmp_path, lookahead, tiny_stream_model):
    from talkmesh.models.release import load_model

    path = tiny_stream_model()
    head = tiny_head()
    audio = np.random.default_rng(1).normal(0, 0.1, int(1.9 * SR)).astype(np.float32)
    # chunks of 10 ms to 200 ms, as a microphone sends them
    stream = open_stream(path, lookahead_ms=lookahead, head=head, offsets=True, blinks=False)
    frames = stream_all(stream, audio, [160, 3200, 800, 1600, 480])
    assert [f.index for f in frames] == list(range(57))  # 1.9 s at 30 fps
    net = load_model(path)
    net.speech.set_lookahead(lookahead)
    offline = (
        net.generate(
            torch.from_numpy(audio)[None],
            torch.from_numpy(head.template)[None],
            style_weights=torch.tensor([[0.5, 0.5]]),
        )[0].numpy()
        - head.template
    )
    streamed = np.stack([f.offsets for f in frames])
    np.testing.assert_allclose(streamed, offline, atol=2e-5)
    assert np.abs(offline[1:] - offline[:-1]).max() > 1e-3  # not a constant output
    weights = np.stack([f.weights for f in frames])
    assert weights.shape == (57, 52) and weights.min() >= 0 and weights.max() <= 1


def test_codetalker_stream_replaces_the_models_eye_motion_with_procedural_eyes(
    tmp_path, tiny_stream_model
):
    from talkmesh.face.lipsync import BLINK_GAZE, INDEX, SpeakingStyle
    from talkmesh.serve.stream import UpperFace

    path, head = tiny_stream_model(), tiny_head()
    audio = np.random.default_rng(3).normal(0, 0.1, 4 * SR).astype(np.float32)
    plain = stream_all(open_stream(path, head=head, offsets=True, blinks=False), audio, [1600])
    eyed = stream_all(open_stream(path, head=head, offsets=True, seed=5), audio, [1600])
    wp, we = (np.stack([f.weights for f in fs]) for fs in (plain, eyed))
    keep = [INDEX[n] for n in BLINK_GAZE]
    other = [i for i in range(52) if i not in keep]
    procedural = UpperFace(30.0, 5, SpeakingStyle(), keep)(0, len(we))
    assert procedural[:, keep].max() > 0.5  # a blink in these 4 s
    np.testing.assert_allclose(we[:, keep], procedural[:, keep])  # replaced, not added to
    np.testing.assert_allclose(we[:, other], wp[:, other])
    basis = head.blendshapes.reshape(52, -1)[keep]
    moved = np.stack([f.offsets for f in eyed]) - np.stack([f.offsets for f in plain])
    np.testing.assert_allclose(moved.reshape(len(we), -1), (we - wp)[:, keep] @ basis, atol=1e-5)


def test_stream_waits_for_its_lookahead_and_lookahead_changes_the_output(
    tmp_path, tiny_stream_model
):
    path = tiny_stream_model()
    head = tiny_head()
    audio = np.random.default_rng(2).normal(0, 0.1, SR).astype(np.float32)
    early = open_stream(path, lookahead_ms=0, head=head, offsets=True, blinks=False)
    late = open_stream(path, lookahead_ms=200, head=head, offsets=True, blinks=False)
    got_early, got_late = early.push(audio[: SR // 2]), late.push(audio[: SR // 2])
    # 0.5 s received: frames up to (0.5 s - look-ahead - the 25 ms mel window) are out
    assert got_early[-1].time <= 0.5 - 0.025 and got_early[-1].time > 0.5 - 0.1
    assert got_late[-1].time <= 0.5 - 0.225 and got_late[-1].time > 0.5 - 0.3
    a = np.stack([f.offsets for f in got_early[: len(got_late)]])
    b = np.stack([f.offsets for f in got_late])
    assert not np.allclose(a, b)


def test_procedural_stream_follows_the_offline_lip_sync(tmp_path):
    wav = tmp_path / "s.wav"
    subprocess.run(
        ["espeak-ng", "-v", "en-us", "-w", str(wav), "Bob bought a big blue map above the bay."],
        check=True,
    )
    audio = load_audio(tmp_path / "s.wav")
    stream = open_stream("procedural", lookahead_ms=100)
    frames = stream_all(stream, audio, [320])  # 20 ms chunks
    n = max(1, round(len(audio) / SR * 30))
    assert [f.index for f in frames] == list(range(n))
    live = np.stack([f.weights for f in frames])[:, JAW]
    offline = phones_to_weights(recognize_phones(audio), n, 30.0)[:, JAW]
    r = np.corrcoef(live, offline)[0, 1]
    print(f"jawOpen: streamed vs offline r = {r:.3f}")
    assert live.max() > 0.1 and r > 0.6


def test_procedural_stream_state_stays_bounded_over_long_audio():
    rng = np.random.default_rng(3)
    stream = open_stream("procedural", lookahead_ms=0, offsets=True)
    head = load_head()
    total = 0
    for _ in range(50):  # 50 s of noise bursts and pauses, in 1 s pushes
        chunk = np.where(rng.random(SR) < 0.5, rng.normal(0, 0.2, SR), 0).astype(np.float32)
        frames = stream.push(chunk)
        total += len(frames)
    assert stream.utt_samples <= 20 * SR  # the recogniser restarted
    assert len(stream.past) < 200  # only the last seconds of phones are kept
    assert total >= 49 * 30 and frames[-1].offsets.shape == (head.num_vertices, 3)


def test_stream_errors(tmp_path, tiny_stream_model):
    with pytest.raises(TalkmeshError, match="look-ahead"):
        open_stream("procedural", lookahead_ms=400)
    with pytest.raises(TalkmeshError, match="unknown streaming model"):
        open_stream("nonexistent.safetensors")
    head = tiny_head()
    with pytest.raises(TalkmeshError, match="cannot stream"):
        open_stream(tiny_stream_model(causal=False), head=head)
    with pytest.raises(TalkmeshError, match="outside what this model was trained for"):
        open_stream(tiny_stream_model(), lookahead_ms=250, head=head)
    stream = open_stream("procedural")
    with pytest.raises(TalkmeshError, match="1-D"):
        stream.push(np.zeros((2, 160), np.float32))
    with pytest.raises(TalkmeshError, match="float or int16"):
        stream.push(np.zeros(160, np.int64))
    assert len(stream.push(np.zeros(160, np.int16))) == 0
    assert len(stream.flush()) == 1  # 10 ms of audio: one frame
    with pytest.raises(TalkmeshError, match="flushed"):
        stream.push(np.zeros(160, np.float32))


@pytest.mark.parametrize("offsets", [True, False])  # False: the model projects onto the basis
def test_streams_pushed_together_get_the_frames_they_get_alone(
    tmp_path, monkeypatch, offsets, tiny_stream_model
):
    from talkmesh.models.codetalker.batch import FrameBatch

    path, head = tiny_stream_model(), tiny_head()
    rng = np.random.default_rng(3)
    audios = [rng.normal(0, 0.1, int(s * SR)).astype(np.float32) for s in (1.5, 0.9, 1.2)]
    chunkings = [[320, 1600], [480], [3200, 160, 800]]

    def open_all():
        streams = [
            open_stream(path, lookahead_ms=la, head=head, offsets=offsets, seed=k)
            for k, la in enumerate((0.0, 100.0, 200.0))
        ]
        return [*streams, open_stream("procedural", head=head, seed=3)]

    alone = [
        stream_all(s, a, c)
        for s, a, c in zip(open_all(), [*audios, audios[0]], [*chunkings, [320]])
    ]
    sizes = []
    step = FrameBatch.step
    monkeypatch.setattr(
        FrameBatch, "step", lambda self, r, basis=None: sizes.append(len(r)) or step(self, r, basis)
    )
    streams = open_all()
    together = [[] for _ in streams]
    ticks = [[] for _ in streams]  # each stream's chunks, dealt out to ticks of 100 ms
    for k, (audio, chunks) in enumerate(zip([*audios, audios[0]], [*chunkings, [320]])):
        i, n = 0, 0
        while i < len(audio):
            size = chunks[n % len(chunks)]
            tick = int(i / (SR / 10))
            ticks[k] += [[] for _ in range(tick + 1 - len(ticks[k]))]
            ticks[k][tick].append(audio[i : i + size])
            i, n = i + size, n + 1
    for tick in range(max(map(len, ticks)) + 1):
        work = [
            (s, ticks[k][tick] if tick < len(ticks[k]) else [], tick == len(ticks[k]) - 1)
            for k, s in enumerate(streams)
            if tick < len(ticks[k])
        ]
        for (s, _, _), frames in zip(work, push_together(work)):
            together[streams.index(s)] += frames
    assert max(sizes) == 3  # the model's three streams stepped together
    for a, b in zip(alone, together):
        assert [f.index for f in a] == [f.index for f in b]
        np.testing.assert_allclose(
            np.stack([f.weights for f in b]), np.stack([f.weights for f in a]), atol=1e-4
        )
        if a[0].offsets is not None:
            np.testing.assert_allclose(
                np.stack([f.offsets for f in b]), np.stack([f.offsets for f in a]), atol=1e-5
            )


def test_a_recogniser_from_the_pool_recognises_as_a_new_one():
    """A server makes its sessions' recognisers up front and takes a closed session's back
    (DecoderPool): the next session on it must get the frames of a fresh recogniser, even when
    the previous one was dropped in the middle of an utterance."""
    from talkmesh.serve.stream import DecoderPool

    librivox = "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb"
    clip = np.concatenate([load_audio(f"{librivox}-{k}.wav") for k in ("0870", "0880")])
    fresh = np.stack([f.weights for f in stream_all(open_stream(lookahead_ms=50), clip, [320])])
    pool = DecoderPool()
    first = open_stream(lookahead_ms=50, decoders=pool)
    first.push(clip[: 3 * SR][::-1].copy())  # other speech, then dropped mid-utterance
    first.release()
    assert len(pool.spares) == 1
    with pytest.raises(TalkmeshError, match="open a new one"):
        first.push(clip[:320])
    again = open_stream(lookahead_ms=50, decoders=pool)
    assert not pool.spares  # it took the released recogniser
    reused = np.stack([f.weights for f in stream_all(again, clip, [320])])
    np.testing.assert_array_equal(reused, fresh)
