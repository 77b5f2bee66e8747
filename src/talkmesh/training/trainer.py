"""Training: ``talkmesh train RECIPE.yaml [key=value ...]`` for every model and stage.

Models are plain ``nn.Module``s; this module wraps them in one Lightning system. A recipe is a YAML
file that maps 1:1 onto :class:`Recipe`::

    task: codetalker-stage1          # which model/stage (see TASKS)
    model: {...}                     # the task's model config (validated by the task)
    data: {kind: synth, root: corpus/synth, batch_size: 4, max_seconds: 4.0}
    train: {lr: 1.0e-4, epochs: 20, seed: 0, out_dir: runs/ct1}
    init: runs/ct1/model.safetensors # optional: a released earlier stage (e.g. stage 1 for stage 2)

Exact resume: checkpoints are written at the end of every epoch (``last.ckpt``) with the optimiser,
the epoch and the RNG states; crops and shuffling depend only on (seed, epoch, index), so a run that
is killed and resumed with ``--resume`` continues the same loss curve. DDP: ``--devices N``
(processes on this machine, gloo on CPU) and ``--num-nodes``; each process sees its own shard.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import random
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np

from talkmesh.config import apply_overrides, from_dict, load_config, merge, read_yaml, to_dict
from talkmesh.errors import MissingDependencyError, TalkmeshError
from talkmesh.training import checkpoints
from talkmesh.training.augment import AugmentConfig
from talkmesh.training.augment import augment as augment_crop
from talkmesh.training.params import decay_groups, trainable

try:
    import torch
    from torch import nn
except ImportError:  # pragma: no cover - torch is a hard requirement of training only
    torch = None
    nn = None


# -- Recipe ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DataConfig:
    """Which dataset to train on and how to cut it into batches."""

    kind: str = "synth"  # a talkmesh.datasets.reader reader: vocaset, biwi, synth, folder
    root: str = "corpus/synth"
    train_split: str = "train"
    val_split: str = "val"
    batch_size: int = 4
    max_seconds: float = 4.0  # random crops of at most this long (0: whole sequences)
    num_workers: int = 0
    regions: str | None = None  # region files directory, if not in the dataset
    augment: AugmentConfig = AugmentConfig()  # training crops only (talkmesh.training.augment)

    def __post_init__(self) -> None:
        if self.batch_size < 1:
            raise ValueError("data.batch_size must be at least 1")
        if self.max_seconds < 0:
            raise ValueError("data.max_seconds must be >= 0")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation and run settings (paper values in the recipes, not here)."""

    lr: float = 1e-4
    weight_decay: float = 0.0
    # the sub-modules weight decay applies to, dotted names in the trained network (MeshTalk's
    # official step 1 decays its decoder only: ``[model.decoder]``); empty: every parameter
    weight_decay_modules: tuple[str, ...] = ()
    optimizer: Literal["adam", "adamw"] = "adamw"
    lr_step_size: int = 0  # multiply the lr by lr_gamma every this many lr_step_unit (0: constant)
    lr_step_unit: Literal["epoch", "step"] = "epoch"
    lr_gamma: float = 0.5
    epochs: int = 10
    max_steps: int = -1  # stop after this many optimiser steps (-1: no limit)
    seed: int = 0
    precision: str = "32-true"  # Lightning precision: "32-true", "bf16-mixed", "16-mixed"
    accelerator: str = "auto"
    devices: int = 1
    num_nodes: int = 1
    grad_clip: float = 0.0
    lip_gap_weight: float = 0.0  # the lip-gap loss (talkmesh.training.lip_gap); 0: the paper's
    lip_close_weight: float = 0.0  # the lip-gap loss counts the truth's closed frames 1 + this
    lip_rest_weight: float = 0.0  # ... and the frames where its mouth is at rest 1 + this
    code_ce_weight: float = 0.0  # cross-entropy on the codes (training.lip_gap.CodeChoice); 0: off
    # names (or name prefixes) of the parameters that learn, among those the task trains (e.g.
    # [head_map.weight]: the style's head term alone); empty: all of them
    trainable: tuple[str, ...] = ()
    log_every: int = 10  # steps between log rows
    val_every: int = 1  # epochs between validation runs
    out_dir: str = "runs/train"
    record_batches: bool = False  # write the sample names each process trained on (DDP checks)

    def __post_init__(self) -> None:
        if self.lr <= 0:
            raise ValueError("train.lr must be positive")
        if self.epochs < 1:
            raise ValueError("train.epochs must be at least 1")
        if self.devices < 1 or self.num_nodes < 1:
            raise ValueError("train.devices and train.num_nodes must be at least 1")
        terms = ("lip_gap_weight", "lip_close_weight", "lip_rest_weight", "code_ce_weight")
        if min(getattr(self, t) for t in terms) < 0:
            raise ValueError(f"train.{', '.join(terms)} must be >= 0")
        if self.lr_step_size < 0 or not 0 < self.lr_gamma <= 1:
            raise ValueError("train.lr_step_size must be >= 0 and train.lr_gamma in (0, 1]")


