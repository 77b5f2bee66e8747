import subprocess
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from scipy.signal import resample_poly

from talkmesh.audio import loading as audio_module
from talkmesh.audio.loading import SAMPLE_RATE, audio_duration, load_audio, resample, save_wav
from talkmesh.errors import TalkmeshError, TalkmeshWarning

ALSA_CLIP = Path("/usr/share/sounds/alsa/Front_Center.wav")  # alsa-utils, 48 kHz mono speech


def sine(freq: float, seconds: float, sr: int, amplitude: float = 0.5) -> np.ndarray:
    t = np.arange(int(seconds * sr)) / sr
    return (amplitude * np.sin(2 * np.pi * freq * t)).astype(np.float32)


def dominant_frequency(x: np.ndarray, sr: int) -> float:
    spectrum = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    return float(np.argmax(spectrum) * sr / len(x))


def ffmpeg(*args: str) -> None:
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-v", "error", "-y", *args]
    subprocess.run(cmd, check=True)


def test_wav_48k_stereo_is_mixed_down_and_resampled(tmp_path):
    left, right = sine(440, 1.0, 48_000), sine(440, 1.0, 48_000, amplitude=0.1)
    path = tmp_path / "stereo.wav"
    sf.write(path, np.stack([left, right], axis=1), 48_000)
    x = load_audio(path)
    assert x.dtype == np.float32 and x.shape == (SAMPLE_RATE,)
    # The mono mix is the channel mean: a 0.3 amplitude sine.
    assert np.max(np.abs(x[1000:-1000])) == pytest.approx(0.3, abs=0.01)
    assert dominant_frequency(x, SAMPLE_RATE) == pytest.approx(440, abs=1.5)


@pytest.mark.parametrize("sr", [8_000, 22_050, 44_100, 48_000, 96_000])
def test_resampling_preserves_a_sine(tmp_path, sr):
    path = tmp_path / f"sine_{sr}.wav"
    sf.write(path, sine(440, 2.0, sr), sr, subtype="FLOAT")
    x = load_audio(path)
    assert len(x) == pytest.approx(2 * SAMPLE_RATE, abs=1)
    assert dominant_frequency(x, SAMPLE_RATE) == pytest.approx(440, abs=1)
    expected = sine(440, len(x) / SAMPLE_RATE, SAMPLE_RATE)[: len(x)]
    # Away from the edges the resampled sine matches the ideal one closely.
    assert np.max(np.abs(x - expected)[200:-200]) < 2e-3


