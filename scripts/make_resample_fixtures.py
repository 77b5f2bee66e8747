"""Make tests/fixtures/resample_reference.npz: the official codes' resamplers run themselves.

    python scripts/make_resample_fixtures.py   # needs torchaudio, librosa and resampy

For each input rate (22.05, 44.1 and 48 kHz) a test signal (:func:`signal_for`, written as a
16-bit WAV as ``tests/test_resamplers.py`` writes it) is brought to 16 kHz as the official codes do:

* ``sinc_hann``: MeshTalk's ``load_audio``: ``torchaudio.transforms.Resample(sr, 16000)``
  (``torchaudio.functional.resample``'s defaults) on the file's samples;
* ``kaiser_best``: FaceFormer's and CodeTalker's ``librosa.load(path, sr=16000)`` with librosa
  0.8.1's default ``res_type="kaiser_best"`` (resampy), here passed explicitly.

torchaudio's C++ extension is not needed by ``resample``: where the installed one does not load
(built for another torch), it is replaced by an empty module before the import.
"""

from __future__ import annotations

import sys
import tempfile
import types
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "resample_reference.npz"
RATES = (22050, 44100, 48000)
SECONDS = 0.15


def signal_for(sr: int, seconds: float = SECONDS) -> np.ndarray:
    """(S,) float64: a tone, a tone near 16 kHz audio's Nyquist frequency and a chirp to the
    input's Nyquist frequency (what the filters must remove), under full scale."""
    t = np.arange(round(sr * seconds)) / sr
    chirp = np.sin(2 * np.pi * (100 * t + (sr / 2 - 100) / (2 * seconds) * t**2))
    return 0.4 * np.sin(2 * np.pi * 440 * t) + 0.2 * np.sin(2 * np.pi * 7600 * t) + 0.3 * chirp


def _torchaudio_functional():
    import torch

    try:
        import torchaudio.functional as F
    except (OSError, AttributeError, ImportError):
        for name in [m for m in sys.modules if m.startswith("torchaudio")]:
            del sys.modules[name]
        ext = types.ModuleType("torchaudio._extension")
        ext._IS_TORCHAUDIO_EXT_AVAILABLE = ext._IS_RIR_AVAILABLE = ext._IS_ALIGN_AVAILABLE = False
        ext.fail_if_no_rir = ext.fail_if_no_align = lambda f: f
        sys.modules["torchaudio._extension"] = ext
        import torchaudio.functional as F
    return torch, F


def main() -> None:
    import librosa
    import soundfile as sf

    from talkmesh.audio.loading import save_wav

    torch, F = _torchaudio_functional()
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for sr in RATES:
            path = Path(tmp) / f"{sr}.wav"
            save_wav(path, signal_for(sr).astype(np.float32), sr)
            samples, _ = sf.read(str(path), dtype="float32")
            hann = F.resample(torch.from_numpy(samples)[None], sr, 16000)[0].numpy()
            kaiser, _ = librosa.load(str(path), sr=16000, res_type="kaiser_best")
            out[f"sinc_hann_{sr}"] = hann.astype(np.float32)
            out[f"kaiser_best_{sr}"] = kaiser.astype(np.float32)
    np.savez_compressed(OUT, **out)
    print(f"wrote {OUT}: " + ", ".join(f"{k} {v.shape}" for k, v in out.items()))


if __name__ == "__main__":
    main()
