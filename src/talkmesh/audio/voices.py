"""Synthetic voices with exact phone timings, for the synthetic corpus.

Three Debian synthesisers give the times of the phones they actually render:

* MBROLA through espeak-ng: ``espeak-ng -v mb-us1 --pho`` writes the phones with durations in ms
  and ``mbrola`` renders exactly that file, so the durations are the truth. Where the database
  lacks a diphone that espeak-ng asks for, MBROLA renders silence instead; those stretches were
  not said, and :func:`dropped_diphones` makes them pauses.
* Festival: the utterance's ``Segment`` relation holds each phone's end time
  (``utt.save.segs``), for diphone and HTS voices alike.
* espeak-ng's own voices (engine ``espeak-lib``, :func:`espeak_voice`; the multilingual corpus):
  the library reports each phone's first output sample (:mod:`talkmesh.audio.espeak_lib`). A
  phone it names but renders as silence (:func:`silent_phones`) is a pause.

Festival's voices of other languages (:func:`festival_voice`; the multilingual corpus) take the
same Festival path, their phone sets mapped by :mod:`talkmesh.audio.festival_voices`.

Twelve voices: the four MBROLA voices at two prosody settings (pitch and rate change the
rendered durations, which the .pho carries) and four Festival voices. They make the default
corpus (its subjects take the voices in this order).

More voices follow them for larger corpora (``talkmesh synth --subjects N`` beyond 12): Festival's
``don`` diphone voice (exact timings), then every other offline English synthesiser in Debian, whose
phone times come from forcing the text onto the audio with PocketSphinx (``engine`` ``espeak``,
``flite``, ``pico``; :func:`synthesize_aligned`): two espeak-ng formant voices (the
others' speech PocketSphinx could not always align),
Flite's ``rms``, ``awb``, ``slt`` and ``kal16``, and SVOX Pico's US and British voices.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from talkmesh.audio.phonemes import ARPABET_PHONES, BILABIALS, SILENCE, Phone
from talkmesh.errors import TalkmeshError

MBROLA_DIR = Path("/usr/share/mbrola")
MBROLA_RATE = 16_000  # Hz of the us1/us2/us3/en1 databases
FESTIVAL_RATE = 16_000  # Hz of the diphone voices; HTS voices are resampled to it below


@dataclass(frozen=True)
class Voice:
    """A synthesiser voice: ``engine`` is "mbrola", "festival" or "espeak-lib" (espeak-ng's own
    voices through its library: exact phone times), or "espeak", "flite" or "pico" (phone times
    by forced alignment)."""

    name: str
    engine: str
    voice: str  # mb-us1 ... for MBROLA, cmn-latn-pinyin+f2 for espeak-lib, Festival's function
    pitch: int = 50  # espeak-ng -p (0-99), MBROLA and espeak-ng voices
    speed: int = 160  # espeak-ng -s (words per minute), MBROLA and espeak-ng voices
    description: str = ""
    phoneset: str = "radio"  # Festival voices: "radio" (US), "mrpa" (British rab), or a key of
    # talkmesh.audio.festival_voices.PHONE_TABLES for the other languages
    language: str = "en"  # espeak-ng language; MBROLA voices of other languages map their SAMPA
    # dialect through talkmesh.audio.languages.sampa_label


VOICES: tuple[Voice, ...] = (
    Voice("mb-us1", "mbrola", "mb-us1", 50, 160, "US female (MBROLA us1)"),
    Voice("mb-us2", "mbrola", "mb-us2", 50, 160, "US male (MBROLA us2)"),
    Voice("mb-us3", "mbrola", "mb-us3", 50, 160, "US male (MBROLA us3)"),
    Voice("mb-en1", "mbrola", "mb-en1", 50, 160, "British male (MBROLA en1)"),
    Voice("mb-us1-high", "mbrola", "mb-us1", 75, 185, "US female, higher and faster"),
    Voice("mb-us2-low", "mbrola", "mb-us2", 25, 140, "US male, lower and slower"),
    Voice("mb-us3-fast", "mbrola", "mb-us3", 60, 195, "US male, fast"),
    Voice("mb-en1-slow", "mbrola", "mb-en1", 35, 135, "British male, slow"),
    Voice(
        "fest-kal", "festival", "voice_kal_diphone", description="US male (Festival kal diphone)"
    ),
    Voice(
        "fest-ked", "festival", "voice_ked_diphone", description="US male (Festival ked diphone)"
    ),
    Voice(
        "fest-rab",
        "festival",
        "voice_rab_diphone",
        description="British male (Festival rab diphone)",
        phoneset="mrpa",
    ),
    Voice(
        "fest-slt",
        "festival",
        "voice_cmu_us_slt_arctic_hts",
        description="US female (Festival slt HTS)",
    ),
    # beyond the default corpus's twelve
    Voice(
        "fest-don",
        "festival",
        "voice_don_diphone",
        description="British male (Festival don diphone)",
        phoneset="mrpa",
    ),
    Voice("espeak-gb-f2", "espeak", "en+f2", 55, 160, "British female (espeak-ng formant)"),
    Voice("espeak-us-f5", "espeak", "en-us+f5", 60, 185, "US female, fast (espeak-ng)"),
    Voice("flite-rms", "flite", "rms", description="US male (Flite rms)"),
    Voice("flite-awb", "flite", "awb", description="Scottish male (Flite awb)"),
    Voice("flite-slt", "flite", "slt", description="US female (Flite slt)"),
    Voice("flite-kal16", "flite", "kal16", description="US male (Flite kal16 diphone)"),
    Voice("pico-us", "pico", "en-US", description="US female (SVOX Pico)"),
    Voice("pico-gb", "pico", "en-GB", description="British female (SVOX Pico)"),
)
ALIGNED_ENGINES = {"espeak": "espeak-ng", "flite": "flite", "pico": "pico2wave"}  # -> program
VOICE_NAMES = tuple(v.name for v in VOICES)

# MBROLA (SAMPA, as espeak-ng writes it for us1-3 and en1) -> ARPABET.
# fmt: skip keeps this lookup table a compact block (one pair a line would be 70 lines).
SAMPA_TO_ARPABET = {
    "_": SILENCE, "p": "P", "p_h": "P", "b": "B", "t": "T", "t_h": "T", "d": "D", "k": "K", "k_h": "K",
    "g": "G", "f": "F", "v": "V", "T": "TH", "D": "DH", "s": "S", "z": "Z", "S": "SH", "Z": "ZH",
    "h": "HH", "tS": "CH", "dZ": "JH", "m": "M", "n": "N", "N": "NG", "l": "L", "r": "R", "w": "W",
    "j": "Y", "i": "IY", "i:": "IY", "I": "IH", "E": "EH", "e": "EH", "{": "AE", "A": "AA", "A:": "AA",
    "Q": "AA", "V": "AH", "O": "AO", "O:": "AO", "O2": "AO", "U": "UH", "u": "UW", "u:": "UW",
    "@": "AH", "5": "L", "r=": "ER", "3:": "ER", "3": "ER", "@U": "OW", "oU": "OW", "EI": "EY",
    "eI": "EY", "AI": "AY", "aI": "AY", "OI": "OY", "aU": "AW", "I@": "IH", "e@": "EH", "U@": "UH",
    "4": "T", "R": "R", "l=": "L", "n=": "N", "m=": "M", "?": SILENCE,
}  # fmt: skip

# Festival's US voices use the radio phone set (lower-case ARPABET with "ax" and "pau"); the
# British rab voice uses MRPA, mapped here to the nearest ARPABET phone.
FESTIVAL_TO_ARPABET = {p.lower(): p for p in ARPABET_PHONES} | {
    "pau": SILENCE,
    "ax": "AH",
    "h#": SILENCE,
}
# fmt: skip keeps this lookup table a compact block.
MRPA_TO_ARPABET = {
    "#": SILENCE, "@": "AH", "@@": "ER", "a": "AE", "aa": "AA", "ai": "AY", "au": "AW", "e": "EH",
    "e@": "EH", "ei": "EY", "h": "HH", "i": "IH", "i@": "IH", "ii": "IY", "o": "AA", "oi": "OY",
    "oo": "AO", "ou": "OW", "u": "UH", "u@": "UH", "uh": "AH", "uu": "UW", "y": "Y",
}  # fmt: skip
PHONESETS = {"radio": FESTIVAL_TO_ARPABET, "mrpa": FESTIVAL_TO_ARPABET | MRPA_TO_ARPABET}


def available_voices() -> list[Voice]:
    """The voices whose synthesiser and data are installed."""
    out = []
    espeak, mbrola, festival = (shutil.which(x) for x in ("espeak-ng", "mbrola", "festival"))
    for v in VOICES:
        if v.engine == "mbrola" and espeak and mbrola and _mbrola_db(v).is_file():
            out.append(v)
        elif v.engine == "festival" and festival and _festival_voice_installed(v):
            out.append(v)
        elif v.engine in ALIGNED_ENGINES and shutil.which(ALIGNED_ENGINES[v.engine]):
            out.append(v)
    return out


def _festival_voice_installed(v: Voice) -> bool:
    """The default corpus's Festival voices are checked when they run (as before); the extra
    ones only count where their folder is installed."""
    if v.name in VOICE_NAMES[:12]:
        return True
    name = v.voice.removeprefix("voice_")
    return any(Path("/usr/share/festival/voices").glob(f"*/{name}"))


def get_voice(name: str) -> Voice:
    for v in VOICES:
        if v.name == name:
            return v
    raise TalkmeshError(f"unknown voice '{name}': use one of {', '.join(VOICE_NAMES)}")


def _mbrola_db(v: Voice) -> Path:
    db = v.voice.removeprefix("mb-")
    return MBROLA_DIR / db / db


def _run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    try:
        return subprocess.run(cmd, capture_output=True, check=True, **kw)
    except FileNotFoundError:
        raise TalkmeshError(
            f"{cmd[0]} is not installed: run `make setup` (Debian packages mbrola, festival)"
        ) from None
    except subprocess.CalledProcessError as e:
        msg = (e.stderr or b"").decode(errors="replace").strip().splitlines()
        raise TalkmeshError(f"{cmd[0]} failed: {msg[-1] if msg else e.returncode}") from None


def _phones_from_pho(pho: str, language: str = "en") -> list[Phone]:
    """An MBROLA .pho file -> timed phones: each phone lasts exactly the ms the file gives it.

    English voices use the ARPABET table above (an unknown symbol is an error); other languages'
    SAMPA dialects go through :func:`talkmesh.audio.languages.sampa_label`.
    """
    from talkmesh.audio.languages import sampa_label

    english = language.split("-")[0] == "en"
    phones, t = [], 0.0
    for line in pho.splitlines():
        parts = line.split()
        if len(parts) < 2 or line.startswith(";"):
            continue
        sym, ms = parts[0], float(parts[1])
        if english:
            if sym not in SAMPA_TO_ARPABET:
                raise TalkmeshError(f"MBROLA phone '{sym}' has no ARPABET mapping")
            label = SAMPA_TO_ARPABET[sym]
        else:
            label = sampa_label(sym)
        phones.append(Phone(label, t, t + ms / 1000.0))
        t += ms / 1000.0
    return phones


# espeak-ng's Hebrew phone table (he_phtrans) serves both Hebrew databases, which spell their
# phones differently: hb1 has r and x but no glottal stop, R or X; hb2 has ?, R and X but no r or
# x. Unmapped, MBROLA drops every diphone with one of them. None: the phone is left out.
PHO_FIXES: dict[str, dict[str, str | None]] = {
    "hb1": {'Q"': "r", "r/": "r", "R": "r", "X": "x", "?": None},
    "hb2": {'Q"': "R", "r/": "R", "r": "R", "x": "X"},
}


def fix_pho(pho: str, db: str) -> str:
    """``pho`` with each phone respelled as the database ``db`` spells it (:data:`PHO_FIXES`)."""
    fixes = PHO_FIXES.get(db)
    if not fixes:
        return pho
    lines = []
    for line in pho.splitlines():
        parts = line.split(maxsplit=1)
        if parts and line[0] != ";" and parts[0] in fixes:
            if fixes[parts[0]] is None:
                continue
            line = " ".join([fixes[parts[0]], *parts[1:]])
        lines.append(line)
    return "\n".join(lines) + "\n"


# mbrola's message for a diphone its database lacks; it renders the diphone as silence
_UNKNOWN_DIPHONE = re.compile(r"Warning: (\S+)-(\S+) unknown, replaced with _-_")
DIGITAL_SILENCE_DB = -90.0  # a 5 ms block this quiet is silence the synthesiser wrote


def dropped_diphones(
    pho: str, messages: str, audio: np.ndarray, sr: int
) -> list[tuple[float, float]]:
    """The stretches (start, end in s) that MBROLA left silent because its database lacks the
    diphone: each diphone its ``messages`` name (``Warning: a-X unknown, replaced with _-_``, in
    the order of the .pho) spans the middle of its first phone to the middle of its second; the
    runs of digital silence in ``audio`` that meet such a span are the stretches."""
    rows = [r for r in (line.split() for line in pho.splitlines() if line[:1] != ";") if len(r) > 1]
    # mbrola starts and ends in silence: a pause of no length either side
    syms, mids, t = ["_"], [0.0], 0.0
    for r in rows:
        ms = float(r[1]) / 1000.0
        syms.append(r[0])
        mids.append(t + ms / 2)
        t += ms
    syms.append("_")
    mids.append(t)
    spans, k = [], 0
    for a, b in _UNKNOWN_DIPHONE.findall(messages):
        at = next((i for i in range(k, len(syms) - 1) if (syms[i], syms[i + 1]) == (a, b)), None)
        if at is not None:  # (a message for a pair the .pho does not have is passed over)
            spans.append((mids[at], mids[at + 1]))
            k = at + 1
    if not spans:
        return []
    hop = max(1, sr // 200)
    blocks = np.asarray(audio[: len(audio) // hop * hop], np.float64).reshape(-1, hop)
    quiet = np.r_[False, 10 * np.log10((blocks**2).mean(1) + 1e-30) < DIGITAL_SILENCE_DB, False]
    starts = np.flatnonzero(~quiet[:-1] & quiet[1:])
    ends = np.flatnonzero(quiet[:-1] & ~quiet[1:])
    runs = [(s * hop / sr, e * hop / sr) for s, e in zip(starts, ends)]
    return [r for r in runs if any(r[0] < b and a < r[1] for a, b in spans)]


def without(phones: list[Phone], stretches: list[tuple[float, float]]) -> list[Phone]:
    """``phones`` with each stretch a pause: phones inside it go, phones across its edges keep
    the part outside (a part shorter than the 5 ms the stretches are measured in joins the
    pause)."""
    out = list(phones)
    for lo, hi in stretches:
        cut = []
        for p in out:
            if p.end <= lo or p.start >= hi:
                cut.append(p)
                continue
            if p.start < lo - 0.005:
                cut.append(Phone(p.label, p.start, lo))
            elif p.start < lo:
                lo = p.start
            if p.end > hi + 0.005:
                cut.append(Phone(p.label, hi, p.end))
            elif p.end > hi:
                hi = p.end
        cut.append(Phone(SILENCE, lo, hi))
        out = sorted(cut, key=lambda p: p.start)
    return out


def mbrola_voice(db: str, language: str, pitch: int = 50, speed: int = 160) -> Voice:
    """An MBROLA voice of any language (``db``: the database, e.g. ``de2``), refused when it is
    reserved for outside checks."""
    from talkmesh.audio.languages import check_not_reserved

    check_not_reserved(db, language)
    name = f"mb-{db}" + ("" if (pitch, speed) == (50, 160) else f"-p{pitch}-s{speed}")
    return Voice(
        name, "mbrola", f"mb-{db}", pitch, speed, f"{language} (MBROLA {db})", language=language
    )


def espeak_voice(voice: str, language: str, pitch: int = 50, speed: int = 160) -> Voice:
    """espeak-ng's own voice ``voice`` (``cmn-latn-pinyin+m3``: a variant after '+') for the
    ``espeak-lib`` engine, refused when its language is reserved for outside checks."""
    from talkmesh.audio.languages import check_espeak_not_reserved

    check_espeak_not_reserved(voice, language)
    name = f"es-{voice}" + ("" if (pitch, speed) == (50, 160) else f"-p{pitch}-s{speed}")
    return Voice(
        name,
        "espeak-lib",
        voice,
        pitch,
        speed,
        f"{language} (espeak-ng {voice})",
        language=language,
    )


def festival_voice(language: str, speaker: str, speed: int = 160) -> Voice:
    """Festival's voice ``speaker`` of ``language`` (:mod:`talkmesh.audio.festival_voices`),
    refused when it is reserved for outside checks. ``speed`` stretches every duration by
    160 / speed (Festival's ``Duration_Stretch``) where the voice honours it (not the unit
    selection and HTS voices); the Segment times are what it rendered."""
    from talkmesh.audio.festival_voices import get_festival_voice
    from talkmesh.audio.languages import check_festival_not_reserved

    v = get_festival_voice(language, speaker)
    check_festival_not_reserved(v.function, language)
    speed = speed if v.stretches else 160
    name = f"fest-{language}-{speaker}" + ("" if speed == 160 else f"-s{speed}")
    return Voice(
        name, "festival", v.function, speed=speed, description=v.description,
        phoneset=v.phoneset, language=language,
    )  # fmt: skip


SILENT_PHONE_DB = -80.0  # a speech phone this quiet all through was not said


def silent_phones(phones: list[Phone], audio: np.ndarray, sr: int) -> list[tuple[float, float]]:
    """The speech phones (start, end in s) whose audio is at most :data:`SILENT_PHONE_DB` over
    the whole phone: phones the synthesiser named but did not say (espeak-ng's Korean gives a
    coda /l/ before a consonant 40-70 ms of digital silence). A /p b m/ is kept: its lips close
    whether or not it is heard."""
    out = []
    for p in phones:
        if p.label == SILENCE or p.label in BILABIALS or p.end <= p.start:
            continue
        seg = np.asarray(audio[int(p.start * sr) : int(p.end * sr)], np.float64)
        if len(seg) and 10 * np.log10((seg**2).mean() + 1e-30) <= SILENT_PHONE_DB:
            out.append((p.start, p.end))
    return out


def espeak_phones(events: list[tuple[str, int]], num_samples: int, sr: int, language: str):
    """The library's phoneme events -> contiguous timed phones: each phone from its event's
    sample to the next event's (the last to the end of the audio), silences merged."""
    from talkmesh.audio.languages import espeak_label

    starts = [min(max(s, 0), num_samples) for _, s in events] + [num_samples]
    phones = [
        Phone(espeak_label(m, language), a / sr, b / sr)
        for (m, _), a, b in zip(events, starts, starts[1:])
    ]
    if not any(p.label != SILENCE and p.end > p.start for p in phones):
        return []
    return _merge(phones, num_samples / sr)