def test_blockwise_resampling_equals_whole_signal(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    signal = rng.uniform(-0.5, 0.5, size=(44_100 * 2, 2)).astype(np.float32)
    path = tmp_path / "noise.wav"
    sf.write(path, signal, 44_100, subtype="FLOAT")
    monkeypatch.setattr(audio_module, "BLOCK_S", 0.0123)  # many small, oddly sized blocks
    x = load_audio(path)
    ratio = Fraction(SAMPLE_RATE, 44_100)
    whole = resample_poly(signal.mean(axis=1), ratio.numerator, ratio.denominator)
    assert x.shape == whole.shape
    np.testing.assert_allclose(x, whole, atol=1e-6)
    np.testing.assert_allclose(resample(signal.mean(axis=1), 44_100), whole, atol=1e-6)


@pytest.mark.parametrize(
    ("ext", "fmt", "subtype"), [("flac", "FLAC", "PCM_16"), ("ogg", "OGG", "VORBIS")]
)
def test_flac_and_ogg(tmp_path, ext, fmt, subtype):
    path = tmp_path / f"tone.{ext}"
    sf.write(path, sine(440, 1.5, 44_100), 44_100, format=fmt, subtype=subtype)
    x = load_audio(path)
    assert len(x) == pytest.approx(1.5 * SAMPLE_RATE, abs=2)
    assert dominant_frequency(x, SAMPLE_RATE) == pytest.approx(440, abs=1)
    assert audio_duration(path) == pytest.approx(1.5, abs=1e-3)


@pytest.mark.parametrize("ext", ["mp3", "m4a"])
def test_compressed_formats_via_ffmpeg(tmp_path, ext):
    path = tmp_path / f"tone.{ext}"
    ffmpeg(
        "-f",
        "lavfi",
        "-i",
        "sine=frequency=440:duration=1.5:sample_rate=44100",
        "-ac",
        "2",
        str(path),
    )
    x = load_audio(path)
    assert x.dtype == np.float32 and x.ndim == 1
    # Encoders add a little padding at the start.
    assert 1.5 * SAMPLE_RATE <= len(x) <= 1.6 * SAMPLE_RATE
    assert dominant_frequency(x, SAMPLE_RATE) == pytest.approx(440, abs=1.5)
    assert audio_duration(path) == pytest.approx(1.5, abs=0.1)


@pytest.mark.skipif(not ALSA_CLIP.exists(), reason="alsa-utils sounds are not installed")
def test_real_48k_speech_clip():
    x = load_audio(ALSA_CLIP)
    info = sf.info(ALSA_CLIP)
    assert info.samplerate == 48_000
    assert len(x) == pytest.approx(info.duration * SAMPLE_RATE, abs=1)
    assert audio_duration(ALSA_CLIP) == pytest.approx(info.duration)
    assert 0.05 < np.max(np.abs(x)) <= 1.0
    assert np.all(np.isfinite(x))


def test_other_target_rate(tmp_path):
    path = tmp_path / "tone.wav"
    sf.write(path, sine(440, 1.0, 16_000), 16_000)
    assert len(load_audio(path, sr=22_050)) == 22_050
    assert len(load_audio(path)) == 16_000


def test_save_wav_round_trip(tmp_path):
    x = sine(300, 0.5, SAMPLE_RATE)
    x[0] = 1.7  # out of range: clipped, not wrapped around
    path = tmp_path / "sub" / "out.wav"
    save_wav(path, x, SAMPLE_RATE)
    y = load_audio(path)
    assert y.shape == x.shape
    assert y[0] == pytest.approx(1.0, abs=1e-4)
    np.testing.assert_allclose(y[1:], x[1:], atol=1e-4)


def assert_one_line_error(excinfo, path: Path) -> None:
    message = str(excinfo.value)
    assert str(path) in message
    assert "\n" not in message


def test_missing_file(tmp_path):
    path = tmp_path / "nope.wav"
    with pytest.raises(TalkmeshError, match="not found") as e:
        load_audio(path)
    assert_one_line_error(e, path)


def test_empty_file(tmp_path):
    path = tmp_path / "empty.wav"
    path.touch()
    with pytest.raises(TalkmeshError, match="empty") as e:
        load_audio(path)
    assert_one_line_error(e, path)


def test_wav_with_no_samples(tmp_path):
    path = tmp_path / "header_only.wav"
    sf.write(path, np.zeros(0, np.float32), 16_000)
    with pytest.raises(TalkmeshError, match="no audio samples") as e:
        load_audio(path)
    assert_one_line_error(e, path)


@pytest.mark.parametrize("name", ["notes.wav", "notes.mp3"])
def test_text_file_renamed_as_audio(tmp_path, name):
    path = tmp_path / name
    path.write_text("these are my lecture notes,\nnot a recording\n" * 20)
    with pytest.raises(TalkmeshError, match="cannot read audio") as e:
        load_audio(path)
    assert_one_line_error(e, path)


def test_directory(tmp_path):
    with pytest.raises(TalkmeshError, match="folder") as e:
        load_audio(tmp_path)
    assert_one_line_error(e, tmp_path)


@pytest.mark.parametrize("ext", ["wav", "mp3"])
def test_overlong_file_is_refused(tmp_path, monkeypatch, ext):
    path = tmp_path / f"long.{ext}"
    if ext == "wav":
        sf.write(path, sine(440, 2.0, 16_000), 16_000)
    else:
        ffmpeg("-f", "lavfi", "-i", "sine=frequency=440:duration=2", str(path))
    monkeypatch.setattr(audio_module, "MAX_DURATION_S", 1.0)
    with pytest.raises(TalkmeshError, match="long, more than the 1.0 s accepted") as e:
        load_audio(path)
    assert_one_line_error(e, path)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_float_wav_with_nan_or_inf_samples_is_refused(tmp_path, bad):
    path = tmp_path / "broken.wav"
    wave = sine(220, 0.5, 16_000)
    wave[1000:1003] = bad
    sf.write(path, wave, 16_000, subtype="FLOAT")
    with pytest.raises(TalkmeshError, match="NaN or infinite") as e:
        load_audio(path)
    assert_one_line_error(e, path)


def test_wav_cut_short_warns_with_both_durations(tmp_path):
    path = tmp_path / "cut.wav"
    sf.write(path, sine(220, 3.17, 16_000), 16_000, subtype="PCM_16")
    data = path.read_bytes()
    path.write_bytes(data[: 44 + 2 * int(1.6 * 16_000)])  # the header still says 3.17 s
    with pytest.warns(TalkmeshWarning) as caught:
        audio = load_audio(path)
    assert len(audio) == int(1.6 * 16_000)
    (message,) = [str(w.message) for w in caught]
    assert "3.17 s" in message and "1.60 s" in message and str(path) in message


def test_duration_limit_is_the_callers(tmp_path):
    path = tmp_path / "two.wav"
    sf.write(path, sine(220, 2.0, 16_000), 16_000)
    assert len(load_audio(path, max_seconds=2.5)) == 32_000
    with pytest.raises(TalkmeshError, match="2.0 s long, more than the 1.5 s accepted"):
        load_audio(path, max_seconds=1.5)
