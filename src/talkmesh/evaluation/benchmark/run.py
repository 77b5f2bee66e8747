"""The whole run: what it would do (``plan_lines``) and doing it (``run_benchmark``), one named
step after the other, each resumable (see the package docstring for the resume rules)."""

from __future__ import annotations

import os
import socket
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from talkmesh.config import to_dict
from talkmesh.errors import TalkmeshError
from talkmesh.evaluation.benchmark.claims import aggregate, check_claims
from talkmesh.evaluation.benchmark.config import (
    DONE_FILE,
    SCORES_FILE,
    TIMING_FILE,
    BenchmarkConfig,
    StagePlan,
    ablation_cells,
    load_benchmark,
    method_stages,
    open_split,
)
from talkmesh.evaluation.benchmark.plots import (
    MAX_PNG_BYTES,
    MAX_VIDEO_BYTES,
    ablation_figure,
    lip_figure,
    motion_figure,
    sample_indices,
    side_by_side_video,
)
from talkmesh.evaluation.benchmark.report import fmt_seconds, render_markdown
from talkmesh.evaluation.benchmark.state import (
    predictions_done,
    read_json,
    stage_state,
    write_json,
)
from talkmesh.evaluation.benchmark.steps import (
    Log,
    baseline,
    codebook_usage,
    machine_info,
    measure_speed,
    now,
    predict,
    score,
    summary,
    train_stage,
)


class BenchmarkResult(NamedTuple):
    """What ``run_benchmark`` wrote and did (``trained``: stage dirs trained or resumed now)."""

    markdown: Path
    json: Path
    figures: list[Path]
    trained: list[Path]
    predicted: list[Path]


