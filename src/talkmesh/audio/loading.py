"""Audio I/O: any speech file -> (S,) float32 mono waveform at 16 kHz.

WAV, FLAC, OGG and the other formats libsndfile reads are decoded with ``soundfile`` block by
block, mixed down to mono and resampled with a polyphase filter (``scipy.signal.resample_poly``
with the exact rational factor), so memory stays bounded by the output plus one block. Everything
else (mp3, m4a, video containers) goes through the static ffmpeg binary of ``imageio-ffmpeg``,
which decodes straight to 16-bit mono PCM at the target rate through a pipe.
"""

from __future__ import annotations

import math
import re
import stat
import subprocess
import tempfile
import warnings
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path

import numpy as np
import soundfile as sf

from talkmesh.audio.resamplers import POLYPHASE, check_resampler, resample_with
from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import MissingDependencyError, TalkmeshError, TalkmeshWarning

MAX_DURATION_S = 3 * 60 * 60  # longer inputs are almost certainly a mistake: refuse them
BLOCK_S = 30.0  # seconds of input decoded and resampled at a time
INT16_SCALE = 32_768.0  # s16 PCM -> [-1, 1)
BYTES_PER_SAMPLE = 2  # s16le from ffmpeg
PIPE_CHUNK_BYTES = 1 << 20  # read from ffmpeg's stdout at a time
RIFF_SCAN_BYTES = 1 << 16  # of a WAV's start searched for its data chunk's header
# libsndfile's frame count (SF_COUNT_MAX) of a stream whose header does not state its length:
# ffmpeg writes FLAC to a pipe with "total samples 0"; the length is then counted by decoding
UNKNOWN_FRAMES = 2**62

# Decoded by libsndfile; anything else is handed to ffmpeg.
SOUNDFILE_EXTENSIONS = frozenset(
    {".wav", ".wave", ".flac", ".ogg", ".oga", ".aif", ".aiff", ".aifc", ".au", ".w64", ".caf"}
)


def load_audio(
    path: str | Path,
    sr: int = SAMPLE_RATE,
    *,
    max_seconds: float | None = None,
    resampler: str = POLYPHASE,
) -> np.ndarray:
    """Read an audio file as a mono waveform.

    Args:
        path: any audio file: wav/flac/ogg are read with soundfile, everything else (mp3, m4a,
            video files) with ffmpeg. Any sample rate and channel count.
        sr: target sample rate in Hz.
        max_seconds: longer files are refused (default ``MAX_DURATION_S``): from the header,
            before anything is decoded, when it states the length, else as soon as the decoded
            audio passes it.
        resampler: how another rate becomes ``sr`` (:data:`talkmesh.audio.resamplers.RESAMPLERS`):
            ``polyphase`` streams the file through the polyphase filter; the others (the
            official codes' resamplers, for imported models) decode the file at its own rate
            and convert it whole.

    Returns:
        (S,) float32 waveform in [-1, 1] at ``sr``; channels are averaged.

    Raises:
        TalkmeshError: the file is missing, empty, not audio, has no samples, is longer than
            ``max_seconds`` or holds NaN or infinite samples (float WAVs can).

    A file whose data ends before the length its header states is read as far as it goes, with a
    :class:`TalkmeshWarning` giving both durations.
    """
    path = _check_file(path)
    if sr <= 0:
        raise TalkmeshError(f"sample rate must be positive, got {sr}")
    max_seconds = MAX_DURATION_S if max_seconds is None else max_seconds
    check_resampler(resampler)
    if path.suffix.lower() in SOUNDFILE_EXTENSIONS:
        try:
            audio = _load_soundfile(path, sr, max_seconds, resampler)
            if audio is None:  # FLAC written to a pipe: ffmpeg counts as it decodes
                reason = "no length in its header"
                audio = _load_ffmpeg_fallback(path, sr, reason, max_seconds, resampler)
        except sf.LibsndfileError as e:
            # libsndfile cannot read some codecs inside WAV (e.g. GSM, MP3-in-RIFF), nor
            # truncated or corrupt files to their end: try ffmpeg.
            reason = _one_line(str(e))
            audio = _load_ffmpeg_fallback(path, sr, reason, max_seconds, resampler)
    else:
        audio = _load_ffmpeg_resampled(path, sr, None, max_seconds, resampler)
    assert audio.ndim == 1 and audio.dtype == np.float32
    if not len(audio):
        raise TalkmeshError(f"{path} contains no audio samples: re-export or re-record it")
    refuse_nonfinite(path, int(np.count_nonzero(~np.isfinite(audio))))
    return audio


