"""Head motion from prosody: seeded, scaled by --head-motion, off at 0, nodding on pitch accents,
turning about the neck, carried to the outputs and drawn in videos."""

from __future__ import annotations

import numpy as np
import pytest

from talkmesh.audio.phonemes import Phone
from talkmesh.cli import main
from talkmesh.errors import TalkmeshError
from talkmesh.face.head_motion import (
    BREATH_M,
    NATURAL,
    PIVOT,
    head_pose,
    phrase_ends,
    pivot_offset,
    pose_vertices,
    quaternions,
    rotations,
)
from talkmesh.output.render import posed
from talkmesh.pipeline import animate

SR = 16_000


def voice(f0: np.ndarray, seconds: float) -> np.ndarray:
    """A buzzy vowel-like tone following the (S,) F0 curve, with a pause in the middle."""
    t = np.arange(int(seconds * SR)) / SR
    phase = 2 * np.pi * np.cumsum(f0) / SR
    wave = sum(np.sin(k * phase) / k for k in range(1, 12)) * 0.2
    wave[(t > 1.9) & (t < 2.5)] = 0.0
    return wave.astype(np.float32)


def accented(seconds: float = 4.0, at: float = 1.2) -> np.ndarray:
    """Speech-like audio at 110 Hz with one pitch accent (a rise to 160 Hz) at ``at`` s."""
    t = np.arange(int(seconds * SR)) / SR
    f0 = 110 + 50 * np.exp(-(((t - at) / 0.08) ** 2))
    return voice(f0, seconds)


PHONES = [Phone("SIL", 0.0, 0.2), Phone("AA", 0.2, 1.9), Phone("SIL", 1.9, 2.5)]
PHONES += [Phone("IY", 2.5, 4.0)]


def test_seeded_and_scaled_and_off_at_zero():
    wave = accented()
    a = head_pose(wave, 120, 30.0, seed=3)
    assert np.array_equal(a, head_pose(wave, 120, 30.0, seed=3))
    assert not np.array_equal(a, head_pose(wave, 120, 30.0, seed=4))
    lively = head_pose(wave, 120, 30.0, amount=1.0, seed=3)
    np.testing.assert_allclose(lively[:, :3], 2 * a[:, :3], atol=1e-6)  # 1 is twice NATURAL
    assert not head_pose(wave, 120, 30.0, amount=0.0).any()
    assert NATURAL == 0.5


def test_a_pitch_accent_gets_a_nod():
    wave = accented(at=1.2)
    pose = head_pose(wave, 120, 30.0, seed=0)
    pitch = np.degrees(pose[:, 0])
    fast = pitch - np.convolve(np.pad(pitch, 9, mode="edge"), np.ones(19) / 19, "same")[9:-9]
    apex = np.argmax(np.abs(fast)) / 30.0
    assert abs(apex - 1.2) < 0.25, apex
    assert np.abs(fast).max() > 1.0  # a nod of degrees (without nods: 0.7, at the pause)


def test_a_phrase_boundary_is_found_in_the_pause():
    speaking = np.r_[np.ones(30), np.zeros(15), np.ones(30), np.zeros(3), np.ones(10)].astype(bool)
    times = np.arange(len(speaking)) / 30.0
    assert phrase_ends(speaking, times) == [1.0]  # the 0.1 s gap is no boundary


def test_the_head_turns_about_the_neck_and_matches_scipy():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    angles = rng.uniform(-0.3, 0.3, (5, 3))
    pitch, yaw, roll = angles.T
    want = Rotation.from_euler("YXZ", np.stack([yaw, pitch, roll], 1)).as_matrix()
    np.testing.assert_allclose(rotations(angles), want, atol=1e-12)
    np.testing.assert_allclose(
        Rotation.from_quat(quaternions(angles)).as_matrix(), want, atol=1e-12
    )
    pose = np.zeros((5, 6), np.float32)
    pose[:, :3] = angles
    pose[:, 3:] = PIVOT[None] - rotations(angles) @ PIVOT
    moved = pose_vertices(np.repeat(PIVOT[None, None], 5, 0).astype(np.float32), pose)
    np.testing.assert_allclose(moved[:, 0], np.repeat(PIVOT[None], 5, 0), atol=1e-6)


def test_animate_keeps_the_face_and_adds_the_pose():
    wave = accented()
    still = animate(wave, phones=PHONES, model="procedural", head_motion=0.0)
    moving = animate(wave, phones=PHONES, model="procedural")
    assert still.head_pose is None
    assert moving.head_pose.shape == (moving.num_frames, 6) and moving.head_pose.any()
    assert np.array_equal(still.vertices, moving.vertices)  # the face in the head's frame
    t = int(np.argmax(np.abs(moving.head_pose[:, 0])))
    drawn = posed(moving, t)
    assert np.abs(drawn - moving.vertices[t]).max() > 1e-4  # the video shows the head move
    assert np.array_equal(posed(still, t), still.vertices[t])


