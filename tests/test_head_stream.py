"""Head motion of a live stream: causal (the chunking changes nothing), seeded, off at 0, alive
in silence (before the speech and after it), close to the offline motion's size, bounded state."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from talkmesh.audio.loading import load_audio
from talkmesh.face.head_motion import head_pose
from talkmesh.face.head_stream import KEEP_HOPS, HeadMotionStream

CLIP = Path(__file__).parents[1] / "examples" / "librivox-sense-and-sensibility.flac"  # 8.3 s
FPS = 30.0
SR = 16_000


@pytest.fixture(scope="module")
def speech() -> np.ndarray:
    return load_audio(CLIP)


def stream(audio: np.ndarray, chunk: int, *, lag: int = 3, seed: int = 0, amount: float = 0.5):
    """Poses of every frame, asked for as a live session does: after each chunk, the frames
    whose audio (and ``lag`` frames more) has arrived; the rest at the end."""
    motion = HeadMotionStream(FPS, amount=amount, seed=seed)
    total = int(len(audio) / SR * FPS)
    out, done = [], 0
    for i in range(0, len(audio), chunk):
        motion.receive(audio[i : i + chunk])
        ready = min(total, int((i + chunk) / SR * FPS) - lag)
        if ready > done:
            out.append(motion.poses(done, ready))
            done = ready
    out.append(motion.poses(done, total))
    return np.concatenate(out), motion


def test_the_chunking_changes_nothing(speech):
    a, _ = stream(speech, 320)  # 20 ms chunks, as the viewer sends
    b, _ = stream(speech, 7919, lag=10)  # odd half-second chunks, frames asked later
    assert a.shape == (int(len(speech) / SR * FPS), 6)
    np.testing.assert_array_equal(a, b)
    late = HeadMotionStream(FPS)  # every frame asked after all the audio (a server's backlog)
    late.receive(speech)
    np.testing.assert_array_equal(a, late.poses(0, len(a)))


def test_seeded_and_scaled_and_off_at_zero(speech):
    a, _ = stream(speech, 1600, seed=3)
    np.testing.assert_array_equal(a, stream(speech, 1600, seed=3)[0])
    assert not np.array_equal(a, stream(speech, 1600, seed=4)[0])
    lively, _ = stream(speech, 1600, seed=3, amount=1.0)
    np.testing.assert_allclose(lively[:, :3], 2 * a[:, :3], atol=1e-6)
    assert not stream(speech, 1600, amount=0.0)[0].any()


def test_the_head_moves_in_silence_before_and_after_the_speech(speech):
    quiet = np.zeros(5 * SR, np.float32)
    poses, _ = stream(np.concatenate([quiet, speech, quiet]), 320)
    n = int(5 * FPS)
    for part in (poses[:n], poses[-n:]):  # 5 s before the speech, 5 s after
        degrees = np.degrees(part[:, :3])
        assert np.ptp(degrees, axis=0).min() > 0.05  # sway on every axis
        assert np.ptp(degrees[:, 0]) > 0.3  # breathing tips the head back
        assert np.ptp(part[:, 4]) > 3e-4  # ... and lifts it


def test_size_and_speed_are_the_offline_motions_within_a_factor_of_two(speech):
    live, motion = stream(speech, 320)
    offline = head_pose(speech, len(live), FPS)
    for poses in (live, offline):
        assert np.isfinite(poses).all()
    live_std, offline_std = (np.degrees(p[:, :3]).std(axis=0).sum() for p in (live, offline))
    assert 0.5 < live_std / offline_std < 2.0, (live_std, offline_std)
    speed = [np.abs(np.diff(np.degrees(p[:, 0]))).mean() for p in (live, offline)]
    assert 0.5 < speed[0] / speed[1] < 2.0, speed


def test_state_stays_bounded_over_a_long_stream(speech):
    motion = HeadMotionStream(FPS)
    done = 0
    minute = np.tile(speech, 8)
    for i in range(0, len(minute), 3200):  # 200 ms chunks, the frames asked as they come
        motion.receive(minute[i : i + 3200])
        ready = int(motion.hops * 0.01 * FPS) - 3
        motion.poses(done, ready)
        done = ready
    assert motion.history.shape == (KEEP_HOPS, 2)
    assert len(motion.nods) <= 3 and len(motion.breaths) <= 3 and len(motion.shifts) <= 2
    assert len(motion.knots) <= 65


def test_a_live_minute_of_silence_blinks_and_moves():
    """What a ``talkmesh serve`` session streams once its audio stops (silence in the client's
    place, talkmesh.serve.session): the procedural streamer's blinks at a resting rate (people
    blink about 10-20 times a minute, lipsync.SpeakingStyle), gaze shifts, and a head that moves
    on every axis in every 5 s."""
    from talkmesh.serve.stream import open_stream

    streamer = open_stream("procedural", lookahead_ms=100)
    motion = HeadMotionStream(FPS)
    silence = np.zeros(60 * SR, np.float32)
    frames, poses = [], []
    for i in range(0, len(silence), SR // 5):  # 200 ms pieces, as the server's idle silence
        motion.receive(silence[i : i + SR // 5])
        new = streamer.push(silence[i : i + SR // 5])
        if new:
            poses.append(motion.poses(new[0].index, new[-1].index + 1))
        frames += new
    weights = np.stack([f.weights for f in frames])
    blink = weights[:, streamer.names.index("eyeBlinkLeft")]
    rate = (np.diff((blink > 0.5).astype(int)) == 1).sum() / (len(frames) / FPS / 60)
    assert 8 <= rate <= 30, rate
    look = weights[:, streamer.names.index("eyeLookUpLeft")]
    assert np.ptp(look - weights[:, streamer.names.index("eyeLookDownLeft")]) > 0.05
    degrees = np.degrees(np.concatenate(poses)[:, :3])
    window = int(5 * FPS)
    for start in range(0, len(degrees) - window + 1, window):
        assert np.ptp(degrees[start : start + window], axis=0).min() > 0.02, start
