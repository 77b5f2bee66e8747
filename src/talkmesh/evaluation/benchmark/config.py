"""A benchmark's configuration: the YAML's dataclasses, its validation, and the plan of every
training stage (each method's recipe re-pointed per seed onto the benchmark's data and work dir)."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field, replace
from itertools import product
from pathlib import Path
from typing import Any, NamedTuple

from talkmesh.config import from_dict, read_yaml
from talkmesh.errors import TalkmeshError

BASELINES = ("static", "procedural")
RESERVED = ("baselines", "ablation")  # directories of WORK that are not methods
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
TIMING_FILE = "timing.json"
DONE_FILE = "done.json"
SCORES_FILE = "scores.json"
METRICS = ("lve", "fdd", "mve", "lip_sync")
# the paper's symbols for the VQ keys of the ablation grid (Fig. 7: P, H; Table 4: C, N)
SYMBOLS = {"temporal_unit": "P", "components": "H", "code_dim": "C", "codebook_size": "N"}


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
    docs_dir: str = "docs/results/benchmarks"
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
            open_split(cfg)  # a missing corpus fails now, not after hours of training
        except TalkmeshError as e:
            raise TalkmeshError(f"{path}: data: {e}") from None
    return cfg


def open_split(cfg: BenchmarkConfig, split: str | None = None):
    """The benchmark's dataset at ``split`` (default: its evaluation split); an empty split is an
    error."""
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


def fmt_value(v: Any) -> str:
    """A grid value as written in a cell's label and directory name (strings unquoted)."""
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
        slug = "-".join(f"{k}{fmt_value(v)}" for k, v in short)
        label = ", ".join(f"{SYMBOLS.get(k, k)}={fmt_value(v)}" for k, v in short)
        extra = (*ab.overrides, *(f"{k}={json.dumps(v)}" for k, v in cell.items()))
        root = Path(cfg.work_dir) / "ablation" / slug
        (plan,) = method_stages(
            cfg, ab.method, ab.seed, root=root, extra=extra, only_stage=ab.stage
        )
        cells.append(Cell(cell, slug, label, plan))
    return cells