def synthesize_espeak_lib(voice: Voice, text: str, wav: Path) -> tuple[list[Phone], int]:
    """Render ``text`` with espeak-ng's own voice into ``wav``; returns (phones, sample rate),
    each phone with the times the synthesiser's phoneme events gave it."""
    import soundfile as sf

    from talkmesh.audio.espeak_lib import render
    from talkmesh.audio.languages import check_espeak_not_reserved

    check_espeak_not_reserved(voice.voice, voice.language)
    out = render(voice.voice, text, voice.pitch, voice.speed)
    phones = espeak_phones(out.events, len(out.audio), out.sample_rate, out.language)
    if not phones:
        raise TalkmeshError(
            f"espeak-ng voice '{voice.voice}' made no phones of {text[:40]!r}: "
            "give it text in its language (pinyin with tone numbers for cmn-latn-pinyin)"
        )
    sf.write(str(wav), out.audio, out.sample_rate, format="WAV", subtype="PCM_16")
    audio = out.audio.astype(np.float32) / 32768.0
    said = without(phones, silent_phones(phones, audio, out.sample_rate))
    return _merge(said, len(out.audio) / out.sample_rate), out.sample_rate


def _merge(phones: list[Phone], duration: float) -> list[Phone]:
    """Contiguous phones from 0 to ``duration``: silences merged, leading/trailing gaps filled."""
    out: list[Phone] = []
    for p in phones:
        if p.end <= p.start:
            continue
        if out and p.label == SILENCE and out[-1].label == SILENCE:
            out[-1] = Phone(SILENCE, out[-1].start, p.end)
        else:
            out.append(p)
    if not out or out[0].start > 0:
        out.insert(0, Phone(SILENCE, 0.0, out[0].start if out else duration))
    if out[-1].end < duration:
        if out[-1].label == SILENCE:
            out[-1] = Phone(SILENCE, out[-1].start, duration)
        else:
            out.append(Phone(SILENCE, out[-1].end, duration))
    elif out[-1].end > duration:
        out = [p for p in out if p.start < duration]
        out[-1] = Phone(out[-1].label, out[-1].start, duration)
    return out