def refuse_nonfinite(path: Path, bad: int) -> None:
    """A one-line error when ``bad`` samples of ``path`` are NaN or infinite."""
    if bad:
        raise TalkmeshError(
            f"{path} holds {bad} NaN or infinite samples (a broken float WAV): re-export it as "
            "16-bit PCM or repair the samples"
        )


def warn_if_cut(path: Path, present_s: float, stated_s: float, sr: int, stacklevel: int) -> None:
    """Warn when less audio is present than the file's header states (a cut-off file)."""
    if present_s < stated_s - 2 / sr:
        warnings.warn(
            f"{path}: the header says {stated_s:.2f} s but only {present_s:.2f} s of audio is "
            "present (a cut-off file?): animating what is there",
            TalkmeshWarning,
            stacklevel=stacklevel + 1,
        )


def audio_duration(path: str | Path, limit: float | None = None) -> float:
    """Duration of an audio file in seconds, from its header (nothing is decoded); a file whose
    header does not state it (FLAC written to a pipe) is decoded to count its samples, up to
    ``limit`` seconds (default MAX_DURATION_S): a longer one returns as soon as it passes it."""
    path = _check_file(path)
    if path.suffix.lower() in SOUNDFILE_EXTENSIONS:
        try:
            info = sf.info(str(path))
            if info.frames < UNKNOWN_FRAMES:
                return info.frames / info.samplerate
            limit = MAX_DURATION_S if limit is None else limit
            return count_frames(path, limit) / info.samplerate
        except sf.LibsndfileError:
            pass  # maybe a codec only ffmpeg knows: probe with it below
    return _ffmpeg_duration(path)


def count_frames(path: Path, limit_s: float) -> int:
    """The frames of a file whose header does not state them, counted by decoding it a block
    at a time (nothing is kept), stopping once past ``limit_s`` seconds. libsndfile fails on
    the last, partial block of such a stream: the count is then short of it (under 0.3 s at
    16 kHz), which is enough to price the file before ffmpeg decodes it whole."""
    size = 4096
    n = 0
    with sf.SoundFile(str(path)) as f:
        limit = int(limit_s * f.samplerate) + 1
        while n <= limit:
            try:
                got = len(f.read(size, dtype="float32", always_2d=True))
            except sf.LibsndfileError:
                break
            n += got
            if got < size:
                break
    return n


def save_wav(path: str | Path, audio: np.ndarray, sr: int = SAMPLE_RATE) -> None:
    """Write a (S,) or (S, C) waveform in [-1, 1] as 16-bit PCM WAV (parent folders are created)."""
    audio = np.asarray(audio, dtype=np.float32)
    if audio.ndim not in (1, 2) or not audio.size:
        raise TalkmeshError(f"cannot write {path}: audio must be a non-empty (S,) or (S, C) array")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # libsndfile wraps out-of-range floats around instead of clipping them.
    sf.write(str(path), np.clip(audio, -1.0, 1.0), sr, subtype="PCM_16")


