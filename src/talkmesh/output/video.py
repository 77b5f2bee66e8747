"""mp4 encoding: one ffmpeg process (the static binary of ``imageio-ffmpeg``) reads raw RGBA frames
on stdin and muxes the audio from a temporary wav in the same pass. Every file is written to a
temporary name next to the target and renamed at the end, so a failed render never leaves a partial
file or destroys an existing one."""

from __future__ import annotations

import os
import re
import subprocess
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from fractions import Fraction
from pathlib import Path
from typing import IO

import numpy as np
import soundfile
from tqdm import tqdm

from talkmesh.errors import MissingDependencyError, TalkmeshError
from talkmesh.output.atomic import temp_prefix
from talkmesh.output.media import VIDEO_SUFFIXES, video_size

VIDEO_CRF = 18  # visually lossless H.264
VIDEO_PRESET = "veryfast"
AUDIO_BITRATE = "128k"
AUDIO_RATE = 48_000  # AAC frames are 1024 samples: 21 ms at 48 kHz, so ends align within a frame
FFMPEG_FINISH_TIMEOUT_S = 120  # time ffmpeg gets to finish after its last frame


def ffmpeg_exe() -> str:
    try:
        import imageio_ffmpeg
    except ImportError as e:
        raise MissingDependencyError("imageio-ffmpeg", "render", "Writing videos") from e
    return imageio_ffmpeg.get_ffmpeg_exe()


def check_output(
    path: str | os.PathLike, suffixes: Sequence[str], inputs: Iterable[str | os.PathLike]
) -> Path:
    """Refuses an output path with another suffix, in a missing folder, or that is an input."""
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise TalkmeshError(f"{path}: the output must end in {' or '.join(suffixes)}")
    if not path.parent.is_dir():
        raise TalkmeshError(f"{path}: the folder {path.parent} does not exist")
    if path.is_dir():
        raise TalkmeshError(f"{path}: is a folder, not a file")
    if path.exists():
        for other in inputs:
            if Path(other).exists() and os.path.samefile(path, other):
                raise TalkmeshError(
                    f"{path}: refusing to overwrite an input; choose another output"
                )
    return path


@contextmanager
def atomic_output(
    path: str | os.PathLike, suffixes: Sequence[str], inputs: Iterable[str | os.PathLike] = ()
) -> Iterator[Path]:
    """Yields a temporary file next to ``path`` that replaces it only if the block succeeds."""
    path = check_output(path, suffixes, inputs)
    mode = path.stat().st_mode & 0o777 if path.exists() else 0o644
    fd, name = tempfile.mkstemp(
        prefix=f"{temp_prefix()}{path.stem}.", suffix=f".part{path.suffix}", dir=path.parent
    )
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def fps_arg(fps: float) -> str:
    """Frame rate as the exact fraction ffmpeg expects (29.97 -> 2997/100)."""
    frac = Fraction(fps).limit_denominator(100_000)
    return f"{frac.numerator}/{frac.denominator}"


def fit_audio(audio: np.ndarray, sample_rate: int, duration: float) -> np.ndarray:
    """(S,) audio zero-padded or trimmed to ``duration`` seconds -> (round(duration * rate),)."""
    num = round(duration * sample_rate)
    fitted = np.zeros(num, dtype=np.float32)
    fitted[: min(num, len(audio))] = audio[:num]
    return fitted