@dataclass(frozen=True)
class Recipe:
    task: str
    model: dict[str, Any] = field(default_factory=dict)
    data: DataConfig = DataConfig()
    train: TrainConfig = TrainConfig()
    init: str | None = None
    # a release whose weights start this stage where their shapes match (a model trained on
    # other speakers: everything but the style table); the rest keeps its initialisation
    warm_start: str | None = None


def warm_start(model, release: Path) -> tuple[int, list[str]]:
    """Copies every tensor of the release at ``release`` whose name and shape match into
    ``model``, except in frozen parts (a stage's ``init``: stage 2's VQ-VAE); returns (tensors
    copied, names left as they were)."""
    from talkmesh.models.release import load_model

    source = load_model(release).state_dict()
    own = model.state_dict()
    frozen = tuple(
        f"{name}."
        for name, child in model.named_children()
        if any(True for _ in child.parameters())
        and not any(p.requires_grad for p in child.parameters())
    )
    copied, skipped = {}, []
    for name, tensor in own.items():
        if name.startswith(frozen):
            continue
        if name in source and source[name].shape == tensor.shape:
            copied[name] = source[name]
        else:
            skipped.append(name)
    model.load_state_dict(copied, strict=False)
    return len(copied), skipped


def load_recipe(path: str | Path | None, overrides: list[str] = ()) -> Recipe:
    """A YAML recipe plus dotted overrides (``train.lr=3e-4``) -> :class:`Recipe`."""
    recipe = load_config(Recipe, path, overrides)
    task_spec(recipe.task)  # fail early on an unknown task
    return recipe


def load_recipes(path: str | Path, overrides: list[str] = ()) -> list[tuple[str, Recipe]]:
    """A recipe file -> its stages as ``(name, Recipe)``, in training order.

    A plain recipe is one stage named after its task. A file with ``stages:`` (a mapping of stage
    name -> recipe sections) holds several, e.g. CodeTalker's VQ-VAE then its speech stage; the
    other top-level sections are shared defaults under each stage, and the overrides apply to
    every stage (``stages.NAME.train.lr=...`` reaches one).
    """
    data = read_yaml(path)
    if "stages" not in data:
        recipe = load_recipe(path, overrides)
        return [(recipe.task, recipe)]
    data = apply_overrides(data, [o for o in overrides if o.startswith("stages.")])
    common = [o for o in overrides if not o.startswith("stages.")]
    stages = data.pop("stages")
    if not isinstance(stages, dict) or not stages:
        raise TalkmeshError(f"{path}: 'stages' must map stage names to recipe sections")
    out = []
    for name, stage in stages.items():
        if not isinstance(stage, dict):
            raise TalkmeshError(f"{path}: stage {name!r} must be a mapping of recipe sections")
        try:
            recipe = from_dict(Recipe, apply_overrides(merge(data, stage), common))
        except TalkmeshError as e:
            raise TalkmeshError(f"{path}: stage {name}: {e}") from None
        task_spec(recipe.task)
        out.append((str(name), recipe))
    return out


# -- Tasks: how each model/stage is built, stepped and released --------------------------------


class StepOutput(NamedTuple):
    """A task step's loss to minimise and scalars to log; for training.lip_gap's terms, predicted
    offsets (B, T, V*3) and (features (B, T, H, C), true codes (B, T, H), codebook (K, C))."""

    loss: Any  # () tensor
    logs: dict[str, float]
    motion: Any = None
    codes: Any = None


