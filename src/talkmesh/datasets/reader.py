"""Dataset readers: VOCASET, BIWI, talkmesh synthetic corpora and users' own folders.

Every dataset is a directory in the de facto contract of FaceFormer/CodeTalker::

    ROOT/wav/<SUBJECT>_<SENTENCE>.wav           speech, any rate (16 kHz mono on load)
    ROOT/vertices_npy/<SUBJECT>_<SENTENCE>.npy  [T_disk, V*3] absolute positions, float32/float64
    ROOT/templates.pkl                          dict subject -> [V, 3] neutral face
    ROOT/<name>.ply                             faces for rendering
    ROOT/regions/lve.txt, regions/fdd.txt       0-based lip / upper-face ids, comma-separated

The subject id is the file stem without its last ``_`` token, the sentence id is that token.
Dataset facts (frame rates, vertex counts, speakers, splits) live in :class:`DatasetSpec` values,
one per kind, in the :data:`READERS` registry; nothing downstream branches on the dataset.

``folder`` datasets describe themselves in ``ROOT/splits.json``::

    {"train_subjects": ["alice", "bob"],          # style one-hot order
     "fps": 60, "motion_fps": 30,                 # frames on disk, frames after reading
     "splits": {"train": {"alice": ["s01", "s02"], "bob": ["s01"]},
                "val": {...}, "test": {"carol": ["s01"]}}}

Synthetic corpora (``talkmesh synth``) carry the same facts in ``ROOT/manifest.json``.
"""

from __future__ import annotations

import io
import json
import pickle
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from talkmesh.constants import BIWI_TRAIN_SUBJECTS, VOCASET_TRAIN_SUBJECTS
from talkmesh.datasets.pickles import safe_load_pickle
from talkmesh.datasets.regions import (
    FLAME_MASKS_FILE,
    DatasetRegions,
    load_regions,
)
from talkmesh.errors import TalkmeshError, TalkmeshWarning

WAV_DIR = "wav"
VERTICES_DIR = "vertices_npy"
TEMPLATES_FILE = "templates.pkl"
REGIONS_DIR = "regions"
MANIFEST_FILE = "manifest.json"
SPLITS_FILE = "splits.json"
AUDIO_TOLERANCE_FRAMES = 2  # a wav may end this many motion frames before the motion does
MIN_FRAMES = 2  # motion frames (after the stride): fewer is too short to train or score on


# ---------------------------------------------------------------------------------------------
# Facts


@dataclass(frozen=True)
class DatasetSpec:
    """What a dataset kind is: frame rates, vertex count, speakers and splits."""

    kind: str
    motion_fps: float
    stride: int  # frames taken on disk: [::stride]
    num_vertices: int | None
    train_subjects: tuple[str, ...]
    splits: dict[str, dict[str, tuple[str, ...]]] = field(default_factory=dict)
    faces_file: str | None = None  # name of the .ply; None: the only .ply in ROOT

    def __post_init__(self) -> None:
        if self.stride < 1 or self.motion_fps <= 0:
            raise TalkmeshError(f"{self.kind}: stride and motion_fps must be positive")


def _sentences(prefix: str, first: int, last: int, width: int = 2) -> tuple[str, ...]:
    return tuple(f"{prefix}{k:0{width}d}" for k in range(first, last + 1))


VOCASET_TRAIN = VOCASET_TRAIN_SUBJECTS
VOCASET_VAL = ("FaceTalk_170811_03275_TA", "FaceTalk_170908_03277_TA")
VOCASET_TEST = ("FaceTalk_170809_00138_TA", "FaceTalk_170731_00024_TA")
VOCASET = DatasetSpec(
    kind="vocaset",
    motion_fps=30.0,
    stride=2,  # captured and stored at 60 fps; the anchors read every second frame
    num_vertices=5023,
    train_subjects=VOCASET_TRAIN,
    splits={
        "train": {s: _sentences("sentence", 1, 40) for s in VOCASET_TRAIN},
        "val": {s: _sentences("sentence", 21, 40) for s in VOCASET_VAL},
        "test": {s: _sentences("sentence", 21, 40) for s in VOCASET_TEST},
    },
    faces_file="FLAME_sample.ply",
)