def synthesize_mbrola(voice: Voice, text: str, wav: Path) -> tuple[list[Phone], int]:
    """Render ``text`` with an MBROLA voice into ``wav``; returns (phones, sample rate)."""
    pho = _run(
        [
            "espeak-ng",
            "-v",
            voice.voice,
            "-p",
            str(voice.pitch),
            "-s",
            str(voice.speed),
            "-q",
            "--pho",
            text,
        ]
    ).stdout.decode()
    pho = fix_pho(pho, voice.voice.removeprefix("mb-"))
    with tempfile.NamedTemporaryFile("w", suffix=".pho", delete=False) as f:
        f.write(pho)
    try:
        done = _run(["mbrola", "-e", str(_mbrola_db(voice)), f.name, str(wav)])
    finally:
        os.unlink(f.name)
    import soundfile as sf

    audio, sr = sf.read(str(wav), dtype="float32")
    if audio.ndim > 1:
        audio = audio.mean(axis=1)
    phones = _phones_from_pho(pho, voice.language)
    messages = (done.stdout + done.stderr).decode(errors="replace")
    phones = without(phones, dropped_diphones(pho, messages, audio, sr))
    return _merge(phones, len(audio) / sr), sr


def _scheme_string(text: str) -> str:
    return '"' + text.replace("\\", " ").replace('"', " ") + '"'


