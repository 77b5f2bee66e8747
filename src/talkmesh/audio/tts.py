"""Synthetic speech with timed phones, for demos and tests: espeak-ng (a Debian package).

The phone timings come from forcing the text onto the synthesised audio with PocketSphinx
(:func:`talkmesh.audio.phonemes.recognize_phones`), which works for any espeak-ng voice. Reading the
synthesiser's own phone timings (``espeak-ng --pho`` with an MBROLA voice) would be exact; that
is not done yet.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

from talkmesh.audio.loading import SAMPLE_RATE, load_audio
from talkmesh.audio.phonemes import Phone, recognize_phones
from talkmesh.errors import TalkmeshError

ESPEAK = "espeak-ng"
DEFAULT_VOICE = "en-us"


def synthesize_speech(text: str, path: str | Path, voice: str = DEFAULT_VOICE) -> list[Phone]:
    """Speak ``text`` into a WAV file and return its timed phones.

    Args:
        text: what to say.
        path: the WAV file to write (espeak-ng's native 22.05 kHz mono).
        voice: an espeak-ng voice (``espeak-ng --voices`` lists them).

    Returns:
        Contiguous phones covering the written audio, as :func:`recognize_phones` returns them.
    """
    if not text.strip():
        raise TalkmeshError("nothing to say: pass a non-empty text to synthesise")
    exe = shutil.which(ESPEAK)
    if exe is None:
        raise TalkmeshError(
            "speech synthesis needs espeak-ng: install it with `sudo apt-get install espeak-ng` "
            "(or `make setup`)"
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The text goes through stdin so that one starting with "-" is not read as an option.
    proc = subprocess.run(
        [exe, "-v", voice, "-w", str(path), "--stdin"],
        input=text,
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        reason = " ".join(proc.stderr.split()) or f"exit status {proc.returncode}"
        raise TalkmeshError(f"espeak-ng could not synthesise with voice '{voice}': {reason}")
    return recognize_phones(load_audio(path), SAMPLE_RATE, text=text)
