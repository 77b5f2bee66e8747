"""The benchmark's markdown page, rendered from its JSON report one section at a time."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from talkmesh.evaluation.benchmark.claims import mean_std
from talkmesh.evaluation.benchmark.config import METRICS
from talkmesh.evaluation.scope import scope_lines

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


def fmt_seconds(s: float | None) -> str:
    """A duration as ``42s`` or ``3m07s`` (``-`` when unknown)."""
    if s is None:
        return "-"
    s = int(round(s))
    return f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s"


def render_markdown(report: dict[str, Any]) -> str:
    """The benchmark's markdown page from its JSON report."""
    out = _header(report)
    out += scope_lines(report)  # the data, variants and budgets behind every number below
    for protocol in ("codetalker", "physical"):
        out += _scores(report, protocol)
    out += _claims(report)
    out += _figures(report)
    out += _ablation(report.get("ablation"))
    out += _speed(report.get("speed"), report["machine"])
    out += _training(report["methods"])
    return "\n".join(out) + "\n"


def _header(report: dict[str, Any]) -> list[str]:
    """Title, command, data, machine."""
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
    return out


def _scores(report: dict[str, Any], protocol: str) -> list[str]:
    """One protocol's table: every method (mean ± std, LVE per seed), then the baselines."""
    units = UNITS[protocol]
    title = (
        "anchor protocol (CodeTalker's cal_metric.py, comparable with the papers)"
        if protocol == "codetalker"
        else "physical protocol (Euclidean, mm)"
    )
    out = ["", f"## Scores: {title}", ""]
    head = ["method"] + [f"{LABELS[k]} ({units[k][1]})" for k in METRICS] + ["LVE per seed"]
    out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in report["methods"].items():
        agg = r["aggregate"][protocol]
        per = ", ".join(
            _num(s["scores"][protocol]["lve"], units["lve"][0]) for s in r["seeds"].values()
        )
        cells = [_pm(agg[k], units[k][0]) for k in METRICS]
        out.append(f"| {name} | " + " | ".join(cells) + f" | {per} |")
    for name, r in report["baselines"].items():
        s = r["scores"][protocol]
        cells = [_num(s[k], units[k][0]) for k in METRICS]
        out.append(f"| {name} (baseline) | " + " | ".join(cells) + " | - |")
    return out


def _claims(report: dict[str, Any]) -> list[str]:
    """The claims table, a one-line verdict per claim and the link to the discussion."""
    out = ["", "## The paper's ordering claims", ""]
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
        out += [_claim_row(c) for c in claims]
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
        link = f"[{report['discussion'].split('#')[0]}]({report['discussion']})"
        out += [
            "",
            f"Why these orderings come out as they do (written by hand, not by this command): {link}.",
        ]
    return out


def _claim_row(c: dict[str, Any]) -> str:
    scale = UNITS[c["protocol"]][c["metric"]][0]
    metric = "\\|FDD\\|" if c["metric"] == "fdd" else LABELS[c["metric"]]
    a = {"mean": c["better_mean"], "std": c["better_std"]}
    b = {"mean": c["worse_mean"], "std": c["worse_std"]}
    return (
        f"| {c['better']} < {c['worse']} in {metric} | {c['protocol']} | {_pm(a, scale)} | "
        f"{_pm(b, scale)} | {c['difference'] * scale:+.3f} | {c['std_sum'] * scale:.3f} | "
        f"{_pairs(c)} | **{c['verdict']}** |"
    )


def _figures(report: dict[str, Any]) -> list[str]:
    figs = report["figures"]
    out = ["", "## Figures", ""]
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
    return out


def _ablation(ab: dict[str, Any] | None) -> list[str]:
    if not ab:
        return []
    out = [
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
            f"{u['perplexity']:.1f} | {fmt_seconds(c['timing'].get('seconds'))} |"
        )
    if ab.get("figure"):
        out += ["", f"![ablation]({ab['figure']})"]
    return out


def _speed(speed: dict[str, Any] | None, machine: dict[str, Any]) -> list[str]:
    if not speed:
        return []
    out = [
        "",
        "## Speed",
        "",
        f"Generation of speech of each length ({speed['audio']}), the minimum of "
        f"{speed['repeats']} runs, {machine['torch_threads']} torch threads on the machine "
        "above; real-time factor = generation time / audio length (below 1: faster than real "
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
    return out


def _training(methods: dict[str, Any]) -> list[str]:
    """Per method and stage: wall time per seed, throughput, prediction time."""
    out = [
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
                fmt_seconds(t.get("seconds")) + (" (resumed)" if t.get("resumed") else "")
                for t in per
            )
            fps = mean_std([t.get("frames_per_second") for t in per])
            pred = ", ".join(fmt_seconds(s["predict"].get("seconds")) for s in r["seeds"].values())
            out.append(
                f"| {name} | {stage['stage']} | {stage.get('task', '-')} | "
                f"{stage.get('epochs', '-')} | {stage.get('batch_size', '-')} | "
                f"{stage.get('max_seconds', '-')} | {walls} | {_pm(fps, 1.0, 0)} | "
                f"{pred if k == len(stages) - 1 else ''} |"
            )
    return out
