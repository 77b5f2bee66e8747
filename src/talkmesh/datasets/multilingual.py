"""``talkmesh synth --multilingual``: the synthetic corpus in many languages, with the teacher's truth.

Every voice of :data:`talkmesh.audio.languages.LANGUAGES` is a subject: its ``train`` voices make
the train split (one per language goes to val where a language has three or more), its ``test``
voices (held-out voices of trained languages, and every voice of the never-trained languages) the
test split. Each utterance is two of the language's sentences with the pause between them, read by
an MBROLA voice, one of espeak-ng's own voices (a variant of the language's voice, phone times
from the library's phoneme events) or a Festival voice (phone times from its utterance's
Segment relation; after every other voice) at the pitch and rate given to its subject; the motion truth is the procedural
animator with the teacher's rules (:mod:`talkmesh.face.teacher`) on the synthesiser's exact phone
timings, which are also saved (``phones/NAME.json``: ``[[label, start, end], ...]``) for the
multilingual benchmark.

The layout is the synthetic corpus's (:mod:`talkmesh.datasets.synth`), so training and
evaluation read it unchanged. Voices reserved for outside checks are refused
(:func:`talkmesh.audio.languages.check_not_reserved`).
"""

from __future__ import annotations

import itertools
import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from talkmesh.datasets import synth
from talkmesh.datasets.synth import CorpusInfo, _atomic_write, _check_request
from talkmesh.errors import TalkmeshError

# 5: the teacher's truth a frame ahead of the sound, vowels 1.5, closures a 30 fps frame or longer
# 6: the pauses' rest not cut short by the lead (the mouth leaves rest 60 ms before speech, not 93)
# 7: as 6, but the mouth closes into a pause ahead of the sound again, as it did in 5
FORMAT_VERSION = 7
ENGINES = ("mbrola", "espeak-lib", "festival")


def utterances(sentences: tuple[str, ...], count: int, rng: np.random.Generator) -> list[str]:
    """``count`` texts of two different sentences each (a pause between them), no pair twice."""
    pairs = list(itertools.permutations(range(len(sentences)), 2))
    order = rng.permutation(len(pairs))[:count]
    return [f"{sentences[pairs[k][0]]} {sentences[pairs[k][1]]}" for k in order]


def plan_subjects(languages: list[str] | None = None) -> list[tuple[str, str, str]]:
    """(split, language code, voice) of every subject, in corpus order; the voice is an MBROLA
    database or, for a language of the ``espeak-lib`` engine, a variant of its espeak-ng voice.
    Festival's voices (``fest-SPEAKER``) follow all of them, so the corpus's earlier subjects keep
    their order (and their identities, prosody and sentences, drawn in that order)."""
    from talkmesh.audio.languages import LANGUAGES, check_espeak_not_reserved, check_not_reserved

    chosen = [lang for lang in LANGUAGES if languages is None or lang.code in languages]
    unknown = set(languages or ()) - {lang.code for lang in LANGUAGES}
    if unknown:
        raise TalkmeshError(f"unknown language(s) {', '.join(sorted(unknown))}")
    out = []
    for lang in chosen:
        for split, db in [("val" if k == 2 else "train", db) for k, db in enumerate(lang.train)] + [
            ("test", db) for db in lang.test
        ]:
            if lang.engine == "espeak-lib":
                check_espeak_not_reserved(lang.voice_name(db), lang.code)
            else:
                check_not_reserved(db, lang.code)
            out.append((split, lang.code, db))
    return out + _festival_subjects(chosen)


def _festival_subjects(chosen: list) -> list[tuple[str, str, str]]:
    """The Festival voices' rows: split as the language's other voices (its third training voice
    goes to val; a never-trained language's voices to test)."""
    from talkmesh.audio.festival_voices import get_festival_voice
    from talkmesh.audio.languages import check_festival_not_reserved

    out = []
    for lang in chosen:
        rows = [
            ("val" if k == 2 else "train", speaker)
            for k, speaker in enumerate(lang.festival, start=len(lang.train))
        ] + [("test", speaker) for speaker in lang.festival_test]
        for split, speaker in rows:
            check_festival_not_reserved(get_festival_voice(lang.code, speaker).function, lang.code)
            out.append((split, lang.code, f"fest-{speaker}"))
    return out


def installed_plan(
    languages: list[str] | None = None, engines: list[str] | None = None
) -> list[tuple[str, str, str]]:
    """The rows of :func:`plan_subjects` whose voices speak here, of ``engines`` only if given."""
    unknown = set(engines or ()) - set(ENGINES)
    if unknown:
        raise TalkmeshError(
            f"unknown engine(s) {', '.join(sorted(unknown))}: use {', '.join(ENGINES)}"
        )
    return [
        row
        for row in plan_subjects(languages)
        if (engines is None or engine_of(row[2], row[1]) in engines) and installed(row[2], row[1])
    ]


def engine_of(db: str, code: str) -> str:
    """The engine of the planned voice ``db`` of language ``code``."""
    from talkmesh.audio.languages import get_language

    return "festival" if db.startswith("fest-") else get_language(code).engine