BIWI_TRAIN = BIWI_TRAIN_SUBJECTS
BIWI_UNSEEN = ("F1", "F5", "F6", "F7", "F8", "M1", "M2", "M6")
BIWI = DatasetSpec(
    kind="biwi",
    motion_fps=25.0,
    stride=1,
    num_vertices=23370,
    train_subjects=BIWI_TRAIN,
    splits={
        "train": {s: _sentences("e", 1, 32) for s in BIWI_TRAIN},
        "val": {s: _sentences("e", 33, 36) for s in BIWI_TRAIN},
        "test": {s: _sentences("e", 37, 40) for s in BIWI_TRAIN},
        "test-a": {s: _sentences("e", 37, 40) for s in BIWI_TRAIN},
        "test-b": {s: _sentences("e", 37, 40) for s in BIWI_UNSEEN},
    },
    faces_file="BIWI.ply",
)


def _spec_from_description(kind: str, path: Path, num_vertices: int | None = None) -> DatasetSpec:
    """A spec from a manifest.json (synth) or splits.json (folder)."""
    if not path.is_file():
        raise TalkmeshError(f"{path} is missing: a {kind} dataset describes its splits there")
    try:
        doc = json.loads(path.read_text())
        fps = float(doc.get("fps", 30))
        motion_fps = float(doc.get("motion_fps", fps))
        stride = int(round(fps / motion_fps))
        if stride < 1 or abs(stride * motion_fps - fps) > 1e-6:
            raise ValueError(f"fps {fps} is not a whole multiple of motion_fps {motion_fps}")
        splits = {
            str(name): {str(s): tuple(map(str, sents)) for s, sents in subjects.items()}
            for name, subjects in doc["splits"].items()
        }
        return DatasetSpec(
            kind=kind,
            motion_fps=motion_fps,
            stride=stride,
            num_vertices=doc.get("num_vertices", num_vertices),
            train_subjects=tuple(map(str, doc["train_subjects"])),
            splits=splits,
            faces_file=doc.get("faces_file"),
        )
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise TalkmeshError(f"{path}: not a valid {kind} description ({e})") from None


READERS: dict[str, Callable[[Path], DatasetSpec]] = {
    "vocaset": lambda root: VOCASET,
    "biwi": lambda root: BIWI,
    "synth": lambda root: _spec_from_description("synth", root / MANIFEST_FILE),
    "folder": lambda root: _spec_from_description("folder", root / SPLITS_FILE),
}


# ---------------------------------------------------------------------------------------------
# Safe file readers


def load_templates(path: str | Path) -> dict[str, np.ndarray]:
    """templates.pkl -> subject -> (V, 3) float32."""
    path = Path(path)
    obj = safe_load_pickle(path)
    if not isinstance(obj, dict):
        raise TalkmeshError(f"{path}: expected a dict of subject -> (V, 3) arrays")
    out = {}
    for key, value in obj.items():
        name = key.decode("latin1") if isinstance(key, bytes) else str(key)
        if isinstance(value, (str, bytes)) or (
            isinstance(value, np.ndarray) and value.dtype.kind not in "biuf"
        ):
            what = value.dtype if isinstance(value, np.ndarray) else type(value).__name__
            raise TalkmeshError(
                f"{path}: template of {name} is {what}, not numbers: expected (V, 3) vertices"
            )
        try:
            arr = np.asarray(value, dtype=np.float32)
        except (TypeError, ValueError, OverflowError) as e:
            raise TalkmeshError(
                f"{path}: template of {name} is not an array of numbers ({type(e).__name__}): "
                "expected (V, 3) vertices"
            ) from None
        if arr.ndim == 1 and arr.size % 3 == 0:
            arr = arr.reshape(-1, 3)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise TalkmeshError(
                f"{path}: template of {name} has shape {arr.shape}, expected (V, 3)"
            )
        if not np.isfinite(arr).all():
            raise TalkmeshError(
                f"{path}: template of {name} has {int((~np.isfinite(arr)).any(axis=1).sum())} "
                "vertices with NaN or infinite coordinates"
            )
        out[name] = arr
    return out


def load_motion(path: str | Path, num_vertices: int, stride: int = 1) -> np.ndarray:
    """[T, V*3] .npy -> (T // stride, V, 3) float32, with one-line errors naming the file."""
    path = Path(path)
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
        raise TalkmeshError(f"{path}: truncated or not a .npy file ({e})") from None
    if not isinstance(arr, np.ndarray) or not np.issubdtype(arr.dtype, np.floating):
        raise TalkmeshError(f"{path}: expected a float array of vertex positions")
    if arr.ndim == 3 and arr.shape[1:] == (num_vertices, 3):
        arr = arr.reshape(len(arr), -1)
    if arr.ndim != 2 or arr.shape[1] != num_vertices * 3:
        raise TalkmeshError(
            f"{path}: shape {arr.shape} does not match the template's {num_vertices} vertices "
            f"(expected [T, {num_vertices * 3}])"
        )
    if len(arr) == 0:
        raise TalkmeshError(f"{path}: no frames")
    try:
        out = np.asarray(arr[::stride], dtype=np.float32).reshape(-1, num_vertices, 3)
    except (ValueError, OSError) as e:
        raise TalkmeshError(f"{path}: truncated .npy ({e})") from None
    if not np.isfinite(out).all():
        raise TalkmeshError(f"{path}: contains NaN or infinite values")
    return out


