"""Live Link Face UDP packets, read back on 127.0.0.1 by a decoder talkmesh did not write
(``pylivelinkface`` from PyPI)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from pylivelinkface import FaceBlendShape, PyLiveLinkFace
from starlette.testclient import TestClient

from talkmesh.animation import Animation
from talkmesh.cli import main
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES
from talkmesh.output.livelink import (
    LiveLinkSender,
    encode_packet,
    live_link_values,
    parse_target,
    play_live_link,
)
from talkmesh.serve.protocol import decode_frame
from talkmesh.serve.server import create_app

CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)  # 3.0 s of speech


@pytest.fixture
def listener():
    """A UDP socket on 127.0.0.1 standing in for Unreal's Live Link Face source."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(5)
    yield sock
    sock.close()


def receive(sock: socket.socket, n: int) -> list[PyLiveLinkFace]:
    faces = []
    for _ in range(n):
        found, face = PyLiveLinkFace.decode(sock.recv(4096))
        assert found
        faces.append(face)
    return faces


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def small_animation(frames: int = 12, fps: float = 60.0) -> Animation:
    rng = np.random.default_rng(3)
    return Animation(
        vertices=np.zeros((frames, 3, 3)),
        faces=np.array([[0, 1, 2]]),
        fps=fps,
        weights=rng.random((frames, 52)).astype(np.float32),
        weight_names=list(ARKIT_NAMES),
        head_pose=rng.normal(0, 0.1, (frames, 6)).astype(np.float32),
    )


def test_packets_read_back_by_pylivelinkface_carry_the_weights_and_head_pose(listener):
    anim = small_animation()
    target = parse_target(f"127.0.0.1:{listener.getsockname()[1]}")
    with LiveLinkSender(target, "Ada") as sender:
        played = play_live_link(anim, sender)
    faces = receive(listener, anim.num_frames)
    assert played.sent == anim.num_frames and played.refused == 0
    assert [f._frames for f in faces] == list(range(anim.num_frames))  # in order, from 0
    for t, face in enumerate(faces):
        assert face.name == "Ada" and face._version == 6
        assert (face.fps, face._denominator) == (60, 1)
        assert face.uuid == "$" + sender.device_id
        for shape in FaceBlendShape:  # the decoder's own names: no order shared with talkmesh
            if shape.value < 52:
                arkit = shape.name[0].lower() + shape.name[1:]
                want = anim.weights[t, ARKIT_NAMES.index(arkit)]
            else:  # head_pose is pitch, yaw, roll; eyes are not rotated
                rotations = {"HeadYaw": 1, "HeadPitch": 0, "HeadRoll": 2}
                index = rotations.get(shape.name)
                want = 0.0 if index is None else anim.head_pose[t, index] / np.pi
            assert face.get_blendshape(shape) == pytest.approx(want, abs=1e-7), shape


def test_head_rotations_are_half_turns_as_pylivelinkface_reads_them():
    """pylivelinkface documents head rotations between -1 and 1 (Unreal maps -180..180 degrees
    there): a quarter turn of yaw reads 0.5, a 30 degree nod 1/6, never radians."""
    pose = np.zeros((1, 6), np.float32)
    pose[0, :3] = np.radians([30.0, 90.0, -45.0])  # pitch, yaw, roll
    values = live_link_values(np.zeros((1, 52), np.float32), pose)
    face = PyLiveLinkFace.decode(encode_packet(values[0], 0, 30.0, "s", "x" * 36))[1]
    got = [face.get_blendshape(FaceBlendShape[n]) for n in ("HeadYaw", "HeadPitch", "HeadRoll")]
    np.testing.assert_allclose(got, [0.5, 1 / 6, -0.25], atol=1e-6)


def test_without_head_pose_the_rotations_are_zero_and_rates_are_exact():
    values = live_link_values(np.full((2, 52), 0.5, np.float32))
    assert values.shape == (2, 61) and not values[:, 52:].any()
    face = PyLiveLinkFace.decode(encode_packet(values[0], 7, 30000 / 1001, "s", "x" * 36))[1]
    assert (face.fps, face._denominator, face._frames) == (30000, 1001, 7)


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("127.0.0.1:0", "port must be 1 to 65535"),
        ("127.0.0.1:http", "port must be 1 to 65535"),
        (":11111", "give HOST:PORT"),
    ],
)
def test_bad_targets_are_one_line(text, fragment):
    with pytest.raises(TalkmeshError, match=fragment):
        parse_target(text)


def test_a_target_nothing_listens_on_is_refused_and_the_socket_closed():
    sender = LiveLinkSender(parse_target(f"127.0.0.1:{free_udp_port()}"))
    with pytest.raises(TalkmeshError, match="nothing listens there"):
        sender.check()
    assert sender.sock.fileno() == -1


def test_an_unknown_host_is_one_line():
    with pytest.raises(TalkmeshError, match="no such host"):
        LiveLinkSender(parse_target("no-such-host.invalid:11111"))