def installed(db: str, code: str = "") -> bool:
    """Whether the voice ``db`` of language ``code`` can speak here: its MBROLA database,
    espeak-ng's library and the voice it names, or Festival and its voice (``fest-SPEAKER``)."""
    from talkmesh.audio.festival_voices import festival_installed, get_festival_voice
    from talkmesh.audio.languages import get_language

    if db.startswith("fest-"):
        return festival_installed(get_festival_voice(code, db.removeprefix("fest-")))
    lang = get_language(code) if code else None
    if lang is None or lang.engine == "mbrola":
        return (Path("/usr/share/mbrola") / db / db).is_file()
    from talkmesh.audio.espeak_lib import voice_details

    try:
        voice_details(lang.voice_name(db))
    except TalkmeshError:
        return False
    return True


def make_multilingual_corpus(
    out: str | Path,
    *,
    utterances_per_voice: int = 10,
    languages: list[str] | None = None,
    engines: list[str] | None = None,
    seed: int = 0,
    workers: int | None = None,
    progress: bool = True,
    overwrite: bool = False,
) -> CorpusInfo:
    """Write the multilingual corpus to ``out``; returns a summary. ``engines`` keeps the voices
    of some engines only (:data:`ENGINES`; ``["mbrola", "espeak-lib"]``: the corpus as it was
    before Festival's voices came, subject for subject)."""
    root = Path(out)
    plan = installed_plan(languages, engines)
    _check_request(root, 1, utterances_per_voice, overwrite)
    if not plan:
        raise TalkmeshError(
            "no voice of the chosen languages is installed: `sudo apt-get install mbrola-de2 "
            "mbrola-fr2 ...`, festvox-ellpc11k ... or libespeak-ng1 (`make setup`; see "
            "docs/results/multilingual.md)"
        )
    jobs, subjects, texts, splits = _jobs(root, plan, utterances_per_voice, seed)
    for sub in ("wav", "vertices_npy", "arkit", "regions", "phones"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    total_s = synth._run_jobs(jobs, len(jobs) * utterances_per_voice, workers, progress)
    num_vertices = synth._write_shared(root, subjects)
    manifest = {
        "format": synth.FORMAT,
        "version": FORMAT_VERSION,
        "seed": seed,
        "fps": synth.DISK_FPS,
        "motion_fps": synth.MOTION_FPS,
        "num_vertices": num_vertices,
        "faces_file": synth.FACES_FILE,
        "train_subjects": list(splits["train"]),
        "splits": splits,
        "subjects": subjects,
        "sentences": texts,
        "teacher": True,
    }
    _atomic_write(
        root / "manifest.json", (json.dumps(manifest, indent=1, sort_keys=True) + "\n").encode()
    )
    size = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
    return CorpusInfo(root, len(jobs), len(jobs) * utterances_per_voice, total_s, size / 1e6)


def _jobs(root: Path, plan: list, count: int, seed: int) -> tuple[list, dict, dict, dict]:
    """One synthesis job per planned voice; the manifest's subjects, texts and splits."""
    from talkmesh.audio.languages import get_language
    from talkmesh.audio.voices import espeak_voice, festival_voice, mbrola_voice
    from talkmesh.face.assets import list_identities
    from talkmesh.face.lipsync import SpeakingStyle

    rng = np.random.default_rng(seed)
    identities = list_identities()
    jobs, subjects, texts, splits = [], {}, {}, {"train": {}, "val": {}, "test": {}}
    ids = [f"utt{k + 1:02d}" for k in range(count)]
    for s, (split, code, db) in enumerate(plan):
        lang = get_language(code)
        identity = identities[s % len(identities)]
        subject = f"ML_{code.replace('-', '')}_{db}_{identity}"
        pitch, speed = int(rng.integers(35, 66)), int(rng.integers(135, 186))
        if db.startswith("fest-"):  # Festival: the rate as a duration stretch, its own pitch
            voice = festival_voice(code, db.removeprefix("fest-"), speed)
        elif lang.engine == "espeak-lib":
            voice = espeak_voice(lang.voice_name(db), code, pitch, speed)
        else:
            voice = mbrola_voice(db, code, pitch, speed)
        style = SpeakingStyle.random(rng)
        mine = utterances(lang.sentences, count, rng)
        subjects[subject] = {
            "identity": identity,
            "voice": voice.name,
            "engine": voice.engine,
            "language": code,
            "family": lang.family,
            "style": asdict(style),
        }
        texts.update({f"{subject}_{i}": t for i, t in zip(ids, mine)})
        splits[split][subject] = ids
        jobs.append(
            {
                "root": str(root),
                "subject": subject,
                "identity": identity,
                "voice_spec": asdict(voice),
                "style": asdict(style),
                "texts": mine,
                "sentence_ids": ids,
                "seed": seed * 100 + s,
                "teacher": True,
                "phones_dir": str(root / "phones"),
            }
        )
    return jobs, subjects, texts, splits


def read_phones(root: Path, name: str):
    """The exact phone timings of one sequence (``phones/NAME.json``)."""
    from talkmesh.audio.phonemes import Phone

    rows = json.loads((Path(root) / "phones" / f"{name}.json").read_text())
    return [Phone(str(label), float(a), float(b)) for label, a, b in rows]
