"""``talkmesh synth``: a multi-speaker synthetic talking-face corpus in the VOCASET layout.

Each subject pairs a bundled identity with its own synthetic voice (:mod:`talkmesh.audio.voices`) and
speaking style. Ground truth is the procedural lip sync (:mod:`talkmesh.face.lipsync`) driven by the
synthesiser's exact phone timings, in the subject's style; blinks, brow drift and gaze come from a
per-sequence seed, so part of the upper face is independent of the audio, as in real capture.

Layout (see :mod:`talkmesh.datasets.reader`)::

    OUT/wav/Synth_01_ada_sentence01.wav           the synthesiser's native rate
    OUT/vertices_npy/Synth_01_ada_sentence01.npy  [T, V*3] float32 at 60 fps (like VOCASET)
    OUT/arkit/Synth_01_ada_sentence01.npy         [T, 52] ARKit weights at 60 fps
    OUT/templates.pkl  OUT/head.ply  OUT/regions/{lve,fdd}.txt  OUT/manifest.json

The same seed gives byte-identical files.
"""

from __future__ import annotations

import json
import os
import warnings
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from talkmesh import constants
from talkmesh.errors import TalkmeshError, TalkmeshWarning

MOTION_FPS = int(constants.MOTION_FPS)  # written into the manifest as an int, as before
DISK_FPS = 2 * MOTION_FPS  # VOCASET stores 60 fps; readers take every second frame
FORMAT = "talkmesh-synth"
FORMAT_VERSION = 1
FACES_FILE = "head.ply"


@dataclass(frozen=True)
class CorpusInfo:
    root: Path
    subjects: int
    sequences: int
    seconds: float
    megabytes: float

    def __str__(self) -> str:
        return (
            f"{self.root}: {self.subjects} subjects, {self.sequences} sequences, "
            f"{self.seconds / 60:.1f} min of speech, {self.megabytes:.0f} MB"
        )


