"""``talkmesh benchmark CONFIG``: train, generate and evaluate every method x seed on one dataset.

The flow, each step resumable (the run can be killed anywhere and started again)::

    load_benchmark(CONFIG)                 validate the config, every recipe and the dataset
    for seed, method (seed-major):         WORK/<method>/seed<seed>/
        for stage in the recipe's stages:  .../<stage>/  train(recipe) with train.seed=<seed>,
                                           train.out_dir=<that dir>, init re-pointed to the
                                           earlier stage's new release, the benchmark's data;
                                           timing.json holds wall time and frames/s
        write_model_predictions            .../pred/    the last stage's release on the test split
        evaluate_dataset x PROTOCOLS       .../scores.json
    baselines (seed-free)                  WORK/baselines/<name>/pred
    ablation (CodeTalker Fig. 7)           WORK/ablation/<cell>/<stage>: stage-1 reconstruction
                                           LVE and codebook usage per grid cell
    speed                                  generation time and real-time factor per method
    report                                 DOCS/<name>.md, DOCS/<name>.json, DOCS/<name>/*.png|mp4

Resume rules: a stage whose ``model.safetensors`` exists is skipped, one with ``last.ckpt`` but no
model is resumed (``train(recipe, resume=True)``), anything else starts afresh. A stage whose
recipe (``recipe.json``, e.g. after an epochs change in the config) or init (the earlier stage's
release, by sha256) changed since it was trained is stale and retrained; predictions are
regenerated when the release they came from changed (``pred/done.json`` keeps its digest).
Completed stages drop their Lightning checkpoints unless ``keep_checkpoints: true`` (hundreds of
MB each; the release is what the benchmark needs).

Aggregates are the mean and the sample standard deviation (ddof=1) over seeds. The paper's ordering
claims (CodeTalker Table 1: LVE CodeTalker < FaceFormer < MeshTalk, VOCA; CodeTalker best in FDD)
are checked between the methods the config names ``codetalker``, ``faceformer``, ``meshtalk`` and
``voca``: a claim holds or is contradicted only when the difference of means exceeds the sum of
the two seed standard deviations, else it is "within seed variance". FDD is compared by its
magnitude (the anchor protocol's FDD is signed).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import re
import shutil
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from itertools import product
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np

from talkmesh.config import from_dict, read_yaml, to_dict
from talkmesh.errors import MissingDependencyError, TalkmeshError

BASELINES = ("static", "procedural")
RESERVED = ("baselines", "ablation")  # directories of WORK that are not methods
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
TIMING_FILE = "timing.json"
DONE_FILE = "done.json"
SCORES_FILE = "scores.json"
METRICS = ("lve", "fdd", "mve", "lip_sync")
# (metric, scale, unit) per protocol: the units of ``talkmesh evaluate``'s tables
UNITS: dict[str, dict[str, tuple[float, str]]] = {
    "codetalker": {
        "lve": (1e4, "x1e-4, squared"),
        "fdd": (1e5, "x1e-5, signed"),
        "mve": (1e3, "mm"),
        "lip_sync": (1.0, "r"),
    },
    "physical": {
        "lve": (1e3, "mm"),
        "fdd": (1e3, "mm, absolute"),
        "mve": (1e3, "mm"),
        "lip_sync": (1.0, "r"),
    },
}
LABELS = {"lve": "LVE", "fdd": "FDD", "mve": "MVE", "lip_sync": "lip sync"}
# CodeTalker Table 1 (VOCASET, BIWI): (metric, better, worse), lower is better
CLAIMS: tuple[tuple[str, str, str], ...] = (
    ("lve", "codetalker", "faceformer"),
    ("lve", "faceformer", "meshtalk"),
    ("lve", "faceformer", "voca"),
    ("fdd", "codetalker", "faceformer"),
    ("fdd", "codetalker", "meshtalk"),
    ("fdd", "codetalker", "voca"),
)
# the paper's symbols for the VQ keys of the ablation grid (Fig. 7: P, H; Table 4: C, N)
SYMBOLS = {"temporal_unit": "P", "components": "H", "code_dim": "C", "codebook_size": "N"}
MAX_PNG_BYTES = 200_000
MAX_VIDEO_BYTES = 2_000_000


# ---------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True)
class DataSpec:
    """The dataset every method trains on (its recipes' data.kind/root are replaced) and the split
    they are evaluated on."""

    kind: str = "synth"
    root: str = "corpus/synth"
    split: str = "test"
    regions: str | None = None  # lve.txt/fdd.txt directory, if not in the dataset


@dataclass(frozen=True)
class MethodSpec:
    """A recipe and its overrides: ``overrides`` reach every stage, ``stage_overrides`` one stage
    each and win over ``overrides``."""

    recipe: str = ""
    overrides: tuple[str, ...] = ()
    stage_overrides: dict[str, tuple[str, ...]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.recipe:
            raise ValueError("recipe is required: a training recipe YAML (see configs/)")


@dataclass(frozen=True)
class AblationSpec:
    """CodeTalker Fig. 7: one stage (the motion VQ-VAE) trained per cell of ``grid`` (dotted key ->
    values), scored by its reconstruction of the evaluation split."""

    grid: dict[str, tuple[Any, ...]] = field(default_factory=dict)
    method: str = "codetalker"
    stage: str = "motion"
    seed: int = 0
    overrides: tuple[str, ...] = ()  # after the method's own, before the cell's

    def __post_init__(self) -> None:
        if not self.grid or any(len(v) == 0 for v in self.grid.values()):
            raise ValueError("ablation.grid must map dotted keys to non-empty lists of values")


@dataclass(frozen=True)
class SpeedSpec:
    seconds: tuple[float, ...] = (4.0, 30.0)  # audio lengths
    repeats: int = 2  # the minimum is reported

    def __post_init__(self) -> None:
        if any(s <= 0 for s in self.seconds) or self.repeats < 1:
            raise ValueError("speed.seconds must be positive and speed.repeats at least 1")


@dataclass(frozen=True)
class BenchmarkConfig:
    name: str = ""
    methods: dict[str, MethodSpec] = field(default_factory=dict)
    data: DataSpec = DataSpec()
    seeds: tuple[int, ...] = (0, 1, 2)
    work_dir: str = "runs/benchmark"
    docs_dir: str = "docs/benchmarks"
    baselines: tuple[str, ...] = BASELINES
    ablation: AblationSpec | None = None
    speed: SpeedSpec = SpeedSpec()
    samples: int = 3  # test sentences in the lip-distance figure; the first is the video's
    video: bool = True
    video_size: int = 256  # pixels per panel
    keep_checkpoints: bool = False  # keep Lightning's last.ckpt/epochNNN.ckpt of finished stages
    discussion: str = (
        ""  # a hand-written reading of the results (path or URL), linked from the report
    )

    def __post_init__(self) -> None:
        if not NAME.match(self.name):
            raise ValueError("name is required: letters, digits, '_', '-' or '.' (a file name)")
        if not self.methods:
            raise ValueError("methods must name at least one method")
        for m in self.methods:
            if not NAME.match(m) or m in RESERVED:
                raise ValueError(
                    f"method name {m!r}: use letters, digits, '_', '-', '.' "
                    f"(not {' or '.join(RESERVED)})"
                )
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise ValueError("seeds must be a non-empty list of distinct integers")
        unknown = sorted(set(self.baselines) - set(BASELINES))
        if unknown:
            raise ValueError(f"unknown baseline {unknown[0]!r}: use {' or '.join(BASELINES)}")
        if self.samples < 0 or self.video_size < 16:
            raise ValueError("samples must be >= 0 and video_size >= 16")
        if self.ablation is not None and self.ablation.method not in self.methods:
            raise ValueError(f"ablation.method {self.ablation.method!r} is not in methods")


class StagePlan(NamedTuple):
    """One training stage of one method and seed, with its re-pointed out_dir and init."""

    method: str
    seed: int
    stage: str
    recipe: Any  # talkmesh.training.trainer.Recipe
    init_stage: str | None  # the earlier stage whose release is this stage's init

    @property
    def out_dir(self) -> Path:
        return Path(self.recipe.train.out_dir)

    @property
    def release(self) -> Path:
        return self.out_dir / "model.safetensors"


class Cell(NamedTuple):
    """One ablation grid cell: its values, its label and its single stage."""

    values: dict[str, Any]
    slug: str
    label: str
    plan: StagePlan


class BenchmarkResult(NamedTuple):
    """What ``run_benchmark`` wrote and did (``trained``: stage dirs trained or resumed now)."""

    markdown: Path
    json: Path
    figures: list[Path]
    trained: list[Path]
    predicted: list[Path]


def load_benchmark(path: str | Path, *, check_data: bool = True) -> BenchmarkConfig:
    """A benchmark YAML -> :class:`BenchmarkConfig`; its recipes, stage names and (with
    ``check_data``) its dataset checked.

    Every error is a one-line :class:`TalkmeshError` naming the file.
    """
    data = read_yaml(path)
    try:
        cfg = from_dict(BenchmarkConfig, data)
    except TalkmeshError as e:
        raise TalkmeshError(f"{path}: {e}") from None
    for method in cfg.methods:
        try:
            stages = method_stages(cfg, method, cfg.seeds[0])
        except TalkmeshError as e:
            raise TalkmeshError(f"{path}: methods.{method}: {e}") from None
        spec = cfg.methods[method]
        names = [p.stage for p in stages]
        unknown = sorted(set(spec.stage_overrides) - set(names))
        if unknown:
            raise TalkmeshError(
                f"{path}: methods.{method}.stage_overrides: {spec.recipe} has no stage "
                f"{unknown[0]!r} (its stages: {', '.join(names)})"
            )
    if cfg.ablation is not None:
        try:
            cells = ablation_cells(cfg)
        except TalkmeshError as e:
            raise TalkmeshError(f"{path}: ablation: {e}") from None
        task = cells[0].plan.recipe.task
        if task != "codetalker-stage1":
            raise TalkmeshError(
                f"{path}: ablation: stage {cfg.ablation.stage!r} of {cfg.ablation.method} is task "
                f"{task}: the ablation reconstructs through a CodeTalker stage-1 VQ-VAE"
            )
    if check_data:
        try:
            _open(cfg)  # a missing corpus fails now, not after hours of training
        except TalkmeshError as e:
            raise TalkmeshError(f"{path}: data: {e}") from None
    return cfg


def _open(cfg: BenchmarkConfig, split: str | None = None):
    from talkmesh.datasets.reader import open_dataset

    d = cfg.data
    try:
        ds = open_dataset(d.kind, d.root, split or d.split, regions=d.regions)
    except TalkmeshError as e:
        hint = f" (make it with `talkmesh synth --out {d.root}`)" if d.kind == "synth" else ""
        raise TalkmeshError(f"{e}{hint}") from None
    if len(ds) == 0:
        raise TalkmeshError(f"{d.root}: the {ds.split} split has no sequences")
    return ds


def _recipe_file(recipe: str) -> dict[str, Any]:
    if not Path(recipe).is_file():
        raise TalkmeshError(f"recipe not found: {recipe}")
    data = read_yaml(recipe)
    if "stages" not in data and "task" not in data:
        raise TalkmeshError(
            f"{recipe} has neither task: (one stage) nor stages: (several): not a training recipe"
        )
    return data


def _load_stages(recipe: str, overrides: list[str]) -> list[tuple[str, Any]]:
    from talkmesh.training.trainer import load_recipes

    try:
        return load_recipes(recipe, overrides)
    except ImportError as e:  # a registered task whose model module is not there yet
        raise TalkmeshError(f"{recipe}: its task's module is not available ({e})") from None


def method_stages(
    cfg: BenchmarkConfig,
    method: str,
    seed: int,
    *,
    root: Path | None = None,
    extra: tuple[str, ...] = (),
    only_stage: str | None = None,
) -> list[StagePlan]:
    """The stages of ``method`` for ``seed``, in training order, with the benchmark's overrides.

    Every override reaches every stage in this order: the method's ``overrides``, its
    ``stage_overrides``, ``extra`` (the ablation's), then ``train.seed``. Each stage trains into
    ``root/<stage>`` (default ``WORK/<method>/seed<seed>/<stage>``) on the benchmark's data; an
    ``init`` that named an earlier stage's release names that stage's new release instead
    (for ``only_stage``, the release of the main run for this seed).
    """
    spec = cfg.methods[method]
    raw = _recipe_file(spec.recipe)
    multi = "stages" in raw
    names = [n for n, _ in _load_stages(spec.recipe, list(spec.overrides))] if multi else [None]
    overrides: list[str] = []
    for name in names:
        prefix = f"stages.{name}." if name is not None else ""
        own = spec.stage_overrides.get(name, ()) if name is not None else ()
        if name is None:  # a one-stage recipe: its stage is named after its task
            own = spec.stage_overrides.get(str(raw.get("task")), ())
        for o in (*spec.overrides, *own, *extra, f"train.seed={seed}"):
            overrides.append(o if o.startswith("stages.") else prefix + o)
    stages = _load_stages(spec.recipe, overrides)
    releases = {Path(r.train.out_dir, "model.safetensors").resolve(): n for n, r in stages}
    seed_dir = Path(cfg.work_dir) / method / f"seed{seed}"
    root = root or seed_dir
    plans, earlier = [], set()
    for name, recipe in stages:
        init_stage = releases.get(Path(recipe.init).resolve()) if recipe.init else None
        if init_stage is not None and init_stage not in earlier:
            raise TalkmeshError(f"{spec.recipe}: stage {name}'s init is a later stage's release")
        earlier.add(name)
        if only_stage is not None and name != only_stage:
            continue
        init = recipe.init
        if init_stage is not None:
            base = seed_dir if only_stage is not None else root
            init = str(base / init_stage / "model.safetensors")
        data = replace(
            recipe.data,
            kind=cfg.data.kind,
            root=cfg.data.root,
            regions=cfg.data.regions or recipe.data.regions,
        )
        train_cfg = replace(recipe.train, out_dir=str(root / name))
        plans.append(
            StagePlan(
                method,
                seed,
                name,
                replace(recipe, init=init, data=data, train=train_cfg),
                init_stage,
            )
        )
    if only_stage is not None and not plans:
        raise TalkmeshError(
            f"{spec.recipe} has no stage {only_stage!r} (its stages: "
            f"{', '.join(n for n, _ in stages)})"
        )
    return plans


def _fmt_value(v: Any) -> str:
    return json.dumps(v) if not isinstance(v, str) else v


def ablation_cells(cfg: BenchmarkConfig) -> list[Cell]:
    """The grid's cells in row-major order, each with its one-stage plan."""
    ab = cfg.ablation
    assert ab is not None
    keys = list(ab.grid)
    cells = []
    for values in product(*(ab.grid[k] for k in keys)):
        cell = dict(zip(keys, values))
        short = [(k.split(".")[-1], v) for k, v in cell.items()]
        slug = "-".join(f"{k}{_fmt_value(v)}" for k, v in short)
        label = ", ".join(f"{SYMBOLS.get(k, k)}={_fmt_value(v)}" for k, v in short)
        extra = (*ab.overrides, *(f"{k}={json.dumps(v)}" for k, v in cell.items()))
        root = Path(cfg.work_dir) / "ablation" / slug
        (plan,) = method_stages(
            cfg, ab.method, ab.seed, root=root, extra=extra, only_stage=ab.stage
        )
        cells.append(Cell(cell, slug, label, plan))
    return cells


# ---------------------------------------------------------------------------------------------
# State on disk: digests, timing records, what each step would do


_DIGESTS: dict[tuple[str, int, int], str] = {}


def file_digest(path: str | Path) -> str:
    """sha256 of a file, memoised on (path, size, mtime)."""
    p = Path(path)
    st = p.stat()
    key = (str(p.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        h = hashlib.sha256()
        with p.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        _DIGESTS[key] = h.hexdigest()
    return _DIGESTS[key]


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    tmp.replace(path)


StageState = Literal["done", "resume", "train", "stale", "waiting"]


def stage_state(plan: StagePlan) -> StageState:
    """done (skip), resume (last.ckpt, no model), train (nothing yet), stale (its recipe or its
    init changed since it was trained: retrain) or waiting (its init does not exist yet)."""
    init = plan.recipe.init
    if init and not Path(init).is_file():
        return "waiting"
    record = _read_json(plan.out_dir / TIMING_FILE)
    if record is not None and init and record.get("init_digest") != file_digest(init):
        return "stale"
    trained = _read_json(plan.out_dir / "recipe.json")  # written by train()
    if trained is not None and trained != json.loads(json.dumps(to_dict(plan.recipe))):
        return "stale"
    if plan.release.is_file():
        return "done"
    return "resume" if (plan.out_dir / "last.ckpt").is_file() else "train"


def predictions_done(pred_dir: Path, release: Path | None) -> bool:
    """Whether ``pred_dir`` is complete (for a model: from this very release)."""
    record = _read_json(pred_dir / DONE_FILE)
    if record is None:
        return False
    if release is None:
        return True
    return release.is_file() and record.get("model_digest") == file_digest(release)


# ---------------------------------------------------------------------------------------------
# Running the steps


class Log:
    """One line per step on stderr, with the time since the benchmark started."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet
        self.start = time.perf_counter()

    def __call__(self, message: str) -> None:
        if not self.quiet:
            elapsed = int(time.perf_counter() - self.start)
            stamp = f"{elapsed // 3600}:{elapsed // 60 % 60:02d}:{elapsed % 60:02d}"
            print(f"[benchmark {stamp}] {message}", file=sys.stderr, flush=True)


def _epoch_frames(recipe) -> tuple[int, int]:
    """(samples, motion frames) of one training epoch: each sample contributes its crop."""
    from talkmesh.datasets.reader import VERTICES_DIR, open_dataset

    d = recipe.data
    ds = open_dataset(d.kind, d.root, d.train_split, regions=d.regions)
    max_frames = int(round(d.max_seconds * ds.spec.motion_fps)) if d.max_seconds else 0
    frames = 0
    for name in ds.names:
        disk = np.load(ds.root / VERTICES_DIR / f"{name}.npy", mmap_mode="r").shape[0]
        n = math.ceil(disk / ds.spec.stride)
        frames += min(n, max_frames) if max_frames else n
    return len(ds), frames


def _checkpoint_epochs(last: Path) -> int:
    """Epochs already completed by the run that wrote ``last``."""
    import torch

    ckpt = torch.load(last, map_location="cpu", weights_only=False, mmap=True)
    return int(ckpt.get("epoch", -1)) + 1


def train_stage(plan: StagePlan, *, keep_checkpoints: bool, progress: bool) -> dict[str, Any]:
    """Train (or resume) one stage; returns and writes its timing record (``timing.json``)."""
    from talkmesh.training.trainer import train

    state = stage_state(plan)
    if state == "waiting":
        raise TalkmeshError(f"{plan.recipe.init} is missing: train stage {plan.init_stage} first")
    out = plan.out_dir
    resume = state == "resume"
    if not resume and out.exists():  # nothing worth keeping: a stale run or a half-made dir
        shutil.rmtree(out)
    recipe = plan.recipe
    samples, frames_per_epoch = _epoch_frames(recipe)
    done_before = _checkpoint_epochs(out / "last.ckpt") if resume else 0
    epochs = max(0, recipe.train.epochs - done_before)
    steps_per_epoch = math.ceil(samples / recipe.data.batch_size)
    fraction = 1.0
    if recipe.train.max_steps > 0:  # Lightning stops at max_steps whatever the epochs
        fraction = min(1.0, recipe.train.max_steps / (recipe.train.epochs * steps_per_epoch))
    init_digest = file_digest(recipe.init) if recipe.init else None
    record: dict[str, Any] = {
        "method": plan.method,
        "seed": plan.seed,
        "stage": plan.stage,
        "task": recipe.task,
        "status": "training",
        "init": recipe.init,
        "init_digest": init_digest,
    }
    _write_json(out / TIMING_FILE, record)
    t0 = time.perf_counter()
    train(recipe, resume=resume, progress=progress)
    seconds = time.perf_counter() - t0
    frames = int(round(frames_per_epoch * epochs * fraction))
    record.update(
        status="done",
        resumed=resume,
        epochs=recipe.train.epochs,
        epochs_trained=epochs,
        batch_size=recipe.data.batch_size,
        max_seconds=recipe.data.max_seconds,
        samples_per_epoch=samples,
        frames_per_epoch=frames_per_epoch,
        frames=frames,
        seconds=seconds,
        frames_per_second=frames / seconds if seconds > 0 else None,
        finished=_now(),
    )
    _write_json(out / TIMING_FILE, record)
    if not keep_checkpoints:
        for ckpt in out.glob("*.ckpt"):
            ckpt.unlink()
    return record


def predict(
    cfg: BenchmarkConfig, release: Path, pred_dir: Path, *, progress: bool, mode: str = "fast"
) -> dict[str, Any]:
    """The release's predictions for the evaluation split (regenerated if the release changed)."""
    from talkmesh.evaluation.evaluate import write_model_predictions

    if pred_dir.exists():
        shutil.rmtree(pred_dir)
    digest = file_digest(release)
    t0 = time.perf_counter()
    n = write_model_predictions(
        cfg.data.kind,
        cfg.data.root,
        pred_dir,
        str(release),
        split=cfg.data.split,
        mode=mode,
        progress=progress,
    )
    record = {
        "model": str(release),
        "model_digest": digest,
        "files": n,
        "mode": mode,
        "seconds": time.perf_counter() - t0,
        "finished": _now(),
    }
    _write_json(pred_dir / DONE_FILE, record)
    return record


def baseline(cfg: BenchmarkConfig, name: str, pred_dir: Path, *, progress: bool) -> dict[str, Any]:
    from talkmesh.evaluation.evaluate import write_baseline

    if pred_dir.exists():
        shutil.rmtree(pred_dir)
    t0 = time.perf_counter()
    n = write_baseline(
        cfg.data.kind, cfg.data.root, pred_dir, method=name, split=cfg.data.split, progress=progress
    )
    record = {"baseline": name, "files": n, "seconds": time.perf_counter() - t0, "finished": _now()}
    _write_json(pred_dir / DONE_FILE, record)
    return record


def score(dataset, pred_dir: Path) -> dict[str, dict[str, Any]]:
    """``scores_to_json`` of every protocol for a complete prediction directory."""
    from talkmesh.evaluation.evaluate import evaluate_dataset, scores_to_json
    from talkmesh.evaluation.metrics import PROTOCOLS

    out = {}
    for protocol in PROTOCOLS:
        scores, missing = evaluate_dataset(dataset, pred_dir, protocol=protocol)
        if missing:
            raise TalkmeshError(
                f"{pred_dir}: no prediction for {len(missing)} sequences "
                f"(e.g. {missing[0]}): delete the directory to regenerate it"
            )
        out[protocol] = scores_to_json(scores, dataset.split)
    return out


def _summary(scores: dict[str, dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    return {p: {m: s[m] for m in (*METRICS, "n_sequences", "n_frames")} for p, s in scores.items()}


def codebook_usage(release: Path, dataset) -> dict[str, Any]:
    """Codes a stage-1 VQ-VAE uses on ``dataset``: distinct codes, their share and perplexity."""
    import torch

    from talkmesh.models.release import load_model

    net = load_model(release)
    size = net.cfg.vq.codebook_size
    counts = torch.zeros(size, dtype=torch.float64)
    with torch.inference_mode():
        for i in range(len(dataset)):
            s = dataset[i]
            motion = torch.from_numpy(s.vertices - s.template).flatten(1)[None]
            codes = net.vqvae(motion).codes
            counts += torch.bincount(codes.flatten(), minlength=size).double()
    p = counts / counts.sum()
    entropy = -(p[p > 0] * p[p > 0].log()).sum()
    used = int((counts > 0).sum())
    return {
        "codebook_size": size,
        "codes_used": used,
        "usage": used / size,
        "perplexity": float(entropy.exp()),
    }


def _test_audio(dataset, seconds: float) -> np.ndarray:
    """``seconds`` of the split's speech, its sequences one after the other (repeated if short)."""
    from talkmesh.audio.loading import SAMPLE_RATE

    need = int(round(seconds * SAMPLE_RATE))
    parts, have, i = [], 0, 0
    while have < need:
        a = dataset[i % len(dataset)].audio
        parts.append(a)
        have += len(a)
        i += 1
    return np.concatenate(parts)[:need].astype(np.float32)


def measure_speed(release: Path, dataset, spec: SpeedSpec) -> list[dict[str, Any]]:
    """Generation time (min over repeats) and real-time factor at each audio length."""
    import torch

    from talkmesh.models.release import load_model

    net = load_model(release)
    template = torch.from_numpy(dataset[0].template)[None]
    styles = list(net.styles)
    weights = torch.full((1, len(styles)), 1.0 / len(styles)) if styles else None
    rows = []
    for seconds in spec.seconds:
        audio = torch.from_numpy(_test_audio(dataset, seconds))[None]
        times = []
        for _ in range(spec.repeats):
            t0 = time.perf_counter()
            with torch.inference_mode():
                out = net.generate(audio, template, style_weights=weights, seed=0)
            times.append(time.perf_counter() - t0)
        best = min(times)
        rows.append(
            {
                "audio_seconds": seconds,
                "frames": int(out.shape[1]),
                "seconds": best,
                "all_seconds": times,
                "real_time_factor": best / seconds,
                "frames_per_second": out.shape[1] / best,
            }
        )
    return rows


def machine_info() -> dict[str, Any]:
    """Which machine produced the numbers."""
    import torch

    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        usable = os.cpu_count()
    return {
        "cpu_model": model or platform.processor() or platform.machine(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
        "usable_cpus": usable,
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


# ---------------------------------------------------------------------------------------------
# Aggregation and claims


def mean_std(values: list[float | None]) -> dict[str, Any]:
    """Mean and sample std (ddof=1; None for fewer than two values) of the finite values."""
    vals = [float(v) for v in values if v is not None and np.isfinite(v)]
    if not vals:
        return {"mean": None, "std": None, "n": 0}
    std = float(np.std(vals, ddof=1)) if len(vals) > 1 else None
    return {"mean": float(np.mean(vals)), "std": std, "n": len(vals)}


def aggregate(per_seed: dict[int, dict[str, dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    """{seed: {protocol: summary}} -> {protocol: {metric: mean/std/n, "abs_fdd": ...}}."""
    protocols = next(iter(per_seed.values())).keys()
    out: dict[str, dict[str, Any]] = {}
    for p in protocols:
        out[p] = {m: mean_std([per_seed[s][p][m] for s in per_seed]) for m in METRICS}
        out[p]["abs_fdd"] = mean_std([abs(per_seed[s][p]["fdd"]) for s in per_seed])
    return out


def check_claims(
    aggregated: dict[str, dict[str, dict[str, Any]]],
    per_seed: dict[str, list[dict[str, dict[str, Any]]]] | None = None,
) -> list[dict[str, Any]]:
    """The paper's pairwise claims between the methods present, per protocol, with verdicts.

    ``per_seed`` (method -> one {protocol: summary} per seed) adds how many of the pairs
    (seed of the better-claimed method, seed of the other) are ordered as claimed.
    """
    rows = []
    for metric, better, worse in CLAIMS:
        if better not in aggregated or worse not in aggregated:
            continue
        key = "abs_fdd" if metric == "fdd" else metric
        for protocol in aggregated[better]:
            a, b = aggregated[better][protocol][key], aggregated[worse][protocol][key]
            if a["mean"] is None or b["mean"] is None:
                continue
            diff = a["mean"] - b["mean"]
            spread = (a["std"] or 0.0) + (b["std"] or 0.0)
            if abs(diff) > spread:
                verdict = "holds" if diff < 0 else "contradicted"
                if a["std"] is None or b["std"] is None:
                    verdict += " (one seed: no variance estimate)"
            else:
                verdict = "within seed variance"
            pairs_holding = pairs_total = None
            if per_seed and better in per_seed and worse in per_seed:
                va = [_claim_value(r[protocol], metric) for r in per_seed[better]]
                vb = [_claim_value(r[protocol], metric) for r in per_seed[worse]]
                pairs_holding = sum(x < y for x in va for y in vb)
                pairs_total = len(va) * len(vb)
            rows.append(
                {
                    "metric": metric,
                    "protocol": protocol,
                    "better": better,
                    "worse": worse,
                    "better_mean": a["mean"],
                    "better_std": a["std"],
                    "worse_mean": b["mean"],
                    "worse_std": b["std"],
                    "difference": diff,
                    "std_sum": spread,
                    "seeds": min(a["n"], b["n"]),
                    "verdict": verdict,
                    "seed_pairs_holding": pairs_holding,
                    "seed_pairs": pairs_total,
                }
            )
    return rows


def _claim_value(summary: dict[str, Any], metric: str) -> float:
    """One seed's value of a claim's metric (FDD by its absolute value, as the aggregate)."""
    v = float(summary[metric])
    return abs(v) if metric == "fdd" else v


# ---------------------------------------------------------------------------------------------
# Figures


def _matplotlib():
    try:
        from matplotlib.collections import PolyCollection
        from matplotlib.figure import Figure
    except ImportError:
        raise MissingDependencyError("matplotlib", "dev", "benchmark figures") from None
    return Figure, PolyCollection


def save_png(fig, path: Path) -> Path:
    """A figure as a palette PNG (docs images stay small)."""
    from io import BytesIO

    from PIL import Image

    buf = BytesIO()
    fig.savefig(buf, format="png")
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.open(buf).convert("RGB").quantize(colors=128).save(path, optimize=True)
    return path


def _load_pred(pred_dir: Path, name: str, num_vertices: int) -> np.ndarray:
    return np.load(pred_dir / f"{name}.npy").reshape(-1, num_vertices, 3)


def _lip_pairs(num_vertices: int) -> np.ndarray | None:
    from talkmesh.face.assets import load_head

    head = load_head()
    if num_vertices != head.num_vertices:
        return None
    return np.asarray(head.regions.lip_pair).reshape(-1, 2)


def sample_indices(n: int, k: int) -> list[int]:
    """``k`` sequence indices spread over a split of ``n`` (the first is always 0)."""
    if k <= 0 or n == 0:
        return []
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(k, n))})


def lip_figure(dataset, indices: list[int], preds: dict[str, Path], path: Path) -> Path | None:
    """Paper Figs. 5/8: upper-lower lip distance over time, every method vs ground truth."""
    from talkmesh.evaluation.metrics import lip_opening_pairs

    Figure, _ = _matplotlib()
    first = dataset[indices[0]]
    pairs = _lip_pairs(len(first.template))
    if pairs is None:
        return None
    fps = dataset.spec.motion_fps
    fig = Figure(figsize=(10, 2.1 * len(indices) + 0.4), dpi=80)
    axes = fig.subplots(len(indices), 1, squeeze=False)[:, 0]
    for ax, index in zip(axes, indices):
        s = dataset[index]
        t = np.arange(len(s.vertices)) / fps
        ax.plot(
            t, lip_opening_pairs(s.vertices, pairs) * 1e3, color="k", lw=2.0, label="ground truth"
        )
        for k, (label, d) in enumerate(preds.items()):
            v = _load_pred(d, s.name, len(s.template))
            style = "--" if label in BASELINES else "-"
            ax.plot(
                np.arange(len(v)) / fps,
                lip_opening_pairs(v, pairs) * 1e3,
                style,
                lw=1.1,
                color=f"C{k}",
                label=label,
            )
        ax.set_title(s.name, fontsize=9)
        ax.set_ylabel("lip distance (mm)", fontsize=8)
        ax.set_xlim(0, t[-1] if len(t) > 1 else 1)
        ax.tick_params(labelsize=7)
    axes[-1].set_xlabel("time (s)", fontsize=8)
    axes[0].legend(fontsize=7, ncol=min(4, len(preds) + 1), loc="upper right")
    fig.tight_layout()
    return save_png(fig, path)


def draw_on_mesh(
    ax, verts: np.ndarray, faces: np.ndarray | None, values: np.ndarray, vmax: float, poly=None
) -> Any:
    """Front orthographic view (x right, y up, +z to the viewer), faces coloured by the mean of
    their vertices' values on one scale 0..vmax; back-facing triangles culled, the rest drawn back
    to front. ``poly``: matplotlib's PolyCollection (imported here when None)."""
    if poly is None:
        poly = _matplotlib()[1]
    if faces is None:
        order = np.argsort(verts[:, 2])
        art = ax.scatter(
            verts[order, 0],
            verts[order, 1],
            c=values[order],
            s=1,
            cmap="inferno",
            vmin=0,
            vmax=vmax,
            linewidths=0,
        )
        shown = verts
    else:
        tri = verts[faces]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        order = np.argsort(tri[:, :, 2].mean(1))
        order = order[normals[order, 2] > 0]
        # edges in the face colour: no hairline gaps between the triangles
        colour = values[faces[order]].mean(1)
        art = poly(tri[order, :, :2], array=colour, cmap="inferno", edgecolors="face", lw=0.3)
        art.set_clim(0, vmax)
        ax.add_collection(art)
        shown = tri[order].reshape(-1, 3)
    ax.set_xlim(shown[:, 0].min(), shown[:, 0].max())
    ax.set_ylim(shown[:, 1].min(), shown[:, 1].max())
    ax.set_aspect("equal")
    ax.axis("off")
    return art


def motion_figure(dataset, preds: dict[str, Path], path: Path) -> Path:
    """Paper Fig. 4: per-vertex mean and std over time of the inter-frame motion, on the mesh."""
    from talkmesh.evaluation.metrics import motion_statistics

    Figure, poly = _matplotlib()
    samples = [dataset[i] for i in range(len(dataset))]
    V = len(samples[0].template)
    rows = [("ground truth", motion_statistics([s.vertices for s in samples]))]
    for label, d in preds.items():
        rows.append((label, motion_statistics([_load_pred(d, s.name, V) for s in samples])))
    top = [max(float(st[k].max()) for _, st in rows) * 1e3 or 1.0 for k in (0, 1)]
    fig = Figure(figsize=(2.3 * len(rows) + 0.8, 5.2), dpi=72)
    axes = fig.subplots(2, len(rows), squeeze=False)
    arts: list[Any] = [None, None]
    for k, (label, (mean, std)) in enumerate(rows):
        for r, (values, name) in enumerate(((mean, "mean"), (std, "std"))):
            arts[r] = draw_on_mesh(
                axes[r, k], samples[0].template, dataset.faces, values * 1e3, top[r], poly
            )
            title = f"{label}\n{name}" if r == 0 else name
            axes[r, k].set_title(f"{title} (max {values.max() * 1e3:.2f})", fontsize=8)
    for r in (0, 1):
        fig.colorbar(arts[r], ax=axes[r, :].tolist(), shrink=0.8, label="mm / frame")
    fig.suptitle(
        f"inter-frame motion per vertex, {dataset.split} split "
        f"({len(samples)} sequences; seed-0 models)",
        fontsize=9,
    )
    return save_png(fig, path)


def ablation_figure(ab: AblationSpec, cells: list[dict[str, Any]], path: Path) -> Path:
    """Heatmaps of reconstruction LVE (mm) and codebook usage (%) over the grid."""
    Figure, _ = _matplotlib()
    keys = list(ab.grid)
    if len(keys) == 2:
        rows, cols = [list(ab.grid[keys[0]]), list(ab.grid[keys[1]])]
    else:
        rows, cols = [None], [c["label"] for c in cells]
    shape = (len(rows), len(cols))
    lve = np.array([c["physical"]["lve"] * 1e3 for c in cells]).reshape(shape)
    usage = np.array([c["usage"]["usage"] * 100 for c in cells]).reshape(shape)
    fig = Figure(figsize=(1.2 * len(cols) * 2 + 2.4, 0.7 * len(rows) + 1.4), dpi=80)
    axes = fig.subplots(1, 2)
    for ax, values, title, cmap in (
        (axes[0], lve, "reconstruction LVE (mm)", "viridis_r"),
        (axes[1], usage, "codebook usage (%)", "viridis"),
    ):
        im = ax.imshow(values, cmap=cmap, aspect="auto")
        for (i, j), v in np.ndenumerate(values):
            r, g, b, _ = im.cmap(im.norm(v))
            dark = 0.299 * r + 0.587 * g + 0.114 * b < 0.5  # white text on dark cells
            text = f"{v:.2f}" if values is lve else f"{v:.0f}"
            ax.text(j, i, text, ha="center", va="center", fontsize=8, color="w" if dark else "k")
        ax.set_xticks(range(len(cols)))
        ax.set_yticks(range(len(rows)))
        if len(keys) == 2:
            short = [SYMBOLS.get(k.split(".")[-1], k.split(".")[-1]) for k in keys]
            ax.set_xticklabels([f"{short[1]}={_fmt_value(c)}" for c in cols], fontsize=8)
            ax.set_yticklabels([f"{short[0]}={_fmt_value(r)}" for r in rows], fontsize=8)
        else:
            ax.set_xticklabels([str(c) for c in cols], fontsize=7, rotation=30)
            ax.set_yticklabels([""])
        ax.set_title(title, fontsize=9)
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.tight_layout()
    return save_png(fig, path)


def side_by_side_video(
    dataset, index: int, preds: dict[str, Path], path: Path, size: int, progress: bool
) -> Path | None:
    """Ground truth and every method (seed 0) on one test sentence, with its audio."""
    from talkmesh.animation import Animation
    from talkmesh.audio.loading import SAMPLE_RATE
    from talkmesh.output.render import render_side_by_side

    faces = dataset.faces
    if faces is None:
        return None
    s = dataset[index]
    fps = dataset.spec.motion_fps
    anims = [Animation(s.vertices, faces, fps, audio=s.audio, sample_rate=SAMPLE_RATE)]
    for d in preds.values():
        anims.append(Animation(_load_pred(d, s.name, len(s.template)), faces, fps))
    path.parent.mkdir(parents=True, exist_ok=True)
    labels = ["ground truth", *preds]
    render_side_by_side(anims, labels, path, size=size, progress=progress)
    if path.stat().st_size > MAX_VIDEO_BYTES:  # docs stay small: trade quality for size
        render_side_by_side(anims, labels, path, size=size, crf=30, progress=progress)
    return path


# ---------------------------------------------------------------------------------------------
# The report


def _num(v: float | None, scale: float = 1.0, digits: int = 3) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v * scale:.{digits}f}"


def _pm(agg: dict[str, Any], scale: float, digits: int = 3) -> str:
    if agg["mean"] is None:
        return "-"
    if agg["std"] is None:
        return _num(agg["mean"], scale, digits)
    return f"{agg['mean'] * scale:.{digits}f} ± {agg['std'] * scale:.{digits}f}"


def _pairs(claim: dict[str, Any]) -> str:
    if claim.get("seed_pairs") is None:
        return "-"
    return f"{claim['seed_pairs_holding']} / {claim['seed_pairs']}"


def _secs(s: float | None) -> str:
    if s is None:
        return "-"
    s = int(round(s))
    return f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s"


def render_markdown(report: dict[str, Any]) -> str:
    """The benchmark's markdown page from its JSON report."""
    cfg, m = report["config"], report["machine"]
    out = [f"# Benchmark: {report['name']}", "", "```", report["command"], "```", ""]
    seeds = ", ".join(map(str, report["seeds"]))
    data = report["data"]
    out += [
        f"Written {report['finished']} by talkmesh {report['talkmesh']}. Methods trained, "
        f"generated and evaluated on the same data: `{data['kind']}` at `{data['root']}`, "
        f"{data['split']} split ({data['sequences']} sequences, {data['frames']} frames at "
        f"{data['motion_fps']:g} fps); seeds {seeds}. Every number below comes from this run; "
        f"raw numbers (per seed) are in [{report['name']}.json]({report['name']}.json), "
        f"checkpoints and predictions in `{cfg['work_dir']}`.",
        "",
        f"Machine: {m['cpu_model']} ({m['usable_cpus']} usable of {m['cpu_count']} CPUs, "
        f"torch {m['torch']} with {m['torch_threads']} threads, Python {m['python']}, "
        f"{m['platform']}; load average {', '.join(f'{x:.1f}' for x in m['load_average'] or [])} "
        "at the start). Other jobs may share it: timings are indicative.",
        "",
        "Mean ± sample standard deviation (ddof=1) over seeds; baselines have no seed. "
        "lip-sync r: Pearson correlation of predicted and true lip opening over time.",
    ]
    methods, baselines = report["methods"], report["baselines"]
    for protocol in ("codetalker", "physical"):
        units = UNITS[protocol]
        title = (
            "anchor protocol (CodeTalker's cal_metric.py, comparable with the papers)"
            if protocol == "codetalker"
            else "physical protocol (Euclidean, mm)"
        )
        out += ["", f"## Scores: {title}", ""]
        head = ["method"] + [f"{LABELS[k]} ({units[k][1]})" for k in METRICS] + ["LVE per seed"]
        out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for name, r in methods.items():
            agg = r["aggregate"][protocol]
            per = ", ".join(
                _num(s["scores"][protocol]["lve"], units["lve"][0]) for s in r["seeds"].values()
            )
            cells = [_pm(agg[k], units[k][0]) for k in METRICS]
            out.append(f"| {name} | " + " | ".join(cells) + f" | {per} |")
        for name, r in baselines.items():
            s = r["scores"][protocol]
            cells = [_num(s[k], units[k][0]) for k in METRICS]
            out.append(f"| {name} (baseline) | " + " | ".join(cells) + " | - |")
    out += ["", "## The paper's ordering claims", ""]
    claims = report["claims"]
    if not claims:
        out.append("No claim applies: the config lacks the pairs of methods they compare.")
    else:
        out += [
            "CodeTalker (Table 1) reports LVE: CodeTalker < FaceFormer < MeshTalk and VOCA, and "
            "CodeTalker best in FDD (compared here by |FDD|). A claim *holds* (or is "
            "*contradicted*) only when the difference of the means exceeds the sum of the two "
            "seed standard deviations; otherwise it is *within seed variance*. *Seed pairs*: of "
            "all pairs (a seed of one method, a seed of the other), how many are ordered as "
            "claimed.",
            "",
            "| claim | protocol | lower (mean ± std) | higher (mean ± std) | difference | "
            "sum of stds | seed pairs | verdict |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for c in claims:
            scale = UNITS[c["protocol"]][c["metric"]][0]
            metric = "\\|FDD\\|" if c["metric"] == "fdd" else LABELS[c["metric"]]
            a = {"mean": c["better_mean"], "std": c["better_std"]}
            b = {"mean": c["worse_mean"], "std": c["worse_std"]}
            out.append(
                f"| {c['better']} < {c['worse']} in {metric} | {c['protocol']} | {_pm(a, scale)} | "
                f"{_pm(b, scale)} | {c['difference'] * scale:+.3f} | {c['std_sum'] * scale:.3f} | "
                f"{_pairs(c)} | **{c['verdict']}** |"
            )
        out += [""]
        pairs: dict[tuple[str, str, str], list[str]] = {}
        for c in claims:
            pairs.setdefault((c["metric"], c["better"], c["worse"]), []).append(
                f"{c['verdict']} ({c['protocol']} protocol)"
            )
        for (metric, better, worse), verdicts in pairs.items():
            name = "|FDD|" if metric == "fdd" else LABELS[metric]
            seeds = len(report["seeds"])
            out.append(f"- {better} < {worse} in {name}: {'; '.join(verdicts)}; {seeds} seeds.")
    if report.get("discussion"):
        out += ["", "Why these orderings come out as they do (written by hand, not by this "
                f"command): [{report['discussion'].split('#')[0]}]({report['discussion']})."]  # fmt: skip
    figs = report["figures"]
    out += ["", "## Figures", ""]
    if figs.get("lip_distance"):
        out += [
            f"Lip distance (upper-lower inner lip) over time on {len(report['samples'])} test "
            "sentences, seed-0 models against the ground truth (paper Figs. 5 and 8):",
            "",
            f"![lip distance]({figs['lip_distance']})",
            "",
        ]
    if figs.get("motion_stats"):
        out += [
            "Per-vertex mean and standard deviation over time of the inter-frame motion "
            "(paper Fig. 4), seed-0 models:",
            "",
            f"![motion statistics]({figs['motion_stats']})",
            "",
        ]
    if figs.get("video"):
        out += [
            f"Side-by-side video of the first sentence ({report['samples'][0]}): "
            f"[{Path(figs['video']).name}]({figs['video']}) ({figs['video_kb']} KB).",
            "",
        ]
    for note in figs.get("notes", []):
        out += [f"- {note}"]
    ab = report.get("ablation")
    if ab:
        out += [
            "",
            f"## Ablation: codebook grid (paper Fig. 7), {ab['method']} stage "
            f"{ab['stage']}, seed {ab['seed']}",
            "",
            "Stage-1 reconstruction of the evaluation split through the VQ-VAE alone (truth "
            "-> codes -> motion) and the codes it uses there.",
            "",
            "| cell | LVE (mm) | LVE (x1e-4, squared) | MVE (mm) | codes used | usage | "
            "perplexity | train time |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for c in ab["cells"]:
            u = c["usage"]
            out.append(
                f"| {c['label']} | {_num(c['physical']['lve'], 1e3)} | "
                f"{_num(c['codetalker']['lve'], 1e4)} | {_num(c['physical']['mve'], 1e3)} | "
                f"{u['codes_used']} / {u['codebook_size']} | {u['usage'] * 100:.0f}% | "
                f"{u['perplexity']:.1f} | {_secs(c['timing'].get('seconds'))} |"
            )
        if ab.get("figure"):
            out += ["", f"![ablation]({ab['figure']})"]
    speed = report.get("speed")
    if speed:
        out += [
            "",
            "## Speed",
            "",
            f"Generation of speech of each length ({speed['audio']}), the minimum of "
            f"{speed['repeats']} runs, {m['torch_threads']} torch threads on the machine above; "
            "real-time factor = generation time / audio length (below 1: faster than real "
            "time).",
            "",
            "| method | audio (s) | frames | generation (s) | real-time factor | frames/s |",
            "|---|---|---|---|---|---|",
        ]
        for name, rows in speed["methods"].items():
            for r in rows:
                out.append(
                    f"| {name} | {r['audio_seconds']:g} | {r['frames']} | "
                    f"{r['seconds']:.2f} | {r['real_time_factor']:.3f} | "
                    f"{r['frames_per_second']:.0f} |"
                )
    out += [
        "",
        "## Training",
        "",
        "Wall time of the training alone (a skipped stage costs nothing; a resumed one counts "
        "only its remaining epochs) and throughput = motion frames seen / wall time, frames "
        "counted in the random crops (data.max_seconds) at the batch size shown.",
        "",
        "| method | stage | task | epochs | batch | crop (s) | wall time per seed | "
        "frames/s | predict time per seed |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in methods.items():
        stages = next(iter(r["seeds"].values()))["training"]
        for k, stage in enumerate(stages):
            per = [s["training"][k] for s in r["seeds"].values()]
            walls = ", ".join(
                _secs(t.get("seconds")) + (" (resumed)" if t.get("resumed") else "") for t in per
            )
            fps = mean_std([t.get("frames_per_second") for t in per])
            pred = ", ".join(_secs(s["predict"].get("seconds")) for s in r["seeds"].values())
            out.append(
                f"| {name} | {stage['stage']} | {stage.get('task', '-')} | "
                f"{stage.get('epochs', '-')} | {stage.get('batch_size', '-')} | "
                f"{stage.get('max_seconds', '-')} | {walls} | {_pm(fps, 1.0, 0)} | "
                f"{pred if k == len(stages) - 1 else ''} |"
            )
    return "\n".join(out) + "\n"


# ---------------------------------------------------------------------------------------------
# The whole run


def _selected(cfg: BenchmarkConfig, only: list[str] | None) -> list[str]:
    if not only:
        return list(cfg.methods)
    unknown = [m for m in only if m not in cfg.methods]
    if unknown:
        raise TalkmeshError(
            f"--only {unknown[0]}: not a method of this benchmark ({', '.join(cfg.methods)})"
        )
    return [m for m in cfg.methods if m in only]


def plan_lines(
    cfg: BenchmarkConfig,
    *,
    only: list[str] | None = None,
    skip_video: bool = False,
    skip_ablation: bool = False,
) -> Iterator[str]:
    """The steps a run would take, one line each, with their out dirs and what is done."""
    work, docs = Path(cfg.work_dir), Path(cfg.docs_dir)
    ds = _open(cfg)
    yield (
        f"benchmark {cfg.name}: {len(_selected(cfg, only))} methods x {len(cfg.seeds)} seeds "
        f"on {cfg.data.kind} {cfg.data.root} ({cfg.data.split}: {len(ds)} sequences)"
    )
    for name in cfg.baselines:
        d = work / "baselines" / name / "pred"
        yield f"baseline {name:<28} -> {d}  [{'done' if predictions_done(d, None) else 'run'}]"
    for method in _selected(cfg, only):
        for seed in cfg.seeds:
            plans = method_stages(cfg, method, seed)
            for p in plans:
                init = f" init {p.recipe.init}" if p.recipe.init else ""
                state = stage_state(p)
                if state == "waiting":
                    state = f"train after {p.init_stage}"
                yield (
                    f"train    {method} seed {seed} {p.stage:<12} {p.recipe.task}{init} "
                    f"-> {p.out_dir}  [{state}]"
                )
            pred = work / method / f"seed{seed}" / "pred"
            state = "done" if predictions_done(pred, plans[-1].release) else "run"
            yield f"predict  {method} seed {seed} {plans[-1].release} -> {pred}  [{state}]"
            yield f"evaluate {method} seed {seed} {pred} (codetalker, physical)"
    if (
        cfg.ablation is not None
        and not skip_ablation
        and cfg.ablation.method in _selected(cfg, only)
    ):
        for c in ablation_cells(cfg):
            yield (
                f"ablation {cfg.ablation.method} {cfg.ablation.stage} {c.label} "
                f"-> {c.plan.out_dir}  [{stage_state(c.plan)}]"
            )
    secs = ", ".join(f"{s:g} s" for s in cfg.speed.seconds)
    yield f"speed    {', '.join(_selected(cfg, only))} (seed {cfg.seeds[0]}) at {secs}"
    fig_dir = docs / cfg.name
    yield f"figures  {fig_dir}/lip_distance.png, motion_stats.png" + (
        ", ablation.png" if cfg.ablation and not skip_ablation else ""
    )
    if cfg.video and not skip_video:
        yield f"video    {fig_dir}/{cfg.name}_side_by_side.mp4"
    yield f"report   {docs / (cfg.name + '.md')}, {docs / (cfg.name + '.json')}"


def run_benchmark(
    config: str | Path,
    *,
    only: list[str] | None = None,
    skip_video: bool = False,
    skip_ablation: bool = False,
    progress: bool = True,
    quiet: bool = False,
    log: Callable[[str], None] | None = None,
) -> BenchmarkResult:
    """Run (or resume) the benchmark of ``config`` and write its markdown, JSON and figures."""
    from talkmesh import __version__

    cfg = load_benchmark(config)
    methods = _selected(cfg, only)
    log = log or Log(quiet)
    progress = progress and not quiet
    machine = machine_info()
    work, docs = Path(cfg.work_dir), Path(cfg.docs_dir)
    dataset = _open(cfg)
    trained: list[Path] = []
    predicted: list[Path] = []

    def ensure_stage(plan: StagePlan, what: str) -> dict[str, Any]:
        state = stage_state(plan)
        if state == "done":
            log(f"{what}: done, skipped ({plan.out_dir})")
            return _read_json(plan.out_dir / TIMING_FILE) or {"stage": plan.stage}
        verb = {"resume": "resuming", "stale": "retraining (its recipe or init changed)"}.get(
            state, "training"
        )
        log(f"{what}: {verb} {plan.recipe.task} -> {plan.out_dir}")
        record = train_stage(plan, keep_checkpoints=cfg.keep_checkpoints, progress=progress)
        trained.append(plan.out_dir)
        fps = record["frames_per_second"]
        log(
            f"{what}: trained in {_secs(record['seconds'])}"
            + (f" ({fps:.0f} frames/s, batch {record['batch_size']})" if fps else "")
        )
        return record

    # baselines: seed-free, once
    baselines: dict[str, Any] = {}
    for name in cfg.baselines:
        d = work / "baselines" / name / "pred"
        if predictions_done(d, None):
            log(f"baseline {name}: predictions done, skipped ({d})")
        else:
            log(f"baseline {name}: predicting -> {d}")
            baseline(cfg, name, d, progress=progress)
            predicted.append(d)
        log(f"baseline {name}: evaluating")
        scores = score(dataset, d)
        _write_json(d.parent / SCORES_FILE, scores)
        baselines[name] = {
            "pred": str(d),
            "scores": _summary(scores),
            "predict": _read_json(d / DONE_FILE),
        }

    # train and predict seed-major (seed 0 of every method first), so that a run stopped part of
    # the way already compares every method; the pass below then only reads and scores
    for seed in cfg.seeds:
        for method in methods:
            plans = method_stages(cfg, method, seed)
            for p in plans:
                ensure_stage(p, f"{method} seed {seed} {p.stage}")
            pred = work / method / f"seed{seed}" / "pred"
            if not predictions_done(pred, plans[-1].release):
                log(f"{method} seed {seed}: predicting {cfg.data.split} -> {pred}")
                predict(cfg, plans[-1].release, pred, progress=progress)
                predicted.append(pred)

    # methods x seeds
    results: dict[str, Any] = {}
    for method in methods:
        per_seed: dict[int, Any] = {}
        for seed in cfg.seeds:
            plans = method_stages(cfg, method, seed)
            training = [ensure_stage(p, f"{method} seed {seed} {p.stage}") for p in plans]
            seed_dir = work / method / f"seed{seed}"
            pred = seed_dir / "pred"
            release = plans[-1].release
            if predictions_done(pred, release):
                log(f"{method} seed {seed}: predictions done, skipped ({pred})")
            else:
                log(f"{method} seed {seed}: predicting {cfg.data.split} -> {pred}")
                predict(cfg, release, pred, progress=progress)
                predicted.append(pred)
            log(f"{method} seed {seed}: evaluating")
            scores = score(dataset, pred)
            _write_json(seed_dir / SCORES_FILE, scores)
            per_seed[seed] = {
                "release": str(release),
                "pred": str(pred),
                "scores": _summary(scores),
                "training": training,
                "predict": _read_json(pred / DONE_FILE),
            }
        agg = aggregate({s: r["scores"] for s, r in per_seed.items()})
        results[method] = {
            "recipe": cfg.methods[method].recipe,
            "seeds": {str(s): r for s, r in per_seed.items()},
            "aggregate": agg,
        }
    claims = check_claims(
        {m: r["aggregate"] for m, r in results.items()},
        {m: [x["scores"] for x in r["seeds"].values()] for m, r in results.items()},
    )

    # ablation
    fig_dir = docs / cfg.name
    ablation = None
    if cfg.ablation is not None and not skip_ablation and cfg.ablation.method in methods:
        ab = cfg.ablation
        cells = []
        for c in ablation_cells(cfg):
            what = f"ablation {c.label}"
            timing = ensure_stage(c.plan, what)
            pred = c.plan.out_dir.parent / "recon"
            if not predictions_done(pred, c.plan.release):
                log(f"{what}: reconstructing {cfg.data.split} -> {pred}")
                predict(cfg, c.plan.release, pred, progress=progress, mode="reconstruct")
            scores = _summary(score(dataset, pred))
            usage = codebook_usage(c.plan.release, dataset)
            cells.append(
                {
                    "values": c.values,
                    "label": c.label,
                    "dir": str(c.plan.out_dir),
                    "codetalker": scores["codetalker"],
                    "physical": scores["physical"],
                    "usage": usage,
                    "timing": timing,
                }
            )
        figure = ablation_figure(ab, cells, fig_dir / "ablation.png")
        ablation = {
            "method": ab.method,
            "stage": ab.stage,
            "seed": ab.seed,
            "grid": {k: list(v) for k, v in ab.grid.items()},
            "cells": cells,
            "figure": f"{cfg.name}/{figure.name}",
        }

    # speed, with the first seed's release of each method
    speed = {
        "audio": f"{cfg.data.split}-split speech of {cfg.data.root}, sequences joined",
        "repeats": cfg.speed.repeats,
        "methods": {},
    }
    for method in methods:
        release = Path(results[method]["seeds"][str(cfg.seeds[0])]["release"])
        log(f"{method}: timing generation at {', '.join(f'{s:g}' for s in cfg.speed.seconds)} s")
        speed["methods"][method] = measure_speed(release, dataset, cfg.speed)

    # figures
    first = str(cfg.seeds[0])
    preds = {m: Path(results[m]["seeds"][first]["pred"]) for m in methods}
    lip_preds = {**preds, **{b: Path(baselines[b]["pred"]) for b in cfg.baselines}}
    indices = sample_indices(len(dataset), cfg.samples)
    figures: dict[str, Any] = {"notes": []}
    written: list[Path] = []
    if indices:
        log("figures: lip distance")
        p = lip_figure(dataset, indices, lip_preds, fig_dir / "lip_distance.png")
        if p is None:
            figures["notes"].append(
                "no lip-distance figure: the mesh is not the bundled head's "
                "topology (its lip pairs are unknown)"
            )
        else:
            figures["lip_distance"] = f"{cfg.name}/{p.name}"
            written.append(p)
    log("figures: motion statistics")
    p = motion_figure(dataset, preds, fig_dir / "motion_stats.png")
    figures["motion_stats"] = f"{cfg.name}/{p.name}"
    written.append(p)
    if ablation:
        written.append(fig_dir / "ablation.png")
    if cfg.video and not skip_video and indices:
        log("video: side by side")
        video = side_by_side_video(
            dataset,
            indices[0],
            lip_preds,
            fig_dir / f"{cfg.name}_side_by_side.mp4",
            cfg.video_size,
            progress,
        )
        if video is None:
            figures["notes"].append("no video: the dataset has no faces (.ply) to render")
        else:
            figures["video"] = f"{cfg.name}/{video.name}"
            figures["video_kb"] = video.stat().st_size // 1024
            written.append(video)
    for p in written:
        if p.stat().st_size > (MAX_PNG_BYTES if p.suffix == ".png" else MAX_VIDEO_BYTES):
            figures["notes"].append(f"{p.name} is {p.stat().st_size // 1024} KB")

    command = " ".join(
        ["talkmesh", "benchmark", str(config)]
        + ([f"--only {','.join(methods)}"] if only else [])
        + (["--skip-video"] if skip_video else [])
        + (["--skip-ablation"] if skip_ablation else [])
    )
    frames = 0
    for i in range(len(dataset)):
        frames += len(dataset[i].vertices)
    report = {
        "name": cfg.name,
        "command": command,
        "finished": _now(),
        "talkmesh": __version__,
        "config": to_dict(cfg),
        "machine": machine,
        "data": {
            "kind": cfg.data.kind,
            "root": cfg.data.root,
            "split": cfg.data.split,
            "sequences": len(dataset),
            "frames": frames,
            "motion_fps": dataset.spec.motion_fps,
        },
        "seeds": list(cfg.seeds),
        "samples": [dataset.names[i] for i in indices],
        "methods": results,
        "baselines": baselines,
        "claims": claims,
        "discussion": cfg.discussion,
        "ablation": ablation,
        "speed": speed,
        "figures": figures,
    }
    docs.mkdir(parents=True, exist_ok=True)
    json_path = docs / f"{cfg.name}.json"
    md_path = docs / f"{cfg.name}.md"
    _write_json(json_path, report)
    md_path.write_text(render_markdown(report))
    log(f"wrote {md_path} and {json_path}")
    return BenchmarkResult(md_path, json_path, written, trained, predicted)


__all__ = [
    "AblationSpec",
    "BenchmarkConfig",
    "BenchmarkResult",
    "DataSpec",
    "MethodSpec",
    "SpeedSpec",
    "StagePlan",
    "aggregate",
    "check_claims",
    "load_benchmark",
    "method_stages",
    "plan_lines",
    "run_benchmark",
]