def parse_name(stem: str) -> tuple[str, str]:
    """``FaceTalk_170728_03272_TA_sentence01`` -> (subject, sentence)."""
    subject, sep, sentence = stem.rpartition("_")
    if not sep or not subject:
        raise TalkmeshError(f"{stem}: file names must be <SUBJECT>_<SENTENCE>")
    return subject, sentence


# ---------------------------------------------------------------------------------------------
# Datasets


class Sample(NamedTuple):
    """One sequence: audio (S,) float32 at 16 kHz, vertices (T, V, 3) float32, template (V, 3)."""

    name: str
    subject: str
    sentence: str
    audio: np.ndarray
    vertices: np.ndarray
    template: np.ndarray
    style: int  # index into spec.train_subjects, -1 for speakers outside the training set


class MotionDataset:
    """The sequences of one split; files are read lazily in ``__getitem__``."""

    def __init__(self, spec: DatasetSpec, root: Path, split: str, regions: DatasetRegions) -> None:
        self.spec = spec
        self.root = root
        self.split = split
        self.regions = regions
        self.templates = load_templates(root / TEMPLATES_FILE)
        wanted = spec.splits[split]
        self.names: list[str] = []
        self.skipped: list[str] = []  # listed in the split, but a file or template is missing
        self.bad: list[str] = []  # present but unusable (corrupt, short, mismatched): warned
        present = [
            (subject, f"{subject}_{sentence}")
            for subject, sentences in wanted.items()
            for sentence in sentences
            if (root / WAV_DIR / f"{subject}_{sentence}.wav").is_file()
            and (root / VERTICES_DIR / f"{subject}_{sentence}.npy").is_file()
        ]
        if spec.num_vertices is not None:
            for subject in dict.fromkeys(s for s, _ in present if s in self.templates):
                v = len(self.templates[subject])
                if v != spec.num_vertices:
                    raise TalkmeshError(
                        f"{root / TEMPLATES_FILE}: template of {subject} has {v} vertices, "
                        f"a {spec.kind} dataset has {spec.num_vertices}"
                    )
        usable = {name for subject, name in present if subject in self.templates}
        for subject, sentences in wanted.items():
            for sentence in sentences:
                name = f"{subject}_{sentence}"
                if name not in usable:
                    self.skipped.append(name)
                    continue
                problem = self._check(name, len(self.templates[subject]))
                if problem is None:
                    self.names.append(name)
                else:
                    self.reject(name, problem)
        self._faces: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.names)

    def _check(self, name: str, num_vertices: int) -> str | None:
        """Why the sequence cannot be used, from the file headers alone (cheap); None if fine."""
        import soundfile as sf

        npy, wav = self.root / VERTICES_DIR / f"{name}.npy", self.root / WAV_DIR / f"{name}.wav"
        try:
            arr = np.load(npy, mmap_mode="r", allow_pickle=False)
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as e:
            return f"{npy.name}: truncated or not a .npy file ({e})"
        if arr.ndim == 3 and arr.shape[1:] == (num_vertices, 3):
            arr = arr.reshape(len(arr), -1)
        if arr.ndim != 2 or arr.shape[1] != num_vertices * 3 or arr.dtype.kind != "f":
            return f"{npy.name}: shape {arr.shape} {arr.dtype}, expected [T, {num_vertices * 3}]"
        frames = -(-len(arr) // self.spec.stride)
        if frames < MIN_FRAMES:
            return f"{frames} motion frame(s), too short (at least {MIN_FRAMES})"
        try:
            info = sf.info(str(wav))
        except (sf.LibsndfileError, RuntimeError, OSError) as e:
            return f"{wav.name}: not readable audio ({e})"
        if info.frames == 0:
            return f"{wav.name}: no samples"
        seconds, motion = info.frames / info.samplerate, frames / self.spec.motion_fps
        if motion - seconds > AUDIO_TOLERANCE_FRAMES / self.spec.motion_fps:
            return f"{wav.name}: {seconds:.2f} s of audio for {motion:.2f} s of motion (no match)"
        return None

    def reject(self, name: str, why: str) -> None:
        warnings.warn(f"skipped {name}: {why}", TalkmeshWarning, stacklevel=3)
        self.bad.append(name)

    def drop_unloadable(self) -> int:
        """Load every sequence once and drop (with a warning naming it) those that fail, so
        everything after (statistics, DataLoader workers) sees only good files. Returns how many
        were dropped; an error if none is left."""
        keep = []
        for index, name in enumerate(list(self.names)):
            try:
                self[index]
            except TalkmeshError as e:
                self.reject(name, str(e))
                continue
            keep.append(name)
        dropped = len(self.names) - len(keep)
        self.names = keep
        if not keep:
            raise TalkmeshError(_empty_message(self))
        return dropped

    def sample_or_next(self, index: int) -> Sample:
        """``self[index]``, or if that sequence fails to load (NaN values, a corrupt body), a
        warning naming it and the next sequence that loads: a run never stops for one file."""
        for k in range(len(self.names)):
            i = (index + k) % len(self.names)
            try:
                return self[i]
            except TalkmeshError as e:
                if self.names[i] not in self.bad:
                    self.reject(self.names[i], str(e))
        raise TalkmeshError(f"{self.root}: no {self.split} sequence could be loaded")

    def __getitem__(self, index: int) -> Sample:
        from talkmesh.audio.loading import SAMPLE_RATE, load_audio

        name = self.names[index]
        subject, sentence = parse_name(name)
        template = self.templates[subject]
        vertices = load_motion(
            self.root / VERTICES_DIR / f"{name}.npy", len(template), self.spec.stride
        )
        wav = self.root / WAV_DIR / f"{name}.wav"
        audio = load_audio(wav)
        samples_per_frame = SAMPLE_RATE / self.spec.motion_fps
        needed = int(round(len(vertices) * samples_per_frame))
        short = needed - len(audio)
        if short > AUDIO_TOLERANCE_FRAMES * samples_per_frame:
            raise TalkmeshError(
                f"{wav}: {len(audio) / SAMPLE_RATE:.2f} s of audio for "
                f"{len(vertices) / self.spec.motion_fps:.2f} s of motion: the pair does not match"
            )
        if short > 0:
            audio = np.pad(audio, (0, short))
        style = (
            self.spec.train_subjects.index(subject) if subject in self.spec.train_subjects else -1
        )
        return Sample(name, subject, sentence, audio[:needed], vertices, template, style)

    @property
    def faces(self) -> np.ndarray | None:
        """(F, 3) triangles from the dataset's .ply (None if it has none)."""
        if self._faces is None:
            self._faces = read_faces(self.root, self.spec.faces_file)
        return self._faces


def read_faces(root: Path, name: str | None) -> np.ndarray | None:
    if name is not None:
        path = root / name
    else:
        plys = sorted(root.glob("*.ply"))
        if not plys:
            return None
        path = plys[0]
    if not path.is_file():
        return None
    import trimesh

    try:
        mesh = trimesh.load(path, process=False, force="mesh")
    except Exception as e:  # trimesh raises many types on bad files
        raise TalkmeshError(f"{path}: not a readable .ply ({type(e).__name__})") from None
    return np.asarray(mesh.faces, dtype=np.int64)


def open_dataset(
    kind: str,
    root: str | Path,
    split: str = "train",
    *,
    regions: str | Path | None = None,
    allow_empty: bool = False,
) -> MotionDataset:
    """The ``split`` of the dataset of ``kind`` at ``root`` (see the module docstring).

    A split without a usable sequence is an error (saying which splits have data) unless
    ``allow_empty``; unusable sequences are skipped with a warning and listed in ``.bad``.
    """
    if kind not in READERS:
        raise TalkmeshError(f"unknown dataset kind '{kind}': use one of {', '.join(READERS)}")
    root = Path(root)
    if not root.is_dir():
        raise TalkmeshError(f"dataset directory not found: {root}")
    for sub in (WAV_DIR, VERTICES_DIR):
        if not (root / sub).is_dir():
            raise TalkmeshError(f"{root / sub} is missing: {root} is not a {kind} dataset")
    if not (root / TEMPLATES_FILE).is_file():
        raise TalkmeshError(f"{root / TEMPLATES_FILE} is missing: {root} is not a {kind} dataset")
    spec = READERS[kind](root)
    if split not in spec.splits:
        raise TalkmeshError(f"{kind} has no split '{split}': use one of {', '.join(spec.splits)}")
    if regions is not None:
        source: Path | None = Path(regions)
    elif (root / REGIONS_DIR).is_dir():
        source = root / REGIONS_DIR
    elif (root / FLAME_MASKS_FILE).is_file():
        source = root / FLAME_MASKS_FILE
    else:
        source = None
    found = load_regions(source) if source is None or source.is_dir() else DatasetRegions()
    dataset = MotionDataset(spec, root, split, found)
    if source is not None and not source.is_dir():  # FLAME's masks: eyelids need a template
        template = next(iter(dataset.templates.values()), None)
        dataset.regions = load_regions(source, template)
    if not dataset.names and not allow_empty:
        raise TalkmeshError(_empty_message(dataset))
    return dataset


def _empty_message(dataset: MotionDataset) -> str:
    spec, root = dataset.spec, dataset.root
    listed = sum(len(s) for s in spec.splits[dataset.split].values())
    why = (
        f"{len(dataset.bad)} unusable (see the warnings)"
        if dataset.bad
        else f"none of its {listed} listed sequences has both a .npy and a .wav"
        if listed
        else "it lists no sequences"
    )
    others = [
        name
        for name, subjects in spec.splits.items()
        if name != dataset.split
        and any(
            (root / VERTICES_DIR / f"{s}_{t}.npy").is_file()
            for s, sents in subjects.items()
            for t in sents
        )
    ]
    hint = f"pass --split {' or --split '.join(others)}" if others else "add data to the split"
    if spec.kind == "synth":
        hint += " (or synthesise at least 3 subjects: talkmesh synth --subjects 3)"
    return f"{root}: the {dataset.split} split has no sequences ({why}): {hint}"


def report_skipped(dataset: MotionDataset, action: str) -> int:
    """Warn once, at the end of a run, how many sequences ``action`` skipped; returns that."""
    if dataset.bad:
        names = ", ".join(dataset.bad[:5]) + (" ..." if len(dataset.bad) > 5 else "")
        warnings.warn(
            f"{len(dataset.bad)} sequences skipped by {action} ({names})",
            TalkmeshWarning,
            stacklevel=2,
        )
    return len(dataset.bad)


# ---------------------------------------------------------------------------------------------
# Batching


class Batch(NamedTuple):
    """Padded arrays: audio (B, S_max), audio_lengths (B,), vertices (B, T_max, V, 3),
    templates (B, V, 3), motion_mask (B, T_max) bool, styles (B,)."""

    names: list[str]
    audio: np.ndarray
    audio_lengths: np.ndarray
    vertices: np.ndarray
    templates: np.ndarray
    motion_mask: np.ndarray
    styles: np.ndarray


def collate(samples: list[Sample]) -> Batch:
    """Pad a list of samples into a :class:`Batch` (padding repeats nothing: zeros, masked out)."""
    if not samples:
        raise TalkmeshError("cannot batch zero samples")
    num_v = samples[0].template.shape[0]
    if any(s.template.shape[0] != num_v for s in samples):
        raise TalkmeshError("samples in one batch must share a topology")
    B = len(samples)
    T = max(len(s.vertices) for s in samples)
    S = max(len(s.audio) for s in samples)
    audio = np.zeros((B, S), np.float32)
    vertices = np.zeros((B, T, num_v, 3), np.float32)
    mask = np.zeros((B, T), bool)
    for b, s in enumerate(samples):
        audio[b, : len(s.audio)] = s.audio
        vertices[b, : len(s.vertices)] = s.vertices
        vertices[b, len(s.vertices) :] = s.template  # padded frames rest at the template
        mask[b, : len(s.vertices)] = True
    return Batch(
        names=[s.name for s in samples],
        audio=audio,
        audio_lengths=np.array([len(s.audio) for s in samples], np.int64),
        vertices=vertices,
        templates=np.stack([s.template for s in samples]).astype(np.float32),
        motion_mask=mask,
        styles=np.array([s.style for s in samples], np.int64),
    )


def write_templates(path: str | Path, templates: dict[str, np.ndarray]) -> None:
    """Write a templates.pkl that both VOCASET-era readers and :func:`load_templates` accept."""
    buf = io.BytesIO()
    pickle.dump(
        {k: np.asarray(v, np.float64) for k, v in sorted(templates.items())}, buf, protocol=2
    )
    Path(path).write_bytes(buf.getvalue())