def _festival_script(voice: Voice, items: list[tuple[str, Path]], tmp: Path) -> Path:
    """The Scheme script that speaks each item, in the character set the voice reads."""
    from talkmesh.audio.festival_voices import ENCODINGS

    lines = [f"({voice.voice})"]
    if voice.speed != 160:
        stretch = 160 / voice.speed  # times the voice's own (the NSK voices set 1.4)
        lines.append("(set! d (Parameter.get 'Duration_Stretch)) (if (not d) (set! d 1.0))")
        lines.append(f"(Parameter.set 'Duration_Stretch (* d {stretch}))")
    for k, (text, wav) in enumerate(items):
        lines.append(f"(set! utt (SynthText {_scheme_string(text)}))")
        lines.append(f'(utt.save.wave utt "{wav}" \'riff)')
        lines.append(f'(utt.save.segs utt "{tmp / f"{k}.segs"}")')
    encoding = ENCODINGS.get(voice.phoneset, "utf-8")
    try:
        data = ("\n".join(lines) + "\n").encode(encoding)
    except UnicodeEncodeError as e:
        bad = e.object[e.start : e.end]
        raise TalkmeshError(
            f"{voice.name} reads {encoding} text and cannot read {bad!r}: give it text in its "
            "language, in a folder whose path it can write"
        ) from None
    script = tmp / "run.scm"
    script.write_bytes(data)
    return script