class TorchBatch(NamedTuple):
    """A padded batch on the model's device.

    names: B sample names; audio (B, S) float32 at 16 kHz; audio_lengths (B,) int64;
    vertices (B, T, V, 3) float32; templates (B, V, 3); motion_mask (B, T) bool; styles (B,) int64
    (-1 for speakers outside the training set).
    """

    names: list[str]
    audio: Any
    audio_lengths: Any
    vertices: Any
    templates: Any
    motion_mask: Any
    styles: Any

    def to(self, device) -> TorchBatch:
        return TorchBatch(self.names, *(t.to(device) for t in self[1:]))


@dataclass(frozen=True)
class DatasetInfo:
    """Facts a task needs to size its model, taken from the training data."""

    num_vertices: int
    motion_fps: float
    train_subjects: tuple[str, ...]
    faces: np.ndarray | None = None
    regions: Any = None  # talkmesh.datasets.reader.DatasetRegions of the training data
    dataset: Any = None  # the training split itself, for a task that measures its motion


@dataclass(frozen=True)
class Task:
    """A trainable model/stage.

    build(model_config: dict, info, init: Path | None) -> nn.Module
    step(model, batch: TorchBatch) -> StepOutput
    parameters(model) -> the parameters to optimise (frozen parts excluded)
    save(model, path) -> writes the release file
    prepare(model, dataset) -> optional: fit normalisation statistics on the training data
    """

    name: str
    build: Callable[..., Any]
    step: Callable[..., StepOutput]
    parameters: Callable[..., Any]
    save: Callable[..., None]
    prepare: Callable[..., None] | None = None


# Task name -> "module:attribute" of a Task, imported on first use (the CLI imports no model).
TASKS: dict[str, str] = {
    "codetalker-stage1": "talkmesh.training.codetalker:STAGE1",
    "codetalker-stage2": "talkmesh.training.codetalker:STAGE2",
    "codetalker-finetune": "talkmesh.training.codetalker:FINETUNE",
    "codetalker-decoder": "talkmesh.training.codetalker:DECODER",
    "codetalker-decoder-speech": "talkmesh.training.codetalker:DECODER_SPEECH",
    "meshtalk": "talkmesh.training.meshtalk:EXPRESSION",
    "meshtalk-prior": "talkmesh.training.meshtalk:PRIOR",
    "faceformer": "talkmesh.training.faceformer:FACEFORMER",
    "voca": "talkmesh.training.voca:VOCA",
}


def task_spec(name: str) -> Task:
    if name not in TASKS:
        raise TalkmeshError(
            f"unknown task '{name}': available tasks are {', '.join(sorted(TASKS))}"
        )
    module, attr = TASKS[name].split(":")
    return getattr(importlib.import_module(module), attr)


# -- Data --------------------------------------------------------------------------------------


def _require_torch() -> None:
    if torch is None:
        raise MissingDependencyError("torch", "train", "training")


def crop_window(
    num_frames: int, max_frames: int, seed: int, epoch: int, index: int
) -> tuple[int, int]:
    """The [start, stop) frames of a sample's crop; depends only on (seed, epoch, index)."""
    if max_frames <= 0 or num_frames <= max_frames:
        return 0, num_frames
    digest = hashlib.blake2b(f"{seed}:{epoch}:{index}".encode(), digest_size=8).digest()
    start = int.from_bytes(digest, "little") % (num_frames - max_frames + 1)
    return start, start + max_frames


class CroppedMotion:
    """A ``MotionDataset`` as a torch dataset of random, reproducible crops.

    The audio is cut to the same time window as the motion (16 kHz samples per frame), then
    augmented (``augment``: recording conditions, speed and silence with the motion re-timed),
    drawn from (seed, epoch, index) like the crop.
    """

    def __init__(
        self, dataset, max_seconds: float, seed: int, augment: AugmentConfig | None = None
    ) -> None:
        self.dataset = dataset
        self.max_frames = int(round(max_seconds * dataset.spec.motion_fps)) if max_seconds else 0
        self.seed = seed
        self.epoch = 0
        self.augment = augment or AugmentConfig()

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int):
        from talkmesh.audio.loading import SAMPLE_RATE

        sample = self.dataset.sample_or_next(index)  # a file that fails to load is skipped
        start, stop = crop_window(
            len(sample.vertices), self.max_frames, self.seed, self.epoch, index
        )
        per_frame = SAMPLE_RATE / self.dataset.spec.motion_fps
        a0, a1 = int(round(start * per_frame)), int(round(stop * per_frame))
        sample = sample._replace(vertices=sample.vertices[start:stop], audio=sample.audio[a0:a1])
        if not self.augment.enabled:
            return sample
        rng = np.random.default_rng([self.seed, self.epoch, index, 0xA06])
        return augment_crop(sample, self.augment, rng, self.dataset.spec.motion_fps, self.seed)


