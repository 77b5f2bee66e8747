"""Festival's voices of other languages in the multilingual corpus: every phone of each voice's
own phone set mapped on purpose, each corpus phone at the time Festival's Segment relation gave
it, /p b m/ as P B M, and voices of reserved languages refused."""

import json
import re
import subprocess

import numpy as np
import pytest
import soundfile as sf
from test_multilingual import _assert_closures

from talkmesh.audio.festival_voices import (
    ENCODINGS,
    FESTIVAL_VOICES,
    PHONE_TABLES,
    festival_installed,
    festival_label,
    get_festival_voice,
)
from talkmesh.audio.languages import check_festival_not_reserved, get_language
from talkmesh.audio.phonemes import ARPABET_PHONES, SILENCE
from talkmesh.audio.voices import Voice, festival_voice, synthesize_festival
from talkmesh.datasets.multilingual import (
    installed_plan,
    make_multilingual_corpus,
    plan_subjects,
    read_phones,
)
from talkmesh.errors import TalkmeshError

LABELS = set(ARPABET_PHONES) | {"UY", "OE", SILENCE}
INSTALLED = [v for v in FESTIVAL_VOICES if festival_installed(v)]


def _festival(script: str, encoding: str = "utf-8") -> str:
    return subprocess.run(
        ["festival", "--pipe"], input=script.encode(encoding), capture_output=True, check=True
    ).stdout.decode("latin-1")


@pytest.fixture(scope="module")
def phone_sets() -> dict[tuple[str, str], list[str]]:
    """Each installed voice's phone set, as Festival lists it once the voice is loaded."""
    if not INSTALLED:
        return {}
    script = "".join(
        f'({v.function}) (format t "SET {v.language} {v.speaker} %l\\n" '
        "(mapcar car (car (cdr (assoc 'phones (PhoneSet.description))))))"
        for v in INSTALLED
    )
    out = {}
    for line in _festival(script).splitlines():
        if line.startswith("SET "):
            _, lang, speaker, phones = line.split(" ", 3)
            out[lang, speaker] = phones.strip("()").split()
    return out


@pytest.mark.parametrize("voice", FESTIVAL_VOICES, ids=lambda v: f"{v.language}-{v.speaker}")
def test_every_phone_of_the_voices_set_is_mapped_on_purpose(voice, phone_sets):
    if voice not in INSTALLED:
        pytest.skip(f"{voice.package} is not installed (make setup)")
    phones = phone_sets[voice.language, voice.speaker]
    # the table is written for this very set: no phone of it missing, none it lacks
    assert sorted(PHONE_TABLES[voice.phoneset]) == sorted(phones)
    assert {festival_label(p, voice.phoneset) for p in phones} <= LABELS


def test_symbols_that_look_alike_map_to_what_they_are_in_each_voice():
    cases = {
        ("spanish", "th"): "TH",  # /θ/
        ("indic", "th"): "T",  # त: a dental stop
        ("indic", "bh"): "B",  # भ: the lips close
        ("msu_ru", "y"): "IH",  # ы: unrounded
        ("finnish", "y"): "UY",  # y: rounded
        ("finnish", "7:"): "OE",  # long ö
        ("finnish", "@"): "AE",  # ä
        ("italian", "nf"): "V",  # ɱ: the lower lip to the teeth, not a closure
        ("spanish", "x"): "HH",
        ("catalan", "ax"): "AH",
        ("msu_ru", "pp"): "P",  # palatalised p: still a closure
        ("finnish", "m:"): "M",
    }
    for (phoneset, symbol), label in cases.items():
        assert festival_label(symbol, phoneset) == label, (phoneset, symbol)
    with pytest.raises(TalkmeshError, match="no mapping"):
        festival_label("q", "spanish")


@pytest.mark.parametrize(
    "voice,language",
    [
        ("voice_czech_dita", "cs"),
        ("voice_czech_krb", ""),  # by name, whatever language it claims
        ("voice_czech_machac", "de"),
        ("voice_czech_ph", "cs"),
        ("voice_el_diphone", "el"),  # Greek by language
        ("voice_anything", "sv"),
        ("voice_swedish_x", ""),
        ("voice_en1_mbrola", "en"),  # a reserved MBROLA database under Festival
        ("voice_de1_mbrola", "de"),
    ],
)
def test_festival_voices_of_reserved_languages_are_refused(voice, language):
    with pytest.raises(TalkmeshError, match="reserved"):
        check_festival_not_reserved(voice, language)
    with pytest.raises(TalkmeshError, match="reserved"):  # before Festival runs
        synthesize_festival(Voice("x", "festival", voice, language=language), [])


def test_the_plans_festival_voices_follow_the_others_and_keep_held_out_speakers_out():
    check_festival_not_reserved("voice_el_diphone", "es")  # Spanish "el" is no Greek
    check_festival_not_reserved("voice_us1_mbrola", "en")
    plan = plan_subjects()
    fest = [row for row in plan if row[2].startswith("fest-")]
    assert fest and plan[: len(plan) - len(fest)] == [r for r in plan if r not in fest]
    assert {r[1] for r in fest} >= {"es", "it", "ru", "fi", "ca", "hi", "mr", "te"}
    # NSK speaks Hindi, Marathi and Telugu: held out in all three (Telugu, Marathi: never trained)
    assert {s for s, _, db in fest if db == "fest-nsk"} == {"test"}
    assert ("train", "fi", "fest-lj") in fest and ("test", "fi", "fest-mv") in fest
    assert get_language("fi").trained and not get_language("mr").trained
    # the split rule of the other voices: a language's third training voice goes to val
    assert ("val", "es", "fest-el") in fest and ("train", "it", "fest-lp") in fest