def split_subjects(num: int) -> tuple[int, int, int]:
    """(train, val, test) subject counts: 8/2/2 for 12, about 2/3 training otherwise."""
    if num < 3:
        return num, 0, 0
    train = max(1, round(num * 2 / 3))
    val = (num - train) // 2
    return train, val, num - train - val


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _npy_bytes(arr: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


def _subject_job(job: dict) -> list[dict]:
    """Synthesise, animate and write every sentence of one subject (runs in a worker)."""
    import soundfile as sf

    from talkmesh.audio.loading import SAMPLE_RATE, resample
    from talkmesh.audio.voices import Voice, get_voice, synthesize
    from talkmesh.face.assets import load_head
    from talkmesh.face.lipsync import SpeakingStyle, phones_to_weights
    from talkmesh.face.teacher import teach

    root = Path(job["root"])
    head = load_head(job["identity"])
    style = SpeakingStyle(**job["style"])
    voice = Voice(**job["voice_spec"]) if "voice_spec" in job else get_voice(job["voice"])
    names = [f"{job['subject']}_{sid}" for sid in job["sentence_ids"]]
    tmp_wavs = [root / "wav" / f"{n}.wav.tmp.wav" for n in names]
    results = synthesize(voice, list(zip(job["texts"], tmp_wavs)))
    rows = []
    for k, (name, tmp, (phones, sr)) in enumerate(zip(names, tmp_wavs, results)):
        audio, file_sr = sf.read(str(tmp), dtype="float32")
        if audio.ndim > 1:
            audio = audio.mean(axis=1)
        if file_sr != sr:
            sr = file_sr
        # Keep the native rate on disk (like VOCASET's 22 kHz); the 32 kHz HTS voice is halved.
        if sr > SAMPLE_RATE:  # store what the readers use: 16 kHz
            audio = resample(audio, sr, SAMPLE_RATE).astype(np.float32)
            sr = SAMPLE_RATE
        peak = float(np.abs(audio).max()) or 1.0
        audio = (audio / peak * 0.9).astype(np.float32)  # the same loudness for every voice
        os.unlink(tmp)
        wav_path = root / "wav" / f"{name}.wav"
        sf.write(str(wav_path) + ".tmp", audio, sr, format="WAV", subtype="PCM_16")
        os.replace(str(wav_path) + ".tmp", wav_path)
        duration = len(audio) / sr
        num_frames = max(1, int(round(duration * DISK_FPS)))
        audio16 = resample(audio, sr, SAMPLE_RATE) if sr != SAMPLE_RATE else audio
        weights = phones_to_weights(
            phones,
            num_frames,
            DISK_FPS,
            audio=audio16,
            sr=SAMPLE_RATE,
            style=style,
            seed=job["seed"] * 1000 + k,
        ).astype(np.float32)
        if job.get("teacher"):
            teach(
                weights,
                phones,
                DISK_FPS,
                head,
                audio=audio16,
                jaw_scale=style.jaw * style.articulation,
            )
        if job.get("phones_dir"):
            _atomic_write(
                Path(job["phones_dir"]) / f"{name}.json",
                json.dumps(
                    [[p.label, round(p.start, 6), round(p.end, 6)] for p in phones]
                ).encode(),
            )
        vertices = head.vertices_from_weights(weights).reshape(num_frames, -1).astype(np.float32)
        _atomic_write(root / "vertices_npy" / f"{name}.npy", _npy_bytes(vertices))
        _atomic_write(root / "arkit" / f"{name}.npy", _npy_bytes(weights))
        rows.append({"name": name, "seconds": duration, "phones": len(phones)})
    return rows


def _check_request(root: Path, subjects: int, sentences: int, overwrite: bool) -> None:
    if subjects < 1 or sentences < 1:
        raise TalkmeshError("--subjects and --sentences must be at least 1")
    if subjects > 99 or sentences > 999:
        raise TalkmeshError("at most 99 subjects and 999 sentences per subject")
    if root.exists() and not root.is_dir():
        raise TalkmeshError(f"{root} is a file: choose a directory for --out")
    if root.is_dir() and any(root.iterdir()) and not overwrite:
        raise TalkmeshError(f"{root} is not empty: choose a new --out or pass --overwrite")


def _warn_empty_splits(subjects: int, n_val: int, n_test: int) -> None:
    if not n_test:
        warnings.warn(
            f"with {subjects} subject(s) the test split is empty, so evaluate, baseline and "
            "predict have nothing to score on it: use --subjects 3 or more",
            TalkmeshWarning,
            stacklevel=3,
        )
    elif not n_val:
        warnings.warn(
            f"with {subjects} subjects the val split is empty (training runs without "
            "validation): use --subjects 5 or more for one",
            TalkmeshWarning,
            stacklevel=3,
        )


def _plan(root: Path, subjects: int, sentences: int, seed: int) -> tuple[list, dict, dict, list]:
    """One job per subject (identity, voice, style, sentences), the manifest's subject and
    sentence tables, and the sentence ids."""
    from talkmesh.audio.voices import available_voices
    from talkmesh.datasets.sentences import generate_sentences
    from talkmesh.face.assets import list_identities
    from talkmesh.face.lipsync import SpeakingStyle

    voices = available_voices()
    if not voices:
        raise TalkmeshError("no synthetic voices installed: run `make setup` (mbrola, festival)")
    identities = list_identities()
    rng = np.random.default_rng(seed)
    texts = generate_sentences(subjects * sentences, seed)
    jobs, manifest_subjects, sentence_text = [], {}, {}
    sentence_ids = [f"sentence{k + 1:02d}" for k in range(sentences)]
    for s in range(subjects):
        identity = identities[s % len(identities)]
        subject = f"Synth_{s + 1:02d}_{identity}"
        voice = voices[s % len(voices)]
        style = SpeakingStyle.random(rng)
        mine = texts[s * sentences : (s + 1) * sentences]
        manifest_subjects[subject] = {
            "identity": identity,
            "voice": voice.name,
            "engine": voice.engine,
            "style": asdict(style),
        }
        for sid, text in zip(sentence_ids, mine):
            sentence_text[f"{subject}_{sid}"] = text
        jobs.append(
            {
                "root": str(root),
                "subject": subject,
                "identity": identity,
                "voice": voice.name,
                "style": asdict(style),
                "texts": mine,
                "sentence_ids": sentence_ids,
                "seed": seed * 100 + s,
            }
        )
    return jobs, manifest_subjects, sentence_text, sentence_ids


def _run_jobs(jobs: list, total: int, workers: int | None, progress: bool) -> float:
    """Synthesise every subject (in processes when ``workers`` > 1); the seconds of speech."""
    from tqdm import tqdm

    total_s = 0.0
    workers = workers or os.cpu_count() or 1
    bar = tqdm(total=total, unit="seq", desc="synth", disable=not progress)
    if workers > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(max_workers=min(workers, len(jobs))) as pool:
            for rows in pool.map(_subject_job, jobs):
                total_s += sum(r["seconds"] for r in rows)
                bar.update(len(rows))
    else:
        for job in jobs:
            rows = _subject_job(job)
            total_s += sum(r["seconds"] for r in rows)
            bar.update(len(rows))
    bar.close()
    return total_s


def _write_shared(root: Path, manifest_subjects: dict) -> int:
    """Templates, the faces file and the region lists; returns the vertex count."""
    from talkmesh.datasets.reader import write_templates
    from talkmesh.face.assets import load_head

    head = load_head()
    write_templates(
        root / "templates.pkl",
        {n: load_head(m["identity"]).template for n, m in manifest_subjects.items()},
    )
    _write_ply(root / FACES_FILE, head.template, head.faces)
    regions = head.regions
    _atomic_write(root / "regions" / "lve.txt", (",".join(map(str, regions.lips)) + "\n").encode())
    _atomic_write(
        root / "regions" / "fdd.txt", (",".join(map(str, regions.upper_face)) + "\n").encode()
    )
    return head.num_vertices


def make_corpus(
    out: str | Path,
    *,
    subjects: int = 12,
    sentences: int = 40,
    seed: int = 0,
    workers: int | None = None,
    progress: bool = True,
    overwrite: bool = False,
) -> CorpusInfo:
    """Write a synthetic corpus to ``out`` (see the module docstring); returns a summary."""
    root = Path(out)
    _check_request(root, subjects, sentences, overwrite)
    jobs, manifest_subjects, sentence_text, sentence_ids = _plan(root, subjects, sentences, seed)
    n_train, n_val, n_test = split_subjects(subjects)
    _warn_empty_splits(subjects, n_val, n_test)
    for sub in ("wav", "vertices_npy", "arkit", "regions"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    names = list(manifest_subjects)
    half = sentence_ids[sentences // 2 :] if sentences > 1 else sentence_ids
    splits = {
        "train": {n: sentence_ids for n in names[:n_train]},
        "val": {n: half for n in names[n_train : n_train + n_val]},
        "test": {n: half for n in names[n_train + n_val :]},
    }
    total_s = _run_jobs(jobs, subjects * sentences, workers, progress)
    num_vertices = _write_shared(root, manifest_subjects)
    manifest = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "seed": seed,
        "fps": DISK_FPS,
        "motion_fps": MOTION_FPS,
        "num_vertices": num_vertices,
        "faces_file": FACES_FILE,
        "train_subjects": names[:n_train],
        "splits": splits,
        "subjects": manifest_subjects,
        "sentences": sentence_text,
    }
    _atomic_write(
        root / "manifest.json", (json.dumps(manifest, indent=1, sort_keys=True) + "\n").encode()
    )
    size = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
    return CorpusInfo(root, subjects, subjects * sentences, total_s, size / 1e6)


def _write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """A binary little-endian PLY (deterministic bytes, readable by trimesh and psbody)."""
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    v = np.asarray(vertices, "<f4").tobytes()
    f = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    f["n"] = 3
    f["i"] = faces
    _atomic_write(path, header + v + f.tobytes())


def augment_audio(
    audio: np.ndarray,
    sr: int,
    rng: np.random.Generator,
    *,
    noise_snr_db: tuple[float, float] = (20.0, 40.0),
    gain_db: tuple[float, float] = (-6.0, 6.0),
    reverb: float = 0.3,
) -> np.ndarray:
    """Training-time augmentation: random gain, white noise at a random SNR and, with probability
    ``reverb``, a synthetic room (exponentially decaying noise impulse response, RT60 0.2-0.6 s).

    audio (S,) float32 -> (S,) float32; pure and seeded through ``rng``.
    """
    x = np.asarray(audio, dtype=np.float64)
    if reverb > 0 and rng.random() < reverb:
        rt60 = rng.uniform(0.2, 0.6)
        n = int(sr * rt60)
        t = np.arange(n) / sr
        ir = rng.standard_normal(n) * np.exp(-6.9 * t / rt60)
        ir[0] = 1.0
        ir /= np.sqrt((ir**2).sum())
        from scipy.signal import fftconvolve

        x = fftconvolve(x, ir)[: len(x)]
    x = x * 10 ** (rng.uniform(*gain_db) / 20)
    power = float(np.mean(x**2)) or 1e-12
    snr = rng.uniform(*noise_snr_db)
    x = x + rng.standard_normal(len(x)) * np.sqrt(power / 10 ** (snr / 10))
    return np.clip(x, -1.0, 1.0).astype(np.float32)