def _festival_phones(segs: Path, voice: Voice) -> list[Phone]:
    """An ``utt.save.segs`` file -> phones, each ending where the Segment relation ends it."""
    from talkmesh.audio.festival_voices import PHONE_TABLES, festival_label

    if not segs.is_file():
        raise TalkmeshError(
            f"Festival did not speak with {voice.voice}: is its voice installed? (make setup)"
        )
    phones, t = [], 0.0
    for line in segs.read_text(encoding="latin-1").splitlines():
        parts = line.split()
        if len(parts) != 3 or line.startswith("#"):
            continue
        end, sym = float(parts[0]), parts[2]
        if voice.phoneset in PHONE_TABLES:
            label = festival_label(sym, voice.phoneset)
        elif sym in PHONESETS[voice.phoneset]:
            label = PHONESETS[voice.phoneset][sym]
        else:
            raise TalkmeshError(f"Festival phone '{sym}' has no ARPABET mapping")
        phones.append(Phone(label, t, end))
        t = end
    return phones


def synthesize_festival(
    voice: Voice, items: list[tuple[str, Path]]
) -> list[tuple[list[Phone], int]]:
    """Render several (text, wav) pairs with one Festival process; returns phones per item."""
    import soundfile as sf

    from talkmesh.audio.languages import check_festival_not_reserved

    check_festival_not_reserved(voice.voice, voice.language)
    with tempfile.TemporaryDirectory() as tmp:
        _run(["festival", "-b", str(_festival_script(voice, items, Path(tmp)))])
        out = []
        for k, (_, wav) in enumerate(items):
            phones = _festival_phones(Path(tmp) / f"{k}.segs", voice)
            info = sf.info(str(wav))
            out.append((_merge(phones, info.frames / info.samplerate), info.samplerate))
    return out


