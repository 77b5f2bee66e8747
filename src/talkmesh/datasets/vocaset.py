"""``talkmesh prepare-vocaset RAW OUT``: VOCASET's release files -> the de facto dataset layout.

VOCASET is released as four files (https://voca.is.tue.mpg.de, registration required)::

    RAW/data_verts.npy          (N, 5023, 3) every captured frame of every sequence, 60 fps (~7.5 GB)
    RAW/raw_audio_fixed.pkl     subject -> sentence -> {"audio": samples, "sample_rate": Hz}
    RAW/subj_seq_to_idx.pkl     subject -> sentence -> frame -> row of data_verts.npy
    RAW/templates.pkl           subject -> (5023, 3) neutral face
    RAW/FLAME_sample.ply        optional: FLAME's triangles, for rendering

OUT gets exactly what FaceFormer's and CodeTalker's ``vocaset/process_voca_data.py`` writes:
``vertices_npy/<SUBJECT>_<SENTENCE>.npy`` with the rows of that sentence in the iteration order of
its ``subj_seq_to_idx.pkl`` entry, shape (frames, 15069), the dtype of ``data_verts.npy``;
``wav/<SUBJECT>_<SENTENCE>.wav`` holding the stored samples at the stored rate (no resampling,
no conversion); and copies of ``templates.pkl`` (and ``FLAME_sample.ply``). The frames stay at
60 fps: readers take every second one (see :data:`talkmesh.datasets.reader.VOCASET`).

``data_verts.npy`` is memory-mapped read-only and read one sentence at a time, so memory stays at
one sequence. Each output is written to a temporary name and renamed, so an interrupted run
leaves no half file and a re-run skips every file that exists. The pickles are read with
:func:`talkmesh.datasets.reader.safe_load_pickle`: no code in them can run.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from talkmesh.datasets.reader import (
    TEMPLATES_FILE,
    VERTICES_DIR,
    VOCASET,
    WAV_DIR,
    load_templates,
    safe_load_pickle,
)
from talkmesh.errors import TalkmeshError

VERTS_FILE = "data_verts.npy"
AUDIO_FILE = "raw_audio_fixed.pkl"
INDEX_FILE = "subj_seq_to_idx.pkl"
FACES_FILE = "FLAME_sample.ply"
NUM_VERTICES = 5023
VERTICES_DIM = NUM_VERTICES * 3  # 15069: the official script's --vertices_dim
RELEASE_HINT = "download VOCASET from https://voca.is.tue.mpg.de (registration required)"


def _name(value: object) -> str:
    return value.decode("latin1") if isinstance(value, bytes) else str(value)


def _nested(obj: object, path: Path, depth: int) -> None:
    """Check that ``obj`` is a dict nested ``depth`` levels deep (one-line error otherwise)."""
    if not isinstance(obj, dict) or not obj:
        raise TalkmeshError(f"{path}: expected a non-empty dict of subject -> sentence -> ...")
    if depth > 1:
        for value in obj.values():
            _nested(value, path, depth - 1)


def read_index(path: Path) -> dict[str, dict[str, list[int]]]:
    """``subj_seq_to_idx.pkl`` -> subject -> sentence -> rows, in the file's frame order.

    The official script iterates ``data2array_verts[sub][seq].items()``: the order in which the
    pickle stores the frames, which is not necessarily sorted. So do we.
    """
    obj = safe_load_pickle(path)
    _nested(obj, path, 3)
    out: dict[str, dict[str, list[int]]] = {}
    for subject, sentences in obj.items():
        for sentence, frames in sentences.items():
            try:
                rows = [int(i) for i in frames.values()]
            except (TypeError, ValueError):
                raise TalkmeshError(
                    f"{path}: frame indices of {subject} {sentence} are not integers"
                ) from None
            out.setdefault(_name(subject), {})[_name(sentence)] = rows
    return out


def read_audio(path: Path) -> dict[str, dict[str, tuple[np.ndarray, int]]]:
    """``raw_audio_fixed.pkl`` -> subject -> sentence -> (samples, sample rate)."""
    obj = safe_load_pickle(path)
    _nested(obj, path, 2)
    out: dict[str, dict[str, tuple[np.ndarray, int]]] = {}
    for subject, sentences in obj.items():
        for sentence, entry in sentences.items():
            entry = {_name(k): v for k, v in entry.items()} if isinstance(entry, dict) else {}
            if "audio" not in entry or "sample_rate" not in entry:
                raise TalkmeshError(
                    f"{path}: {_name(subject)} {_name(sentence)} has no 'audio' and 'sample_rate'"
                )
            out.setdefault(_name(subject), {})[_name(sentence)] = (
                np.asarray(entry["audio"]),
                int(entry["sample_rate"]),
            )
    return out


def open_verts(path: Path) -> np.ndarray:
    """``data_verts.npy`` memory-mapped read-only, as (N, 15069) rows."""
    if not path.is_file():
        raise TalkmeshError(f"{path} is missing: {RELEASE_HINT}")
    try:
        verts = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise TalkmeshError(f"{path}: truncated or not a .npy file ({e})") from None
    if verts.ndim == 3 and verts.shape[1:] == (NUM_VERTICES, 3):
        verts = verts.reshape(len(verts), VERTICES_DIM)
    if verts.ndim != 2 or verts.shape[1] != VERTICES_DIM:
        raise TalkmeshError(
            f"{path}: shape {verts.shape}, expected (frames, {NUM_VERTICES}, 3): not VOCASET's"
        )
    return verts


def write_atomic(target: Path, write: Callable[[Path], None]) -> None:
    """``write(tmp)`` then rename to ``target``: a killed run never leaves a half file."""
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.stem}.", suffix=target.suffix)
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _save_npy(rows: np.ndarray) -> Callable[[Path], None]:
    def write(tmp: Path) -> None:
        with tmp.open("wb") as f:
            np.save(f, rows)

    return write


def _save_wav(samples: np.ndarray, rate: int) -> Callable[[Path], None]:
    def write(tmp: Path) -> None:
        from scipy.io import wavfile

        wavfile.write(tmp, rate, samples)

    return write


def prepare_vocaset(raw: str | Path, out: str | Path, *, progress: bool = True) -> tuple[int, int]:
    """Convert the release in ``raw`` into ``out`` (see the module docstring).

    Returns (files written, files that already existed and were skipped).
    """
    from tqdm import tqdm

    raw, out = Path(raw), Path(out)
    if not raw.is_dir():
        raise TalkmeshError(f"VOCASET directory not found: {raw}")
    for name in (INDEX_FILE, AUDIO_FILE, TEMPLATES_FILE):
        if not (raw / name).is_file():
            raise TalkmeshError(f"{raw / name} is missing: {RELEASE_HINT}")
    verts = open_verts(raw / VERTS_FILE)
    index = read_index(raw / INDEX_FILE)
    audio = read_audio(raw / AUDIO_FILE)
    templates = load_templates(raw / TEMPLATES_FILE)
    bad = [s for s, t in templates.items() if t.shape != (NUM_VERTICES, 3)]
    if bad:
        raise TalkmeshError(f"{raw / TEMPLATES_FILE}: {bad[0]} is not a (5023, 3) FLAME template")
    for sub in (VERTICES_DIR, WAV_DIR):
        (out / sub).mkdir(parents=True, exist_ok=True)

    jobs: list[tuple[Path, Callable[[], Callable[[Path], None]]]] = []
    for subject, sentences in index.items():
        for sentence, rows in sentences.items():
            target = out / VERTICES_DIR / f"{subject}_{sentence}.npy"
            if rows and (max(rows) >= len(verts) or min(rows) < -len(verts)):
                raise TalkmeshError(
                    f"{raw / INDEX_FILE}: {subject} {sentence} points past the {len(verts)} rows "
                    f"of {VERTS_FILE}: the files come from different releases"
                )
            # fancy indexing on the memory map reads just these rows, in this order
            jobs.append((target, lambda rows=rows: _save_npy(np.asarray(verts[rows]))))
    for subject, sentences in audio.items():
        for sentence, (samples, rate) in sentences.items():
            target = out / WAV_DIR / f"{subject}_{sentence}.wav"
            jobs.append((target, lambda s=samples, r=rate: _save_wav(s, r)))

    written = skipped = 0
    for target, make in tqdm(jobs, desc="prepare-vocaset", unit="file", disable=not progress):
        if target.is_file():
            skipped += 1
            continue
        write_atomic(target, make())
        written += 1
    for name in (TEMPLATES_FILE, FACES_FILE):
        if (raw / name).is_file() and not (out / name).is_file():
            shutil.copyfile(raw / name, out / name)
    return written, skipped


def missing_pairs(out: str | Path) -> list[str]:
    """Sequences of the standard splits that have no .npy or no .wav in ``out``."""
    out = Path(out)
    names = [
        f"{s}_{t}"
        for split in ("train", "val", "test")
        for s, sents in VOCASET.splits[split].items()
        for t in sents
    ]
    return [
        n
        for n in dict.fromkeys(names)
        if not (out / VERTICES_DIR / f"{n}.npy").is_file()
        or not (out / WAV_DIR / f"{n}.wav").is_file()
    ]