def write_video(
    frames: Iterable[np.ndarray],
    num_frames: int,
    size: tuple[int, int],
    fps: float,
    path: str | os.PathLike,
    *,
    audio: np.ndarray | None,
    sample_rate: int,
    inputs: Iterable[str | os.PathLike],
    crf: int,
    progress: bool,
    audio_file: str | os.PathLike | None = None,
) -> Path:
    """Encodes ``num_frames`` (H, W, 4) uint8 RGBA frames and optional (S,) audio into an mp4.

    One ffmpeg process reads the frames on stdin and the audio, padded or trimmed to the video's
    duration so that both streams end together, from a temporary wav; or, given ``audio_file``
    (the user's speech file, which ``audio`` was read from), from that file, at its own sample
    rate and with its own channels (a 44.1 kHz recording keeps what lies above 8 kHz).
    """
    width, height = video_size(size)
    path = Path(path)
    cmd = [ffmpeg_exe(), "-hide_banner", "-nostdin", "-loglevel", "error", "-y"]
    cmd += ["-f", "rawvideo", "-pix_fmt", "rgba", "-s", f"{width}x{height}"]
    cmd += ["-framerate", fps_arg(fps), "-i", "pipe:0"]
    with tempfile.TemporaryDirectory(prefix="talkmesh-") as tmpdir:
        if audio_file is not None and Path(audio_file).is_file():
            seconds = f"{num_frames / fps:.6f}"
            cmd += ["-i", str(audio_file), "-map", "0:v:0", "-map", "1:a:0"]
            cmd += ["-af", "apad", "-t", seconds, "-c:a", "aac", "-b:a", AUDIO_BITRATE]
        elif audio is not None:
            wav = Path(tmpdir) / "audio.wav"
            soundfile.write(wav, fit_audio(audio, sample_rate, num_frames / fps), sample_rate)
            cmd += ["-i", str(wav), "-map", "0:v:0", "-map", "1:a:0"]
            cmd += ["-c:a", "aac", "-b:a", AUDIO_BITRATE, "-ar", str(AUDIO_RATE)]
        cmd += ["-c:v", "libx264", "-preset", VIDEO_PRESET, "-crf", str(crf), "-pix_fmt", "yuv420p"]
        with (
            atomic_output(path, VIDEO_SUFFIXES, inputs) as tmp,
            open(Path(tmpdir) / "ffmpeg.log", "w+b") as log,
        ):
            cmd += ["-movflags", "+faststart", "-f", "mp4", str(tmp)]
            proc = subprocess.Popen(
                cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=log
            )
            try:
                _pipe_frames(proc, frames, num_frames, (height, width, 4), progress)
                returncode = proc.wait(timeout=FFMPEG_FINISH_TIMEOUT_S)
            except BrokenPipeError:  # ffmpeg stopped reading: its log says why
                returncode = proc.wait(timeout=FFMPEG_FINISH_TIMEOUT_S) or 1
            except BaseException:
                proc.kill()
                proc.wait()
                raise
            finally:
                try:
                    proc.stdin.close()
                except OSError:  # a broken pipe: ffmpeg has gone already
                    pass
            if returncode != 0:
                raise TalkmeshError(
                    f"{path}: ffmpeg could not write the video ({_first_error(log)})"
                )
    return path


def _first_error(log: IO[bytes]) -> str:
    """The first line of an ffmpeg log (the cause; later lines are consequences), unprefixed."""
    log.seek(0)
    for line in log.read().decode(errors="replace").splitlines():
        line = re.sub(r"^\[[^\]]*\]\s*", "", line.strip())  # "[libx264 @ 0x55...] Value ..."
        if line:
            return line
    return "no message"


def _pipe_frames(
    proc: subprocess.Popen,
    frames: Iterable[np.ndarray],
    num_frames: int,
    shape: tuple[int, int, int],
    progress: bool,
) -> None:
    """Writes exactly ``num_frames`` frames of ``shape`` to ffmpeg's stdin, then closes it."""
    written = 0
    with tqdm(total=num_frames, unit="frame", disable=not progress) as bar:
        for frame in frames:
            if written == num_frames:
                break
            assert frame.shape == shape and frame.dtype == np.uint8, (frame.shape, frame.dtype)
            proc.stdin.write(np.ascontiguousarray(frame).data)
            written += 1
            bar.update()
    assert written == num_frames, (written, num_frames)
    proc.stdin.close()