def test_cli_sends_the_speech_in_order(listener, capsys):
    port = listener.getsockname()[1]
    args = ["livelink", str(CLIP), "--to", f"127.0.0.1:{port}", "--no-audio", "-q"]
    assert main([*args, "--model", "procedural", "--subject", "Lee"]) == 0
    listener.recv(4096)  # the check's rest frame
    faces = receive(listener, 90)  # 3.0 s at 30 fps
    assert [f._frames for f in faces] == list(range(90))
    jaw = np.array([f.get_blendshape(FaceBlendShape.JawOpen) for f in faces])
    assert jaw.max() > 0.2 and {f.name for f in faces} == {"Lee"}
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize(
    "target, fragment",
    [("127.0.0.1:99999", "port must be 1 to 65535"), ("no-such-host.invalid", "no such host")],
)
def test_cli_bad_target_is_one_line_before_any_work(target, fragment):
    res = subprocess.run(
        [sys.executable, "-m", "talkmesh", "livelink", str(CLIP), "--to", target, "--no-audio"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode != 0
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("talkmesh: error:") and fragment in lines[0]


def test_cli_refused_target_is_one_line():
    target = f"127.0.0.1:{free_udp_port()}"
    res = subprocess.run(
        [sys.executable, "-m", "talkmesh", "livelink", str(CLIP), "--to", target, "--no-audio"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode != 0 and "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines() == [
        f"talkmesh: error: Live Link target {target}: nothing listens there (port unreachable); "
        "start Unreal with a Live Link Face source on that port, or give its address"
    ]


def test_serve_sends_each_session_under_its_subject(listener):
    pcm = np.zeros(16000, "<i2").tobytes()  # 1 s of silence: 30 rest frames
    app = create_app(livelink=f"127.0.0.1:{listener.getsockname()[1]}")
    listener.recv(4096)  # the start-up check's rest frame
    with TestClient(app) as client:
        with client.websocket_connect("/ws/stream?livelink=Mia") as ws:
            ws.receive_json()
            ws.send_bytes(pcm)
            ws.send_json({"type": "end"})
            sent = []
            while (message := ws.receive())["type"] != "websocket.close":
                if message.get("bytes") is not None:
                    sent.append(decode_frame(message["bytes"]))
        with client.websocket_connect("/ws/stream?livelink=0") as ws:  # opted out
            ws.receive_json()
            ws.send_json({"type": "end"})
            while ws.receive()["type"] != "websocket.close":
                pass
    faces = receive(listener, 30)
    assert [f._frames for f in faces] == list(range(30)) and {f.name for f in faces} == {"Mia"}
    assert (faces[0].fps, faces[0]._denominator) == (30, 1)
    # the head turns with the session's head pose (breathing and sway in silence), in half turns
    for face, frame in zip(faces, sent, strict=True):
        got = [face.get_blendshape(FaceBlendShape[n]) for n in ("HeadYaw", "HeadPitch", "HeadRoll")]
        np.testing.assert_allclose(got, frame.head_pose[[1, 0, 2]] / np.pi, atol=1e-7)
    assert np.ptp([f.get_blendshape(FaceBlendShape.HeadPitch) for f in faces]) > 0
    listener.settimeout(0.3)
    with pytest.raises(TimeoutError):
        listener.recv(4096)  # the second session sent nothing


def test_serve_refuses_a_subject_when_it_sends_no_live_link():
    with TestClient(create_app()) as client:
        with client.websocket_connect("/ws/stream?livelink=Mia") as ws:
            message = ws.receive_json()
    assert message["type"] == "error" and "start it with --livelink" in message["message"]


def test_serve_with_a_refused_target_does_not_start():
    with pytest.raises(TalkmeshError, match="nothing listens there"):
        create_app(livelink=f"127.0.0.1:{free_udp_port()}")


def test_serve_on_a_port_in_use_is_one_line_and_leaves_nothing_running(listener):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        target = f"127.0.0.1:{listener.getsockname()[1]}"
        proc = subprocess.Popen(
            [sys.executable, "-m", "talkmesh", "serve", "--port", str(port), "--livelink", target],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,  # its workers share its process group
        )
        _, err = proc.communicate(timeout=300)
    assert proc.returncode != 0
    assert err.strip().splitlines() == [
        f"talkmesh: error: cannot listen on 127.0.0.1:{port} (Address already in use): "
        "choose another --port or --host"
    ]
    assert not group_alive(proc.pid), "a worker of the server outlived it"


def group_alive(pgid: int, wait_s: float = 30.0) -> bool:
    """Whether a process of group ``pgid`` still exists after up to ``wait_s`` seconds (a worker
    that exits with its parent is reaped by init a moment later)."""
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return False
        time.sleep(0.1)
    return True


def test_cli_without_a_sound_library_says_to_pass_no_audio(listener, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "sounddevice", None)  # import fails, as without PortAudio
    port = listener.getsockname()[1]
    args = ["livelink", str(CLIP), "--to", f"127.0.0.1:{port}", "--model", "procedural"]
    assert main(args) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot play the audio" in err[0] and "--no-audio" in err[0]