@pytest.mark.parametrize("amount", [-0.1, 1.5, float("nan")])
def test_out_of_range_amounts_are_one_line(amount):
    with pytest.raises(TalkmeshError, match="--head-motion") as e:
        animate(accented(), phones=PHONES, model="procedural", head_motion=amount)
    assert "\n" not in str(e.value)


def test_cli_refuses_a_bad_amount_before_any_work(tmp_path, capsys):
    speech = tmp_path / "a.wav"
    speech.write_bytes(b"")
    assert main(["animate", str(speech), "-o", str(tmp_path / "a.npz"), "--head-motion", "3"]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "--head-motion 3" in err[0]


def test_the_face_does_not_freeze_when_the_speech_stops():
    # two seconds of speech, then ten of silence: breathing, sway, blinks and gaze go on
    wave = np.concatenate([accented(seconds=2.0, at=1.0), np.zeros(10 * SR, np.float32)])
    phones = [Phone("SIL", 0.0, 0.2), Phone("AA", 0.2, 1.9), Phone("SIL", 1.9, 12.0)]
    anim = animate(wave, phones=phones, model="procedural", seed=1)
    quiet = slice(int(3 * anim.fps), anim.num_frames)
    pose = anim.head_pose[quiet]
    rise = pose[:, 4] - pivot_offset(pose[:, :3])[:, 1]  # the lift, less the turn's share
    breaths = (np.diff((rise > 0.5 * BREATH_M).astype(int)) == 1).sum()
    assert 2 <= breaths <= 4  # a breath about every 4 s
    assert np.degrees(np.ptp(anim.head_pose[quiet, :3], axis=0)).min() > 0.1
    names = anim.weight_names
    blink = anim.weights[quiet, names.index("eyeBlinkLeft")]
    assert (np.diff((blink > 0.5).astype(int)) == 1).sum() >= 1
    gaze = (
        anim.weights[quiet, names.index("eyeLookInLeft")]
        - anim.weights[quiet, names.index("eyeLookOutLeft")]
    )
    assert np.ptp(gaze) > 0.05


def test_cli_writes_the_head_pose_unless_it_is_off(tmp_path):
    from test_cli import CLIP

    wav = tmp_path / "a.wav"
    wav.write_bytes(CLIP.read_bytes())
    files = {}
    for name, extra in (("moving", []), ("still", ["--head-motion", "0"])):
        files[name] = tmp_path / f"{name}.npz"
        argv = ["animate", str(wav), "--model", "procedural", "-o", str(files[name]), "-q"]
        assert main(argv + extra) == 0
    with np.load(files["moving"]) as moving, np.load(files["still"]) as still:
        assert "head_pose" not in still.files
        assert moving["head_pose"].shape == (len(moving["weights"]), 6)
        assert np.degrees(np.ptp(moving["head_pose"][:, :3], axis=0)).min() > 0.5
        np.testing.assert_array_equal(moving["offsets"], still["offsets"])


def blinks_per_minute(blink: np.ndarray, fps: float) -> float:
    """Closures (the lid crossing half-closed) per minute of ``blink`` (T,) eyeBlink weights."""
    return (np.diff((blink > 0.5).astype(int)) == 1).sum() / (len(blink) / fps / 60)


def test_a_minute_of_silence_blinks_at_a_natural_rate_and_the_head_never_stops():
    """After speech, a minute of silence: blinks at a resting rate (people blink about 10-20
    times a minute, lipsync.SpeakingStyle; 8 to 30 allows the renewal process's spread over one
    minute), the eyes shift, and no 5 s of it holds the head still."""
    wave = np.concatenate([accented(seconds=2.0, at=1.0), np.zeros(60 * SR, np.float32)])
    phones = [Phone("SIL", 0.0, 0.2), Phone("AA", 0.2, 1.9), Phone("SIL", 1.9, 62.0)]
    for seed in (0, 1):
        anim = animate(wave, phones=phones, model="procedural", seed=seed)
        quiet = slice(int(2 * anim.fps), anim.num_frames)
        names = anim.weight_names
        rate = blinks_per_minute(anim.weights[quiet, names.index("eyeBlinkLeft")], anim.fps)
        assert 8 <= rate <= 30, (seed, rate)
        degrees = np.degrees(anim.head_pose[quiet, :3])
        window = int(5 * anim.fps)
        for start in range(0, len(degrees) - window + 1, window):
            part = degrees[start : start + window]
            assert np.ptp(part, axis=0).min() > 0.02, (seed, start)  # every axis moves
        look = anim.weights[quiet, names.index("eyeLookUpLeft")]
        look = look - anim.weights[quiet, names.index("eyeLookDownLeft")]
        assert np.ptp(look) > 0.05
