"""What an MBROLA voice did not say is a pause: a diphone its database lacks is rendered as
silence, so the phones there go, and the Hebrew voices get phones their databases have."""

import numpy as np
import soundfile as sf

from talkmesh.audio.languages import get_language
from talkmesh.audio.phonemes import SILENCE, Phone
from talkmesh.audio.voices import (
    SILENT_PHONE_DB,
    dropped_diphones,
    espeak_voice,
    fix_pho,
    mbrola_voice,
    silent_phones,
    synthesize_espeak_lib,
    synthesize_mbrola,
    without,
)

SR = 16_000
PHO = "_\t50\na\t100\nb\t100\nk\t100\nd\t100\n_\t50\n"


def _speech(seconds: float) -> np.ndarray:
    return (0.1 * np.random.default_rng(0).standard_normal(int(seconds * SR))).astype(np.float32)


def test_a_dropped_diphone_is_a_pause_and_other_silences_are_not():
    audio = _speech(0.5)
    audio[int(0.2 * SR) : int(0.3 * SR)] = 0  # the b-k diphone: middle of b to middle of k
    audio[int(0.37 * SR) : int(0.4 * SR)] = 0  # a stop's silent closure inside d: said
    messages = "Warning: b-k unknown, replaced with _-_\n"
    stretches = dropped_diphones(PHO, messages, audio, SR)
    assert np.allclose(stretches, [(0.2, 0.3)])
    phones = [Phone(SILENCE, 0, 0.05), Phone("AA", 0.05, 0.15), Phone("B", 0.15, 0.25)]
    phones += [Phone("K", 0.25, 0.35), Phone("D", 0.35, 0.45), Phone(SILENCE, 0.45, 0.5)]
    cut = without(phones, stretches)
    assert [(p.label, round(p.start, 3), round(p.end, 3)) for p in cut] == [
        (SILENCE, 0, 0.05),
        ("AA", 0.05, 0.15),
        ("B", 0.15, 0.2),
        (SILENCE, 0.2, 0.3),
        ("K", 0.3, 0.35),
        ("D", 0.35, 0.45),
        (SILENCE, 0.45, 0.5),
    ]
    # no message, nothing dropped, even where the audio is silent
    assert dropped_diphones(PHO, "", audio, SR) == []
    # a message the .pho does not have (in order) drops nothing either
    assert dropped_diphones(PHO, "Warning: d-a unknown, replaced with _-_", audio, SR) == []


def test_a_phone_inside_a_dropped_stretch_goes():
    phones = [Phone("AA", 0, 0.1), Phone("B", 0.1, 0.2), Phone("AA", 0.2, 0.3)]
    cut = without(phones, [(0.05, 0.25)])
    assert [p.label for p in cut] == ["AA", SILENCE, "AA"]
    assert [(p.start, p.end) for p in cut] == [(0, 0.05), (0.05, 0.25), (0.25, 0.3)]


def _silent_speech_phones(phones, audio, sr, db=-90.0):
    """Speech phones whose whole span is under ``db`` (digital silence: nothing was said)."""
    out = []
    for p in phones:
        seg = np.asarray(audio[int(p.start * sr) : int(p.end * sr)], np.float64)
        if p.label != SILENCE and len(seg) and 10 * np.log10(np.mean(seg**2) + 1e-30) <= db:
            out.append(p)
    return out


def test_a_voice_that_lacks_diphones_says_only_what_it_has(tmp_path):
    """Debian's nl1 lacks most of the diphones espeak-ng asks for (@-k, k-A, ...)."""
    text = "De kat zit op de mat en de hond slaapt."
    phones, sr = synthesize_mbrola(mbrola_voice("nl1", "nl"), text, tmp_path / "nl1.wav")
    audio, _ = sf.read(tmp_path / "nl1.wav", dtype="float32")
    assert not _silent_speech_phones(phones, audio, sr)
    said = sum(p.end - p.start for p in phones if p.label != SILENCE)
    assert said < 0.5 * phones[-1].end  # most of it was silence
    # a voice with every diphone: the phones are the .pho's, as before
    full, sr = synthesize_mbrola(mbrola_voice("nl3", "nl"), text, tmp_path / "nl3.wav")
    audio, _ = sf.read(tmp_path / "nl3.wav", dtype="float32")
    labels = [p.label for p in full if p.label != SILENCE]
    assert len(labels) >= 25 and not _silent_speech_phones(full, audio, sr)