def test_engines_pick_voices_and_the_corpus_before_festival_is_a_prefix(tmp_path):
    old = installed_plan(engines=["mbrola", "espeak-lib"])
    assert old and not any(db.startswith("fest-") for _, _, db in old)
    assert installed_plan()[: len(old)] == old  # the earlier corpus, subject for subject
    fest = installed_plan(engines=["festival"])
    assert all(db.startswith("fest-") for _, _, db in fest)
    assert len(fest) == len(INSTALLED)
    with pytest.raises(TalkmeshError, match="unknown engine"):
        make_multilingual_corpus(tmp_path / "x", engines=["pico"])
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(
    "argv,fragment",
    [
        (["--multilingual", "--engines", "pico"], "unknown engine(s) pico"),
        (["--engines", "festival"], "need --multilingual"),
    ],
)
def test_bad_engines_on_the_command_line_are_one_line(tmp_path, capsys, argv, fragment):
    from talkmesh.cli import main

    assert main(["synth", "--out", str(tmp_path / "x"), "-q", *argv]) != 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("talkmesh: error:") and fragment in err and "\n" not in err
    assert not (tmp_path / "x").exists()


def test_text_the_voice_cannot_read_is_one_line(tmp_path):
    voice = festival_voice("es", "el")
    assert ENCODINGS[voice.phoneset] == "latin-1"
    with pytest.raises(TalkmeshError, match="cannot read 'Привет'"):
        synthesize_festival(voice, [("Привет", tmp_path / "a.wav")])
    with pytest.raises(TalkmeshError, match="no Festival voice"):
        get_festival_voice("es", "zz")


def _segments(voice: Voice, text: str, tmp_path) -> list[tuple[float, str]]:
    """Festival's own Segment relation for ``text`` at the voice's rate: (end, phone) rows."""
    segs = tmp_path / "own.segs"
    stretch = f"(Parameter.set 'Duration_Stretch (* (Parameter.get 'Duration_Stretch) {160 / voice.speed}))"
    script = (
        f"({voice.voice}) {stretch if voice.speed != 160 else ''}"
        f'(utt.save.segs (SynthText "{text}") "{segs}")'
    )
    _festival(script, ENCODINGS.get(voice.phoneset, "utf-8"))
    rows = [line.split() for line in segs.read_text(encoding="latin-1").splitlines()]
    return [(float(r[0]), r[2]) for r in rows if len(r) == 3 and not r[0].startswith("#")]


def test_finnish_corpus_phones_are_festivals_segments_and_p_b_m_close(tmp_path):
    v = get_festival_voice("fi", "lj")
    if not all(festival_installed(get_festival_voice("fi", s)) for s in ("lj", "mv")):
        pytest.skip(f"{v.package} or festvox-suopuhe-mv is not installed (make setup)")
    info = make_multilingual_corpus(
        tmp_path / "ml", utterances_per_voice=1, languages=["fi"], workers=1, progress=False
    )
    assert info.subjects == 2
    manifest = json.loads((tmp_path / "ml" / "manifest.json").read_text())
    assert [s.split("_")[2] for s in manifest["splits"]["train"]] == ["fest-lj"]
    assert [s.split("_")[2] for s in manifest["splits"]["test"]] == ["fest-mv"]
    for name, text in manifest["sentences"].items():
        subject = manifest["subjects"][name.rsplit("_", 1)[0]]
        assert subject["engine"] == "festival" and subject["language"] == "fi"
        speaker, _, speed = subject["voice"].removeprefix("fest-fi-").partition("-s")
        voice = festival_voice("fi", speaker, int(speed or 160))
        own = _segments(voice, text, tmp_path)
        phones = read_phones(tmp_path / "ml", name)
        # each speech phone spans exactly Festival's segment (as written: 1 us)
        starts = [0.0] + [end for end, _ in own[:-1]]
        truth = [
            (festival_label(sym, voice.phoneset), a, b)
            for (b, sym), a in zip(own, starts)
            if festival_label(sym, voice.phoneset) != SILENCE
        ]
        speech = [(p.label, p.start, p.end) for p in phones if p.label != SILENCE]
        assert [t[0] for t in speech] == [t[0] for t in truth]
        assert np.abs(np.subtract([t[1:] for t in speech], [t[1:] for t in truth])).max() <= 1e-6
        audio, sr = sf.read(tmp_path / "ml" / "wav" / f"{name}.wav")
        assert abs(len(audio) / sr - phones[-1].end) < 0.02
        # Finnish spelling is phonemic: each run of p, b or m in the text is one P, B or M
        letters = [run[0].upper() for run in re.findall(r"p+|b+|m+", text.lower())]
        assert [p.label for p in phones if p.label in {"P", "B", "M"}] == letters
        _assert_closures(tmp_path / "ml", name, subject, phones)
