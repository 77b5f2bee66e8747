"""Aggregation over seeds and the paper's ordering claims (CodeTalker Table 1), with verdicts."""

from __future__ import annotations

from typing import Any

import numpy as np

from talkmesh.evaluation.benchmark.config import METRICS

# CodeTalker Table 1 (VOCASET, BIWI): (metric, better, worse), lower is better
CLAIMS: tuple[tuple[str, str, str], ...] = (
    ("lve", "codetalker", "faceformer"),
    ("lve", "faceformer", "meshtalk"),
    ("lve", "faceformer", "voca"),
    ("fdd", "codetalker", "faceformer"),
    ("fdd", "codetalker", "meshtalk"),
    ("fdd", "codetalker", "voca"),
)


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
