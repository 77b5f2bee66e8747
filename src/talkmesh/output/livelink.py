"""Live Link Face over UDP: ARKit weights sent live to Unreal Engine as the iPhone app sends them.

Epic's Live Link Face app streams one UDP datagram per frame to Unreal's Live Link source
(port 11111 by default); a MetaHuman's face animation blueprint reads the curves by their ARKit
names. A datagram (version 6 of the app's format, every number big-endian):

====================  =======================================================================
``uint8``             packet version, 6
``int32`` + bytes     device id: its length, then UTF-8 (a UUID string, 36 characters)
``int32`` + bytes     subject name: its length, then UTF-8 (what Unreal lists the subject as)
``int32, float32``    frame time: frame number and sub-frame
``int32, int32``      frame rate: numerator and denominator (30/1, 30000/1001, ...)
``uint8``             value count, 61
``61 x float32``      the 52 blendshapes in ARKit's order (:data:`ARKIT_NAMES`, Unreal's
                      ``EARFaceBlendShape``), then head yaw, pitch, roll and the left and right
                      eyes' yaw, pitch, roll (half turns: radians / pi, -1 to 1, as
                      Unreal's ARKit face support maps them)
====================  =======================================================================

The packet's blendshapes keep ARKit's order, where the app's CSV takes swap jawLeft/jawRight and
mouthLeft/mouthRight (:mod:`talkmesh.face.arkit`); the nine rotations are the CSV's last
columns, as :func:`talkmesh.output.arkit_files.export_live_link_csv` writes them: the head's from
an Animation's ``head_pose`` when it has one, the eyes' zero (the eyes move by their eyeLook
blendshapes). Frame numbers count frames from the start of the animation or stream.
"""

from __future__ import annotations

import socket
import struct
import time
import uuid
from dataclasses import dataclass
from fractions import Fraction
from typing import NamedTuple

import numpy as np

from talkmesh.animation import Animation
from talkmesh.errors import TalkmeshError
from talkmesh.face.arkit import ARKIT_NAMES, LIVE_LINK_ROTATIONS, live_link_head

PACKET_VERSION = 6
DEFAULT_PORT = 11111  # Unreal's Live Link Face source listens here unless told otherwise
DEFAULT_SUBJECT = "talkmesh"
MAX_SUBJECT = 64
PACKET_VALUES = len(ARKIT_NAMES) + len(LIVE_LINK_ROTATIONS)  # 61
HEAD_COLUMNS = len(ARKIT_NAMES) + np.arange(3)  # HeadYaw, HeadPitch, HeadRoll
CHECK_WAIT_S = 0.2  # how long a check waits for "port unreachable" from the target
SPIN_S = 0.0005  # the last half millisecond before a frame is waited out by spinning
_VALUES = struct.Struct(f">B{PACKET_VALUES}f")


class Target(NamedTuple):
    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


def parse_target(text: str) -> Target:
    """``HOST:PORT`` (``[::1]:PORT`` for IPv6; ``HOST`` alone: port 11111) -> a :class:`Target`."""
    text = text.strip()
    host, sep, port_text = text.rpartition(":")
    if not sep or host.endswith(":"):  # no port, or a bare IPv6 address
        host, port_text = text, str(DEFAULT_PORT)
    host = host.strip("[]")
    if not host:
        raise TalkmeshError(f"Live Link target '{text}': give HOST:PORT, e.g. 127.0.0.1:11111")
    if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise TalkmeshError(f"Live Link target '{text}': the port must be 1 to 65535")
    return Target(host, int(port_text))


def check_subject(name: str) -> str:
    """A subject name Unreal can list: 1 to 64 printable ASCII characters."""
    if not 1 <= len(name) <= MAX_SUBJECT or not name.isascii() or not name.isprintable():
        raise TalkmeshError(
            f"Live Link subject '{name[:80]}': give 1 to {MAX_SUBJECT} printable ASCII characters"
        )
    return name


def frame_rate(fps: float) -> tuple[int, int]:
    """``fps`` as the packet's numerator / denominator (29.97 -> 30000/1001)."""
    rate = Fraction(fps).limit_denominator(1001)
    return rate.numerator, rate.denominator


def live_link_values(weights: np.ndarray, head_pose: np.ndarray | None = None) -> np.ndarray:
    """(T, 52) ARKit-order weights and an optional (T, 6) head pose -> (T, 61) float32 packet
    values: the weights, then the head's and the eyes' rotations."""
    weights = np.asarray(weights, np.float32)
    assert weights.ndim == 2 and weights.shape[1] == len(ARKIT_NAMES), weights.shape
    values = np.zeros((len(weights), PACKET_VALUES), np.float32)
    values[:, : len(ARKIT_NAMES)] = weights
    if head_pose is not None:
        values[:, HEAD_COLUMNS] = live_link_head(head_pose)
    return values