class EpochShuffle:
    """A shuffling sampler whose order depends only on (seed, epoch): exact after a resume.

    Lightning calls ``set_epoch`` before each epoch (and shards it across DDP processes).
    """

    def __init__(self, num_samples: int, seed: int) -> None:
        self.num_samples = num_samples
        self.seed = seed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return self.num_samples

    def __iter__(self):
        rng = np.random.default_rng([self.seed, self.epoch])
        return iter(rng.permutation(self.num_samples).tolist())


def collate_torch(samples) -> TorchBatch:
    """Samples -> a padded :class:`TorchBatch` (see ``talkmesh.datasets.reader.collate``)."""
    from talkmesh.datasets.reader import collate

    b = collate(samples)
    return TorchBatch(
        names=list(b.names),
        audio=torch.from_numpy(b.audio),
        audio_lengths=torch.from_numpy(b.audio_lengths),
        vertices=torch.from_numpy(b.vertices),
        templates=torch.from_numpy(b.templates),
        motion_mask=torch.from_numpy(b.motion_mask),
        styles=torch.from_numpy(b.styles),
    )


def dataset_info(dataset) -> DatasetInfo:
    first = dataset.sample_or_next(0)
    return DatasetInfo(
        num_vertices=int(first.template.shape[0]),
        motion_fps=float(dataset.spec.motion_fps),
        train_subjects=tuple(dataset.spec.train_subjects),
        faces=getattr(dataset, "faces", None),
        regions=getattr(dataset, "regions", None),
        dataset=dataset,
    )


# -- The Lightning system ----------------------------------------------------------------------