def test_hebrew_has_its_vowels_in_both_voices(tmp_path):
    for db in ("hb1", "hb2"):
        voice = mbrola_voice(db, "he")
        for k, text in enumerate(get_language("he").sentences):
            phones, sr = synthesize_mbrola(voice, text, tmp_path / f"{db}_{k}.wav")
            audio, _ = sf.read(tmp_path / f"{db}_{k}.wav", dtype="float32")
            labels = [p.label for p in phones]
            vowels = [x for x in labels if x in {"AA", "EH", "IY", "OW", "UW"}]
            assert len(vowels) >= 0.3 * len([x for x in labels if x != SILENCE]), (db, labels)
            assert not _silent_speech_phones(phones, audio, sr), (db, text)
            assert {"M", "B", "P"} & set(labels)


def test_the_hebrew_databases_get_phones_they_spell():
    pho = '?\t50\na\t80\nQ"\t60\nX\t70\nr/\t40\n_\t10\n'
    assert fix_pho(pho, "hb1").split() == ["a", "80", "r", "60", "x", "70", "r", "40", "_", "10"]
    assert fix_pho(pho, "hb2").split()[::2] == ["?", "a", "R", "X", "R", "_"]
    assert fix_pho(pho, "us1") == pho


def test_a_diphone_from_or_into_the_edge_silence_is_found():
    """mbrola starts and ends in silence: the first phone's diphone from it can be missing too."""
    pho = "b\t100\na\t100\n"
    audio = _speech(0.2)
    audio[: int(0.05 * SR)] = 0
    messages = "Warning: _-b unknown, replaced with _-_\nWarning: x-y unknown, replaced with _-_\n"
    assert np.allclose(dropped_diphones(pho, messages, audio, SR), [(0.0, 0.05)])
    # a message that matches nothing does not hide the ones after it
    audio[int(0.15 * SR) :] = 0
    messages += "Warning: a-_ unknown, replaced with _-_\n"
    assert np.allclose(dropped_diphones(pho, messages, audio, SR), [(0.0, 0.05), (0.15, 0.2)])


def test_a_phone_rendered_as_silence_is_a_pause_but_a_silent_bilabial_is_kept():
    audio = _speech(0.4)
    audio[int(0.1 * SR) : int(0.16 * SR)] = 0  # an /l/ the synthesiser named but did not say
    audio[int(0.25 * SR) : int(0.3 * SR)] = 0  # an unreleased /p/: its lips still close
    phones = [Phone("AA", 0.0, 0.1), Phone("L", 0.1, 0.16), Phone("K", 0.16, 0.25)]
    phones += [Phone("P", 0.25, 0.3), Phone("IY", 0.3, 0.4)]
    assert silent_phones(phones, audio, SR) == [(0.1, 0.16)]
    cut = without(phones, silent_phones(phones, audio, SR))
    assert [p.label for p in cut] == ["AA", SILENCE, "K", "P", "IY"]


def test_espeak_korean_says_every_phone_it_names(tmp_path):
    """espeak-ng's Korean renders a coda /l/ before a consonant as digital silence (-100 dB)."""
    voice = espeak_voice("ko+m1", "ko")
    text = get_language("ko").sentences[0]
    phones, sr = synthesize_espeak_lib(voice, text, tmp_path / "ko.wav")
    audio, _ = sf.read(str(tmp_path / "ko.wav"), dtype="float32")
    assert len(phones) > 10 and phones[0].start == 0 and phones[-1].end == len(audio) / sr
    assert all(a.end == b.start for a, b in zip(phones, phones[1:]))
    assert not _silent_speech_phones(phones, audio, sr, SILENT_PHONE_DB)