def encode_packet(
    values: np.ndarray, frame: int, fps: float, subject: str, device_id: str, sub_frame: float = 0.0
) -> bytes:
    """One Live Link Face datagram of ``values`` (61,) from :func:`live_link_values`."""
    assert values.shape == (PACKET_VALUES,), values.shape
    device, name = device_id.encode(), subject.encode()
    numerator, denominator = frame_rate(fps)
    return b"".join(
        (
            struct.pack(">B", PACKET_VERSION),
            struct.pack(">i", len(device)),
            device,
            struct.pack(">i", len(name)),
            name,
            struct.pack(">ifii", frame, sub_frame, numerator, denominator),
            _VALUES.pack(len(values), *values.tolist()),
        )
    )


class LiveLinkSender:
    """A UDP socket aimed at one Live Link target, sending frames under one subject name.

    Raises:
        TalkmeshError: the host has no address (a typo, no DNS).
    """

    def __init__(self, target: Target, subject: str = DEFAULT_SUBJECT, fps: float = 30.0) -> None:
        self.target, self.subject, self.fps = target, check_subject(subject), float(fps)
        self.device_id = str(uuid.uuid4())  # 36 characters, as the app's
        try:
            info = socket.getaddrinfo(target.host, target.port, type=socket.SOCK_DGRAM)
        except (socket.gaierror, UnicodeError) as e:
            raise TalkmeshError(
                f"Live Link target {target}: no such host ({e}); give an address or a name "
                "that resolves"
            ) from None
        family, kind, proto, _, address = info[0]
        self.sock = socket.socket(family, kind, proto)
        try:
            self.sock.connect(address)  # errors of later sends are this target's
        except OSError as e:
            self.sock.close()
            raise TalkmeshError(f"Live Link target {target}: {e.strerror or e}") from None
        self.sock.setblocking(False)  # a send never stalls a frame loop
        self.sent = 0
        self.refused = 0

    def send(self, values: np.ndarray, frame: int) -> bool:
        """Send one frame; False when the target refused it (nothing listens there yet)."""
        try:
            self.sock.send(encode_packet(values, frame, self.fps, self.subject, self.device_id))
        except (ConnectionRefusedError, BlockingIOError):
            self.refused += 1
            return False
        self.sent += 1
        return True

    def check(self) -> None:
        """Send a rest frame and wait briefly for "port unreachable": a target on this machine
        (or one whose host answers ICMP) with nothing listening is a one-line error. A silent
        host cannot be told from a listening one: UDP has no answer to wait for."""
        rest = np.zeros(PACKET_VALUES, np.float32)
        self.sock.settimeout(CHECK_WAIT_S)
        try:
            self.sock.send(encode_packet(rest, 0, self.fps, self.subject, self.device_id))
            self.sock.recv(1)
        except ConnectionRefusedError:
            self.close()
            raise TalkmeshError(
                f"Live Link target {self.target}: nothing listens there (port unreachable); "
                "start Unreal with a Live Link Face source on that port, or give its address"
            ) from None
        except TimeoutError:
            pass  # no refusal: something may listen
        except OSError as e:
            self.close()
            raise TalkmeshError(f"Live Link target {self.target}: {e.strerror or e}") from None
        finally:
            if self.sock.fileno() >= 0:
                self.sock.setblocking(False)  # a send never stalls a frame loop

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> LiveLinkSender:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class Played:
    """What :func:`play_live_link` did: frames sent, refused and how late each frame was sent
    after its time (seconds, (T,))."""

    sent: int
    refused: int
    late: np.ndarray


def play_live_link(
    anim: Animation, sender: LiveLinkSender, *, start: float | None = None
) -> Played:
    """Send ``anim``'s frames in real time: frame ``i`` at ``start + i / fps`` (``start``: the
    :func:`time.perf_counter` time of frame 0, default now)."""
    if anim.weights is None:
        raise TalkmeshError(
            "the animation has no ARKit weights (a model on its own topology): Live Link needs the "
            "bundled head's blendshapes"
        )
    from talkmesh.face.arkit import to_arkit_order

    values = live_link_values(to_arkit_order(anim.weights, anim.weight_names), anim.head_pose)
    sender.fps = float(anim.fps)
    late = np.zeros(len(values))
    start = time.perf_counter() if start is None else start
    for i, row in enumerate(values):
        due = start + i / anim.fps
        wait = due - time.perf_counter()
        if wait > SPIN_S:
            time.sleep(wait - SPIN_S)
        while time.perf_counter() < due:
            pass
        late[i] = time.perf_counter() - due
        sender.send(row, i)
    return Played(sender.sent, sender.refused, late)


def start_audio(audio: np.ndarray, sample_rate: int) -> float:
    """Start playing ``audio`` on the default output device; returns the device's output latency
    (seconds), by which the frames should follow."""
    try:
        import sounddevice
    except (ImportError, OSError) as e:  # OSError: the PortAudio library is missing
        raise TalkmeshError(
            f"cannot play the audio ({e}): install talkmesh[livelink] and PortAudio "
            "(apt install libportaudio2), or pass --no-audio"
        ) from None
    try:
        sounddevice.play(audio, sample_rate)
        return float(sounddevice.get_stream().latency)
    except sounddevice.PortAudioError as e:
        raise TalkmeshError(f"cannot play the audio ({e}): pass --no-audio") from None


def stop_audio() -> None:
    import sounddevice

    sounddevice.stop()