def resample(
    audio: np.ndarray, orig_sr: int, sr: int = SAMPLE_RATE, method: str = POLYPHASE
) -> np.ndarray:
    """Resample a (S,) waveform from ``orig_sr`` to ``sr``; float32 out. ``method``: the
    polyphase filter, or an official code's (:mod:`talkmesh.audio.resamplers`)."""
    audio = np.asarray(audio, dtype=np.float32)
    assert audio.ndim == 1, f"expected a (S,) waveform, got shape {audio.shape}"
    if check_resampler(method) != POLYPHASE:
        return resample_with(audio, orig_sr, sr, method)
    return _resample_blocks(iter([audio]), len(audio), orig_sr, sr)


def _check_file(path: str | Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise TalkmeshError(f"audio file not found: {path}: check the path")
    if path.is_dir():
        raise TalkmeshError(f"{path} is a folder, not an audio file: pass a wav, flac or mp3 file")
    if not path.is_file():  # reading a FIFO would wait for a writer; a device never ends
        kind = "a named pipe (FIFO)" if stat.S_ISFIFO(path.stat().st_mode) else "a device"
        raise TalkmeshError(
            f"{path} is {kind}, not an audio file: save the audio to a file and pass that"
        )
    if path.stat().st_size == 0:
        raise TalkmeshError(f"audio file {path} is empty (0 bytes): re-export or re-record it")
    return path


def _check_duration(path: Path, seconds: float, max_seconds: float | None = None) -> None:
    if max_seconds is None:
        max_seconds = MAX_DURATION_S
    if seconds > max_seconds:
        raise AudioTooLong(path, seconds, max_seconds)


class AudioTooLong(TalkmeshError):
    """The audio is longer than the caller accepts (``seconds`` and ``limit`` say by how much)."""

    def __init__(self, path: Path, seconds: float, limit: float):
        self.seconds, self.limit = seconds, limit
        super().__init__(
            f"{path} is {_span(seconds)} long, more than the {_span(limit)} accepted: split it "
            "into shorter files"
        )


def _span(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.1f} hours"
    return f"{seconds / 60:.1f} minutes" if seconds >= 120 else f"{seconds:.1f} s"


def _one_line(message: str) -> str:
    return " ".join(message.split())


def _unreadable(path: Path, reason: str) -> TalkmeshError:
    return TalkmeshError(
        f"cannot read audio from {path} ({reason}): check that it is a valid audio file "
        "(wav, flac, ogg, mp3, m4a) and not corrupt"
    )


# --- soundfile path -------------------------------------------------------------------------


def _load_soundfile(
    path: Path, sr: int, max_seconds: float | None = None, resampler: str = POLYPHASE
) -> np.ndarray | None:
    """The waveform through libsndfile, None for a stream without a stated length."""
    with sf.SoundFile(str(path)) as f:
        if f.frames >= UNKNOWN_FRAMES:  # libsndfile fails on its last block: ffmpeg reads it
            return None
        if f.frames <= 0:
            raise TalkmeshError(f"{path} contains no audio samples: re-export or re-record it")
        _check_duration(path, f.frames / f.samplerate, max_seconds)
        block = max(1, int(BLOCK_S * f.samplerate))
        blocks = (
            b[:, 0] if b.shape[1] == 1 else b.mean(axis=1, dtype=np.float32)
            for b in f.blocks(blocksize=block, dtype="float32", always_2d=True)
        )
        if resampler == POLYPHASE:
            audio = _resample_blocks(blocks, f.frames, f.samplerate, sr)
        else:  # the whole file at its own rate, then the official code's resampler
            native = _resample_blocks(blocks, f.frames, f.samplerate, f.samplerate)
            audio = resample_with(native, f.samplerate, sr, resampler)
        # libsndfile trims a WAV's frame count to the bytes present: ask the header itself
        stated = _riff_stated_seconds(path) or f.frames / f.samplerate
    warn_if_cut(path, len(audio) / sr, stated, sr, stacklevel=3)
    return audio


def _riff_stated_seconds(path: Path) -> float | None:
    """The duration a RIFF WAV's ``data`` chunk header states (None: not RIFF or no such chunk)."""
    with open(path, "rb") as f:
        head = f.read(RIFF_SCAN_BYTES)
    if head[:4] != b"RIFF" or head[8:12] != b"WAVE":
        return None
    pos, rate, align = 12, 0, 0
    while pos + 8 <= len(head):
        kind, size = head[pos : pos + 4], int.from_bytes(head[pos + 4 : pos + 8], "little")
        if kind == b"fmt " and pos + 24 <= len(head):
            rate = int.from_bytes(head[pos + 12 : pos + 16], "little")
            align = int.from_bytes(head[pos + 20 : pos + 22], "little")
        elif kind == b"data":
            return size / align / rate if rate and align and size < 0xFFFFFFFF else None
        pos += 8 + size + (size & 1)
    return None


def _resample_blocks(blocks: Iterator[np.ndarray], n_in: int, orig_sr: int, sr: int) -> np.ndarray:
    """Polyphase-resample a stream of (n,) float32 blocks holding ``n_in`` samples in total.

    Each piece is filtered with enough context either side that the result equals
    ``resample_poly`` on the whole signal: pieces start on multiples of ``down`` input samples,
    which fall exactly on output samples. If the stream ends early (a truncated file), the
    output is shortened to match.
    """
    from scipy.signal import resample_poly  # here: scipy.signal takes a second to import

    ratio = Fraction(sr, orig_sr)
    up, down = ratio.numerator, ratio.denominator
    out = np.empty(-(-n_in * up // down), dtype=np.float32)
    # resample_poly's filter reaches 10 * max(up, down) samples either side at the upsampled rate.
    margin = down * math.ceil((math.ceil(10 * max(up, down) / up) + 1) / down)

    buf = np.zeros(0, dtype=np.float32)
    buf_start = 0  # input index of buf[0]; always a multiple of down
    done = 0  # input samples whose output is written; a multiple of down until the end
    n_written = 0

    def emit(ready: int) -> None:
        nonlocal buf, buf_start, done, n_written
        if up == down:
            piece = buf[done - buf_start : ready - buf_start]
        else:
            y = resample_poly(buf, up, down)  # y[0] is output sample buf_start * up / down
            lo = (done - buf_start) * up // down
            piece = y[lo : lo - (-(ready - done) * up // down)]
        out[n_written : n_written + len(piece)] = piece
        n_written += len(piece)
        done = ready
        keep = max(0, done - margin)
        buf, buf_start = buf[keep - buf_start :], keep

    for block in blocks:
        buf = np.concatenate([buf, block[: n_in - (buf_start + len(buf))]])
        end = buf_start + len(buf)
        ready = n_in if end >= n_in else (end - margin) // down * down
        if ready > done:
            emit(ready)
        if done >= n_in:
            break
    if done < buf_start + len(buf):  # the stream ended before n_in samples
        emit(buf_start + len(buf))
    return out[:n_written]


# --- ffmpeg path ----------------------------------------------------------------------------


def _ffmpeg_exe() -> str:
    try:
        import imageio_ffmpeg
    except ImportError as e:
        raise MissingDependencyError(
            "imageio-ffmpeg", "render", "Reading mp3, m4a and other compressed audio"
        ) from e
    return imageio_ffmpeg.get_ffmpeg_exe()


def _load_ffmpeg_fallback(
    path: Path, sr: int, reason: str, max_seconds: float, resampler: str = POLYPHASE
) -> np.ndarray:
    try:
        exe = _ffmpeg_exe()
    except MissingDependencyError:
        raise _unreadable(path, reason) from None
    return _load_ffmpeg_resampled(path, sr, exe, max_seconds, resampler)


_RATE = re.compile(r"Audio:[^\n]*?(\d+) Hz")


def _load_ffmpeg_resampled(
    path: Path, sr: int, exe: str | None, max_seconds: float, resampler: str
) -> np.ndarray:
    """ffmpeg's decoding at ``sr`` (its own resampler), or with another ``resampler``: decoded at
    the stream's own rate (from ffmpeg's probe), then converted."""
    if resampler == POLYPHASE:
        return _load_ffmpeg(path, sr, exe, max_seconds)
    exe = exe or _ffmpeg_exe()
    header = _ffmpeg_header(path, exe)
    m = _RATE.search(header)
    rate = int(m.group(1)) if m else sr
    audio = _load_ffmpeg(path, rate, exe, max_seconds, header)
    return resample_with(audio, rate, sr, resampler)


def _load_ffmpeg(
    path: Path,
    sr: int,
    exe: str | None = None,
    max_seconds: float | None = None,
    header: str | None = None,
) -> np.ndarray:
    """Decode with ffmpeg to s16le mono at ``sr`` through a pipe, refusing overlong streams
    (``header``: what ffmpeg says of the file, when it was already asked)."""
    exe = exe or _ffmpeg_exe()
    max_seconds = MAX_DURATION_S if max_seconds is None else max_seconds
    seconds, _ = _ffmpeg_probe(path, exe, header)
    if seconds is not None:  # else no duration in the header: the decoded length tells
        _check_duration(path, seconds, max_seconds)
    max_bytes = int(max_seconds * sr) * BYTES_PER_SAMPLE
    cmd = [exe, "-nostdin", "-v", "error", "-i", str(path), "-vn", "-sn", "-dn"]
    cmd += ["-ac", "1", "-ar", str(sr), "-f", "s16le", "-acodec", "pcm_s16le", "-"]
    data = bytearray()
    # stderr goes to a file: a corrupt input can log more than a pipe buffer holds.
    with tempfile.TemporaryFile() as log:
        with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log) as proc:
            assert proc.stdout is not None
            while chunk := proc.stdout.read(PIPE_CHUNK_BYTES):
                data += chunk
                if len(data) > max_bytes:
                    proc.kill()
                    _check_duration(path, len(data) / BYTES_PER_SAMPLE / sr, max_seconds)
            returncode = proc.wait()
        log.seek(0)
        errors = log.read().decode(errors="replace").strip()
    if returncode != 0:
        raise _unreadable(path, _ffmpeg_reason(errors, path) or f"ffmpeg exit status {returncode}")
    n = len(data) // BYTES_PER_SAMPLE
    pcm = np.frombuffer(data, dtype="<i2", count=n)
    audio = np.empty(n, dtype=np.float32)
    np.multiply(pcm, np.float32(1 / INT16_SCALE), out=audio)
    return audio


_DURATION = re.compile(r"Duration:\s*(\d+):(\d\d):(\d\d(?:\.\d+)?)")


def _ffmpeg_duration(path: Path) -> float:
    seconds, log = _ffmpeg_probe(path, _ffmpeg_exe())
    if seconds is None:
        raise _unreadable(path, log or "no duration in its header")
    return seconds


def _ffmpeg_header(path: Path, exe: str) -> str:
    """What ffmpeg says of the file's container and streams (nothing is decoded)."""
    proc = subprocess.run(
        [exe, "-nostdin", "-hide_banner", "-i", str(path)],
        capture_output=True,
        text=True,
        errors="replace",
    )
    return proc.stderr


def _ffmpeg_probe(path: Path, exe: str, header: str | None = None) -> tuple[float | None, str]:
    """The duration in the container header (nothing is decoded) or None with ffmpeg's reason."""
    header = _ffmpeg_header(path, exe) if header is None else header
    m = _DURATION.search(header)
    if m is None:
        return None, _ffmpeg_reason(header, path)
    hours, minutes, seconds = m.groups()
    return int(hours) * 3600 + int(minutes) * 60 + float(seconds), ""


def _ffmpeg_reason(log: str, path: Path) -> str:
    """ffmpeg's last complaint, without the file name it prefixes."""
    lines = [line for line in log.splitlines() if line.strip() and "output file" not in line]
    return _one_line(lines[-1].replace(str(path), "").strip(": ")) if lines else ""
