"""The benchmark's steps, each on one stage or one prediction directory: train (or resume) a
stage, generate a release's predictions, write a baseline, score, count codebook usage, time
generation, describe the machine."""

from __future__ import annotations

import math
import os
import platform
import shutil
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from talkmesh.errors import TalkmeshError
from talkmesh.evaluation.benchmark.config import (
    DONE_FILE,
    METRICS,
    TIMING_FILE,
    BenchmarkConfig,
    SpeedSpec,
    StagePlan,
)
from talkmesh.evaluation.benchmark.state import file_digest, stage_state, write_json


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
    """Epochs already completed by the run in ``last``'s folder: the newest checkpoint there that
    loads with ``weights_only`` (one that would run code is refused, never unpickled), the one
    ``train(resume=True)`` continues."""
    from talkmesh.training.checkpoints import newest_checkpoint

    return newest_checkpoint(last.parent).epoch + 1


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
    write_json(out / TIMING_FILE, record)
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
        finished=now(),
    )
    write_json(out / TIMING_FILE, record)
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
        "finished": now(),
    }
    write_json(pred_dir / DONE_FILE, record)
    return record


def baseline(cfg: BenchmarkConfig, name: str, pred_dir: Path, *, progress: bool) -> dict[str, Any]:
    from talkmesh.evaluation.evaluate import write_baseline

    if pred_dir.exists():
        shutil.rmtree(pred_dir)
    t0 = time.perf_counter()
    n = write_baseline(
        cfg.data.kind, cfg.data.root, pred_dir, method=name, split=cfg.data.split, progress=progress
    )
    record = {"baseline": name, "files": n, "seconds": time.perf_counter() - t0, "finished": now()}
    write_json(pred_dir / DONE_FILE, record)
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


def summary(scores: dict[str, dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """Per protocol, the metrics and counts of ``score``'s output (per-sequence rows dropped)."""
    return {p: {m: s[m] for m in (*METRICS, "n_sequences", "n_frames")} for p, s in scores.items()}


def codebook_usage(release: Path, dataset) -> dict[str, Any]:
    """Codes a stage-1 VQ-VAE uses on ``dataset``: distinct codes, their share and perplexity."""
    import torch

    from talkmesh.models.release import load_model

    net = load_model(release)
    size = net.codebook_size
    counts = torch.zeros(size, dtype=torch.float64)
    with torch.inference_mode():
        for i in range(len(dataset)):
            s = dataset[i]
            # copies: the dataset memory-maps its arrays read-only
            vertices, template = torch.tensor(s.vertices), torch.tensor(s.template)
            codes = net.motion_codes(vertices[None], template[None])
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


def now() -> str:
    """UTC time of day, to the second, for the records."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")