def _aligned_command(voice: Voice, wav: Path, text_file: Path, text: str) -> list[str]:
    if voice.engine == "espeak":
        pitch, speed = ["-p", str(voice.pitch)], ["-s", str(voice.speed)]
        return [
            "espeak-ng",
            "-v",
            voice.voice,
            *pitch,
            *speed,
            "-w",
            str(wav),
            "-f",
            str(text_file),
        ]
    if voice.engine == "flite":
        return ["flite", "-voice", voice.voice, "-f", str(text_file), "-o", str(wav)]
    return ["pico2wave", "-l", voice.voice, "-w", str(wav), "--", text]


def synthesize_aligned(voice: Voice, text: str, wav: Path) -> tuple[list[Phone], int]:
    """Render ``text`` with an espeak-ng, Flite or Pico voice into ``wav`` (a ``.wav`` path);
    the phones are the text forced onto the audio (PocketSphinx), as for a real recording."""
    import soundfile as sf

    from talkmesh.audio.loading import SAMPLE_RATE, load_audio
    from talkmesh.audio.phonemes import recognize_phones

    with tempfile.TemporaryDirectory() as tmp:
        text_file = Path(tmp) / "text.txt"
        text_file.write_text(text + "\n")
        _run(_aligned_command(voice, Path(wav), text_file, text))
    info = sf.info(str(wav))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clip the transcript cannot be forced onto has no truth
        try:
            phones = recognize_phones(load_audio(wav), SAMPLE_RATE, text=text)
        except Warning as w:
            raise TalkmeshError(f"{voice.name}: {text!r}: {w}") from None
    return _merge(phones, info.frames / info.samplerate), info.samplerate


def synthesize(voice: Voice, items: list[tuple[str, Path]]) -> list[tuple[list[Phone], int]]:
    """Speak each (text, wav path) with ``voice``; returns (phones, sample rate) per item."""
    if voice.engine == "festival":
        return synthesize_festival(voice, items)
    if voice.engine == "espeak-lib":
        return [synthesize_espeak_lib(voice, text, wav) for text, wav in items]
    if voice.engine in ALIGNED_ENGINES:
        return [synthesize_aligned(voice, text, wav) for text, wav in items]
    return [synthesize_mbrola(voice, text, wav) for text, wav in items]


def phone_coverage(phones: list[Phone]) -> dict[str, int]:
    """How often each ARPABET phone occurs."""
    labels = [p.label for p in phones if p.label != SILENCE]
    return {p: int(n) for p, n in zip(*np.unique(labels, return_counts=True))}