def selected(cfg: BenchmarkConfig, only: list[str] | None) -> list[str]:
    """The methods named by ``--only`` (all when None), in the config's order."""
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
    ds = open_split(cfg)
    yield (
        f"benchmark {cfg.name}: {len(selected(cfg, only))} methods x {len(cfg.seeds)} seeds "
        f"on {cfg.data.kind} {cfg.data.root} ({cfg.data.split}: {len(ds)} sequences)"
    )
    for name in cfg.baselines:
        d = work / "baselines" / name / "pred"
        yield f"baseline {name:<28} -> {d}  [{'done' if predictions_done(d, None) else 'run'}]"
    for method in selected(cfg, only):
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
        and cfg.ablation.method in selected(cfg, only)
    ):
        for c in ablation_cells(cfg):
            yield (
                f"ablation {cfg.ablation.method} {cfg.ablation.stage} {c.label} "
                f"-> {c.plan.out_dir}  [{stage_state(c.plan)}]"
            )
    secs = ", ".join(f"{s:g} s" for s in cfg.speed.seconds)
    yield f"speed    {', '.join(selected(cfg, only))} (seed {cfg.seeds[0]}) at {secs}"
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
    cluster: str | None = None,
    cpus_per_task: float = 1,
) -> BenchmarkResult:
    """Run (or resume) the benchmark of ``config`` and write its markdown, JSON and figures;
    ``cluster`` (a Ray address) trains and predicts the cells there (:func:`_train_and_predict`)."""
    from talkmesh.version import __version__

    cfg = load_benchmark(config)
    methods = selected(cfg, only)
    log = log or Log(quiet)
    progress = progress and not quiet
    machine = machine_info()
    docs = Path(cfg.docs_dir)
    fig_dir = docs / cfg.name
    run = _Run(cfg, open_split(cfg), log, progress)
    baselines = _baselines(run)
    _train_and_predict(run, methods, cluster, cpus_per_task)
    results = _score_methods(run, methods)
    claims = check_claims(
        {m: r["aggregate"] for m, r in results.items()},
        {m: [x["scores"] for x in r["seeds"].values()] for m, r in results.items()},
    )
    ablation = None
    if cfg.ablation is not None and not skip_ablation and cfg.ablation.method in methods:
        ablation = _ablation(run, fig_dir)
    speed = _speed(run, methods, results)
    video = cfg.video and not skip_video
    figures, written, indices = _figures(
        run, methods, results, baselines, fig_dir, video=video, ablation=ablation is not None
    )
    command = " ".join(
        ["talkmesh", "benchmark", str(config)]
        + ([f"--only {','.join(methods)}"] if only else [])
        + (["--skip-video"] if skip_video else [])
        + (["--skip-ablation"] if skip_ablation else [])
    )
    dataset = run.dataset
    report = {
        "name": cfg.name,
        "command": command,
        "finished": now(),
        "talkmesh": __version__,
        "config": to_dict(cfg),
        "machine": machine,
        "data": {
            "kind": cfg.data.kind,
            "root": cfg.data.root,
            "split": cfg.data.split,
            "sequences": len(dataset),
            "frames": sum(len(dataset[i].vertices) for i in range(len(dataset))),
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
    write_json(json_path, report)
    md_path.write_text(render_markdown(report))
    log(f"wrote {md_path} and {json_path}")
    return BenchmarkResult(md_path, json_path, written, run.trained, run.predicted)


@dataclass
class _Run:
    """What the steps of one run share: the config, the evaluation split, the log, and the stage
    and prediction directories made by this run."""

    cfg: BenchmarkConfig
    dataset: Any
    log: Callable[[str], None]
    progress: bool
    trained: list[Path] = field(default_factory=list)
    predicted: list[Path] = field(default_factory=list)

    def stage(self, plan: StagePlan, what: str) -> dict[str, Any]:
        """The stage's timing record: read when it is done, else after training it now."""
        log = self.log
        state = stage_state(plan)
        if state == "done":
            log(f"{what}: done, skipped ({plan.out_dir})")
            return read_json(plan.out_dir / TIMING_FILE) or {"stage": plan.stage}
        verb = {"resume": "resuming", "stale": "retraining (its recipe or init changed)"}.get(
            state, "training"
        )
        log(f"{what}: {verb} {plan.recipe.task} -> {plan.out_dir}")
        record = train_stage(
            plan, keep_checkpoints=self.cfg.keep_checkpoints, progress=self.progress
        )
        self.trained.append(plan.out_dir)
        fps = record["frames_per_second"]
        log(
            f"{what}: trained in {fmt_seconds(record['seconds'])}"
            + (f" ({fps:.0f} frames/s, batch {record['batch_size']})" if fps else "")
        )
        return record

    def predict(self, release: Path, pred: Path, what: str) -> None:
        """The release's predictions for the evaluation split into ``pred``."""
        self.log(f"{what}: predicting {self.cfg.data.split} -> {pred}")
        predict(self.cfg, release, pred, progress=self.progress)
        self.predicted.append(pred)


def _baselines(run: _Run) -> dict[str, Any]:
    """Seed-free baselines, predicted once and scored: {name: pred dir, scores, predict record}."""
    out: dict[str, Any] = {}
    for name in run.cfg.baselines:
        d = Path(run.cfg.work_dir) / "baselines" / name / "pred"
        if predictions_done(d, None):
            run.log(f"baseline {name}: predictions done, skipped ({d})")
        else:
            run.log(f"baseline {name}: predicting -> {d}")
            baseline(run.cfg, name, d, progress=run.progress)
            run.predicted.append(d)
        run.log(f"baseline {name}: evaluating")
        scores = score(run.dataset, d)
        write_json(d.parent / SCORES_FILE, scores)
        out[name] = {"pred": str(d), "scores": summary(scores), "predict": read_json(d / DONE_FILE)}
    return out


def _train_and_predict(
    run: _Run, methods: list[str], cluster: str | None = None, cpus_per_task: float = 1
) -> None:
    """Every stage and prediction, seed-major (seed 0 of every method first), so that a run
    stopped part of the way already compares every method; scoring then only reads. With
    ``cluster`` (a Ray address or ``local``, :mod:`talkmesh.batch.cluster`) the method x seed
    cells are Ray tasks of ``cpus_per_task`` CPUs; baselines, scores, the ablation, speed and the
    report stay on this machine, so work and docs folders must be on a shared file system."""
    if cluster is not None:
        _train_and_predict_on_cluster(run, methods, cluster, cpus_per_task)
        return
    for seed in run.cfg.seeds:
        for method in methods:
            _cell(run, method, seed)


def _cell(run: _Run, method: str, seed: int) -> None:
    """One method x seed: its stages in order, then its predictions (each skipped when done)."""
    plans = method_stages(run.cfg, method, seed)
    for p in plans:
        run.stage(p, f"{method} seed {seed} {p.stage}")
    pred = Path(run.cfg.work_dir) / method / f"seed{seed}" / "pred"
    if not predictions_done(pred, plans[-1].release):
        run.predict(plans[-1].release, pred, f"{method} seed {seed}")


class CellResult(NamedTuple):
    """What a cell run elsewhere reports: its log lines, the stage and prediction folders it
    made, and where it ran (``host pid N``)."""

    lines: list[str]
    trained: list[Path]
    predicted: list[Path]
    where: str


def run_cell(cfg: BenchmarkConfig, method: str, seed: int, cwd: str) -> CellResult:
    """One method x seed cell in this process, from the driver's folder ``cwd`` (relative paths
    of the config mean the same there): a Ray task of ``run_benchmark(cluster=...)``."""
    os.chdir(cwd)
    lines: list[str] = []
    run = _Run(cfg, None, lines.append, progress=False)
    _cell(run, method, seed)
    return CellResult(
        lines, run.trained, run.predicted, f"{socket.gethostname()} pid {os.getpid()}"
    )


def _train_and_predict_on_cluster(
    run: _Run, methods: list[str], cluster: str, cpus_per_task: float
) -> None:
    """The cells of :func:`_train_and_predict` as Ray tasks, all at once; their logs as each ends."""
    from talkmesh.batch.cluster import map_tasks

    calls = [(run.cfg, m, s, os.getcwd()) for s in run.cfg.seeds for m in methods]
    run.log(f"cluster {cluster}: {len(calls)} cells, {cpus_per_task:g} CPUs each")
    for (_, method, seed, _), cell in map_tasks(run_cell, calls, cluster, num_cpus=cpus_per_task):
        for line in cell.lines:
            run.log(line)
        run.log(f"{method} seed {seed}: ran on {cell.where}")
        run.trained += cell.trained
        run.predicted += cell.predicted


def _score_methods(run: _Run, methods: list[str]) -> dict[str, Any]:
    """{method: recipe, per-seed scores/timings, aggregate over seeds}."""
    results: dict[str, Any] = {}
    for method in methods:
        per_seed: dict[int, Any] = {}
        for seed in run.cfg.seeds:
            plans = method_stages(run.cfg, method, seed)
            training = [run.stage(p, f"{method} seed {seed} {p.stage}") for p in plans]
            seed_dir = Path(run.cfg.work_dir) / method / f"seed{seed}"
            pred = seed_dir / "pred"
            release = plans[-1].release
            if predictions_done(pred, release):
                run.log(f"{method} seed {seed}: predictions done, skipped ({pred})")
            else:
                run.predict(release, pred, f"{method} seed {seed}")
            run.log(f"{method} seed {seed}: evaluating")
            scores = score(run.dataset, pred)
            write_json(seed_dir / SCORES_FILE, scores)
            per_seed[seed] = {
                "release": str(release),
                "pred": str(pred),
                "scores": summary(scores),
                "training": training,
                "predict": read_json(pred / DONE_FILE),
            }
        results[method] = {
            "recipe": run.cfg.methods[method].recipe,
            "seeds": {str(s): r for s, r in per_seed.items()},
            "aggregate": aggregate({s: r["scores"] for s, r in per_seed.items()}),
        }
    return results


def _ablation(run: _Run, fig_dir: Path) -> dict[str, Any]:
    """CodeTalker Fig. 7: each grid cell's stage trained, its reconstruction scored, its codebook
    usage counted; the heatmaps drawn."""
    cfg, ab = run.cfg, run.cfg.ablation
    assert ab is not None
    cells = []
    for c in ablation_cells(cfg):
        what = f"ablation {c.label}"
        timing = run.stage(c.plan, what)
        pred = c.plan.out_dir.parent / "recon"
        if not predictions_done(pred, c.plan.release):
            run.log(f"{what}: reconstructing {cfg.data.split} -> {pred}")
            predict(cfg, c.plan.release, pred, progress=run.progress, mode="reconstruct")
        scores = summary(score(run.dataset, pred))
        cells.append(
            {
                "values": c.values,
                "label": c.label,
                "dir": str(c.plan.out_dir),
                "codetalker": scores["codetalker"],
                "physical": scores["physical"],
                "usage": codebook_usage(c.plan.release, run.dataset),
                "timing": timing,
            }
        )
    figure = ablation_figure(ab, cells, fig_dir / "ablation.png")
    return {
        "method": ab.method,
        "stage": ab.stage,
        "seed": ab.seed,
        "grid": {k: list(v) for k, v in ab.grid.items()},
        "cells": cells,
        "figure": f"{cfg.name}/{figure.name}",
    }


def _speed(run: _Run, methods: list[str], results: dict[str, Any]) -> dict[str, Any]:
    """Generation time of each method's first-seed release at each audio length."""
    cfg = run.cfg
    speed: dict[str, Any] = {
        "audio": f"{cfg.data.split}-split speech of {cfg.data.root}, sequences joined",
        "repeats": cfg.speed.repeats,
        "methods": {},
    }
    for method in methods:
        release = Path(results[method]["seeds"][str(cfg.seeds[0])]["release"])
        run.log(
            f"{method}: timing generation at {', '.join(f'{s:g}' for s in cfg.speed.seconds)} s"
        )
        speed["methods"][method] = measure_speed(release, run.dataset, cfg.speed)
    return speed


def _figures(
    run: _Run,
    methods: list[str],
    results: dict[str, Any],
    baselines: dict[str, Any],
    fig_dir: Path,
    *,
    video: bool,
    ablation: bool,
) -> tuple[dict[str, Any], list[Path], list[int]]:
    """Lip distance, motion statistics and the video from the seed-0 predictions: (the report's
    figures entry, the files written, the sampled sequence indices)."""
    cfg, dataset = run.cfg, run.dataset
    first = str(cfg.seeds[0])
    preds = {m: Path(results[m]["seeds"][first]["pred"]) for m in methods}
    lip_preds = {**preds, **{b: Path(baselines[b]["pred"]) for b in cfg.baselines}}
    indices = sample_indices(len(dataset), cfg.samples)
    figures: dict[str, Any] = {"notes": []}
    written: list[Path] = []
    if indices:
        run.log("figures: lip distance")
        p = lip_figure(dataset, indices, lip_preds, fig_dir / "lip_distance.png")
        if p is None:
            figures["notes"].append(
                "no lip-distance figure: the mesh is not the bundled head's "
                "topology (its lip pairs are unknown)"
            )
        else:
            figures["lip_distance"] = f"{cfg.name}/{p.name}"
            written.append(p)
    run.log("figures: motion statistics")
    p = motion_figure(dataset, preds, fig_dir / "motion_stats.png")
    figures["motion_stats"] = f"{cfg.name}/{p.name}"
    written.append(p)
    if ablation:
        written.append(fig_dir / "ablation.png")
    if video and indices:
        run.log("video: side by side")
        mp4 = fig_dir / f"{cfg.name}_side_by_side.mp4"
        made = side_by_side_video(dataset, indices[0], lip_preds, mp4, cfg.video_size, run.progress)
        if made is None:
            figures["notes"].append("no video: the dataset has no faces (.ply) to render")
        else:
            figures["video"] = f"{cfg.name}/{made.name}"
            figures["video_kb"] = made.stat().st_size // 1024
            written.append(made)
    for p in written:
        if p.stat().st_size > (MAX_PNG_BYTES if p.suffix == ".png" else MAX_VIDEO_BYTES):
            figures["notes"].append(f"{p.name} is {p.stat().st_size // 1024} KB")
    return figures, written, indices