def _lightning():
    try:
        import lightning as L
    except ImportError:
        raise MissingDependencyError("lightning", "train", "training") from None
    return L


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def build_system(recipe: Recipe, info: DatasetInfo, init: Path | None):
    """The LightningModule that trains ``recipe.task`` (a plain nn.Module inside)."""
    L = _lightning()
    task = task_spec(recipe.task)

    class MotionSystem(L.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            self.model = task.build(recipe.model, info, init)
            self.recorded: list[str] = []
            self.terms: list = []  # the optional terms of training.lip_gap

        def _loss(self, batch: TorchBatch) -> tuple[Any, dict[str, float]]:
            out = task.step(self.model, batch)
            loss, logs = out.loss, out.logs
            for term in self.terms:
                loss, logs = term.add(loss, logs, out, batch, recipe.task)
            return loss, logs

        def training_step(self, batch: TorchBatch, batch_idx: int):
            loss, logs = self._loss(batch)
            bs = len(batch.names)
            self.log("train/loss", loss.detach(), prog_bar=True, batch_size=bs, sync_dist=False)
            for key, value in logs.items():
                self.log(f"train/{key}", value, batch_size=bs)
            if recipe.train.record_batches:
                self.recorded.extend(batch.names)
            return loss

        def validation_step(self, batch: TorchBatch, batch_idx: int) -> None:
            loss, _ = self._loss(batch)
            self.log("val/loss", loss, prog_bar=True, batch_size=len(batch.names), sync_dist=True)

        def configure_optimizers(self):
            params = trainable(self.model, task.parameters(self.model), recipe.train.trainable)
            t = recipe.train
            opt = torch.optim.AdamW if t.optimizer == "adamw" else torch.optim.Adam
            groups = decay_groups(self.model, params, t.weight_decay, t.weight_decay_modules)
            optimizer = opt(groups, lr=t.lr, weight_decay=t.weight_decay)
            if not t.lr_step_size:
                return optimizer
            # CodeTalker's StepLR (per epoch), MeshTalk's x0.1 at an iteration (per step)
            decay = torch.optim.lr_scheduler.StepLR(optimizer, t.lr_step_size, t.lr_gamma)
            return {
                "optimizer": optimizer,
                "lr_scheduler": {"scheduler": decay, "interval": t.lr_step_unit},
            }

        def on_train_epoch_start(self) -> None:
            loader = self.trainer.train_dataloader
            dataset = getattr(loader, "dataset", None)
            if isinstance(dataset, CroppedMotion):
                dataset.epoch = self.current_epoch

        def on_save_checkpoint(self, checkpoint: dict) -> None:
            checkpoint["talkmesh_recipe"] = to_dict(recipe)
            checkpoint["talkmesh_rng"] = _rng_state()

        def on_load_checkpoint(self, checkpoint: dict) -> None:
            rng = checkpoint.get("talkmesh_rng")
            if rng:
                torch.set_rng_state(rng["torch"])
                name, keys, pos, has_gauss, cached = rng["numpy"]
                np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
                random.setstate(rng["python"])
            for state in checkpoint.get("optimizer_states", []):  # changed settings apply
                for i, group in enumerate(state.get("param_groups", [])):
                    group["lr"] = recipe.train.lr
                    # decay_groups: the decayed parameters first, then the others (no decay)
                    group["weight_decay"] = recipe.train.weight_decay if i == 0 else 0.0

    return MotionSystem()


def _rng_state() -> dict:
    """The random generators' states in plain types and tensors only: the checkpoint loads with
    torch.load(weights_only=True)."""
    name, keys, pos, has_gauss, cached = np.random.get_state()
    return {
        "torch": torch.get_rng_state(),
        "numpy": [
            name,
            torch.from_numpy(keys.astype(np.int64)),
            int(pos),
            int(has_gauss),
            float(cached),
        ],
        "python": random.getstate(),
    }


def _loaders(recipe: Recipe, train_set):
    """The training loader (crops, epoch shuffle) and the validation loader (None without one)."""
    from talkmesh.datasets.reader import open_dataset

    loader_args = dict(
        batch_size=recipe.data.batch_size,
        num_workers=recipe.data.num_workers,
        collate_fn=collate_torch,
    )
    train_loader = torch.utils.data.DataLoader(
        CroppedMotion(train_set, recipe.data.max_seconds, recipe.train.seed, recipe.data.augment),
        sampler=EpochShuffle(len(train_set), recipe.train.seed),
        **loader_args,
    )
    val_loader = None
    if recipe.data.val_split:
        val_set = open_dataset(
            recipe.data.kind,
            recipe.data.root,
            recipe.data.val_split,
            regions=recipe.data.regions,
            allow_empty=True,
        )
        if len(val_set):
            val_loader = torch.utils.data.DataLoader(
                CroppedMotion(val_set, recipe.data.max_seconds, recipe.train.seed),
                shuffle=False,
                **loader_args,
            )

    return train_loader, val_loader


def _lightning_trainer(L, recipe: Recipe, out: Path, progress: bool):
    """A Lightning Trainer: CSV (and TensorBoard) logs and a checkpoint per epoch in ``out``."""
    from lightning.pytorch.callbacks import ModelCheckpoint
    from lightning.pytorch.loggers import CSVLogger

    loggers = [CSVLogger(out, name="logs", version="")]
    try:
        import tensorboard  # noqa: F401
        from lightning.pytorch.loggers import TensorBoardLogger

        loggers.append(TensorBoardLogger(out, name="logs", version="tb"))
    except ImportError:
        pass
    trainer = L.Trainer(
        default_root_dir=out,
        max_epochs=recipe.train.epochs,
        max_steps=recipe.train.max_steps,
        accelerator=recipe.train.accelerator,
        devices=recipe.train.devices,
        num_nodes=recipe.train.num_nodes,
        strategy="ddp" if recipe.train.devices * recipe.train.num_nodes > 1 else "auto",
        precision=recipe.train.precision,
        gradient_clip_val=recipe.train.grad_clip or None,
        log_every_n_steps=recipe.train.log_every,
        # the deprecation chatter of Lightning's internals is not the user's business
        check_val_every_n_epoch=recipe.train.val_every,
        callbacks=[
            ModelCheckpoint(
                dirpath=out,
                filename="epoch{epoch:03d}",
                auto_insert_metric_name=False,
                save_last=True,
                every_n_epochs=1,
            )
        ],
        logger=loggers,
        enable_progress_bar=progress,
        enable_model_summary=progress,
        num_sanity_val_steps=0,
        deterministic=False,
    )
    return trainer


def _record_run(out: Path, rank: int, system) -> None:
    """The batches this rank saw and a digest of its weights (for determinism checks)."""
    (out / f"batches_rank{rank}.txt").write_text("\n".join(system.recorded) + "\n")
    digest = hashlib.sha256()
    for p in system.model.state_dict().values():
        digest.update(p.detach().cpu().numpy().tobytes())
    (out / f"weights_rank{rank}.sha256").write_text(digest.hexdigest() + "\n")


def _init_path(init: str | None) -> Path | None:
    """A recipe's ``init``: a release file, or the name of a bundled model."""
    if not init:
        return None
    if Path(init).is_file():
        return Path(init)
    from talkmesh.models.release import MODELS_DIR

    bundled = MODELS_DIR / f"{init}.safetensors"
    if "/" not in init and bundled.is_file():
        return bundled
    raise TalkmeshError(f"init checkpoint not found: {init} (train the earlier stage first)")


def train(recipe: Recipe, *, resume: bool = False, progress: bool = True) -> Path:
    """Train ``recipe`` and write ``<out_dir>/model.safetensors``; returns that path.

    ``resume=True`` continues from the newest loadable checkpoint in ``out_dir`` (the same loss
    curve as an uninterrupted run); a recipe whose model differs from it is refused before anything
    is written, changed settings are warned about and apply from there on. Logs go to ``<out_dir>/logs`` as CSV (and TensorBoard if installed).
    """
    _require_torch()
    L = _lightning()
    import warnings

    warnings.filterwarnings("ignore", module=r"lightning(\.|$)")  # not the user's business
    warnings.filterwarnings(
        "ignore", message=".*(treespec|logging interval|not have many workers).*"
    )
    from talkmesh.datasets.reader import open_dataset, report_skipped

    out = Path(recipe.train.out_dir)
    ckpt = checkpoints.newest_checkpoint(out) if resume else None
    if ckpt is not None:
        checkpoints.check_resume(ckpt, to_dict(recipe))
    elif checkpoints.checkpoint_files(out):
        raise TalkmeshError(
            f"{out} already holds a run: pass --resume to continue it or choose train.out_dir"
        )

    seed_everything(recipe.train.seed)
    train_set = open_dataset(
        recipe.data.kind, recipe.data.root, recipe.data.train_split, regions=recipe.data.regions
    )
    if len(train_set) == 0:
        raise TalkmeshError(f"{recipe.data.root}: the {recipe.data.train_split} split is empty")
    train_set.drop_unloadable()  # a bad file is skipped (and counted), never fatal
    info = dataset_info(train_set)
    init = _init_path(recipe.init)
    system = build_system(recipe, info, init)
    if recipe.warm_start and ckpt is None:
        copied, skipped = warm_start(system.model, _init_path(recipe.warm_start))
        print(f"warm start from {recipe.warm_start}: {copied} tensors; kept {', '.join(skipped)}")
    if ckpt is not None:  # every check before the first write into the run folder
        checkpoints.check_state_shapes(ckpt, system.state_dict())
        checkpoints.announce(ckpt)
    out.mkdir(parents=True, exist_ok=True)
    (out / "recipe.json").write_text(json.dumps(to_dict(recipe), indent=2, sort_keys=True))
    task = task_spec(recipe.task)
    if task.prepare is not None and not resume:  # a resumed run restores them from the checkpoint
        task.prepare(system.model, train_set)
    from talkmesh.training.lip_gap import optional_terms

    system.terms = optional_terms(recipe.train, train_set, info)

    train_loader, val_loader = _loaders(recipe, train_set)
    trainer = _lightning_trainer(L, recipe, out, progress)
    trainer.fit(
        system,
        train_loader,
        val_loader,
        ckpt_path=str(ckpt.path) if ckpt is not None else None,
        weights_only=True,
    )

    if recipe.train.record_batches:
        _record_run(out, trainer.global_rank, system)
    release = out / "model.safetensors"
    if trainer.is_global_zero:
        task_spec(recipe.task).save(system.model, release)
        report_skipped(train_set, "training")
    return release


def recipe_from_checkpoint(path: str | Path) -> Recipe:
    """The recipe stored in a Lightning checkpoint written by :func:`train`."""
    ckpt = checkpoints.read_checkpoint(path)
    if not isinstance(ckpt.get("talkmesh_recipe"), dict):
        raise TalkmeshError(f"{path}: not written by talkmesh train (no recipe inside)")
    return from_dict(Recipe, ckpt["talkmesh_recipe"])


__all__ = [
    "DataConfig",
    "DatasetInfo",
    "Recipe",
    "StepOutput",
    "Task",
    "TorchBatch",
    "TrainConfig",
    "crop_window",
    "load_recipe",
    "train",
]
