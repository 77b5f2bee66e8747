"""Metrics, exactly as the papers' evaluation scripts compute them, and in physical form.

Anchor protocol (CodeTalker ``cal_metric.py``; comparable with published tables):

* LVE: pool all frames of all sequences; per frame, the max over lip vertices of the SQUARED L2
  error (no square root); mean over the pooled frames. Papers print it as "x1e-4 mm" although
  it is a squared quantity.
* FDD: per sequence, over upper-face vertices, e_v(t) = ||x_v(t) - template_v||^2 and
  D = mean_v std_t(e_v) (population std); FDD = mean over sequences of (D_gt - D_pred), SIGNED.

Physical protocol (what a reader can picture):

* LVE: per frame the max over lip vertices of the Euclidean error (with the square root); mean
  over pooled frames, in the data's units (metres for talkmesh heads: x1000 for mm).
* FDD: as above but e_v(t) = ||x_v(t) - template_v|| (a distance, not its square) and the mean of
  |D_gt - D_pred| (absolute).

Both report MVE (mean over frames and all vertices of the Euclidean error) and lip-sync
correlation (Pearson r over time between predicted and true lip opening, mean over sequences).
MeshTalk's lip error (lip vertices centred per frame, Euclidean, max, mean) is
:func:`meshtalk_lip_error`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from talkmesh.errors import TalkmeshError

Protocol = Literal["codetalker", "physical"]
PROTOCOLS = ("codetalker", "physical")


def _f64(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def _check_pair(pred: np.ndarray, gt: np.ndarray) -> None:
    if pred.ndim != 3 or pred.shape[2] != 3 or pred.shape != gt.shape:
        raise TalkmeshError(
            f"prediction {pred.shape} and ground truth {gt.shape} must both be (T, V, 3)"
        )


def lip_max_error(pred: np.ndarray, gt: np.ndarray, lips: np.ndarray, squared: bool) -> np.ndarray:
    """(T, V, 3) x2, lip ids -> (T,) per-frame max over lips of the (squared) L2 error."""
    _check_pair(pred, gt)
    err = ((_f64(pred[:, lips]) - _f64(gt[:, lips])) ** 2).sum(-1)  # (T, L)
    per_frame = err.max(axis=1)
    return per_frame if squared else np.sqrt(per_frame)


def meshtalk_lip_error(pred: np.ndarray, gt: np.ndarray, lips: np.ndarray) -> float:
    """MeshTalk's lip error: lip vertices centred per frame, Euclidean, max over lips, mean."""
    p, g = _f64(pred[:, lips]), _f64(gt[:, lips])
    p = p - p.mean(axis=1, keepdims=True)
    g = g - g.mean(axis=1, keepdims=True)
    return float(np.sqrt(((p - g) ** 2).sum(-1)).max(axis=1).mean())


def dynamics(vertices: np.ndarray, template: np.ndarray, upper: np.ndarray, squared: bool) -> float:
    """D = mean over upper-face vertices of the std over time of the motion magnitude."""
    motion = _f64(vertices[:, upper]) - _f64(template[upper])[None]
    e = (motion**2).sum(-1)  # (T, U)
    if not squared:
        e = np.sqrt(e)
    return float(e.std(axis=0).mean())  # population std (ddof=0), as the anchors


def mean_vertex_error(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """(T,) mean over vertices of the Euclidean error per frame."""
    _check_pair(pred, gt)
    return np.sqrt(((_f64(pred) - _f64(gt)) ** 2).sum(-1)).mean(axis=1)


def lip_opening_pairs(vertices: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(T, V, 3), (P, 2) upper/lower lip vertex pairs -> (T,) mean distance between the pairs."""
    pairs = np.asarray(pairs).reshape(-1, 2)
    v = _f64(vertices)
    return np.linalg.norm(v[:, pairs[:, 0]] - v[:, pairs[:, 1]], axis=-1).mean(axis=1)


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson r of two (T,) curves; NaN when either is constant."""
    a, b = _f64(a), _f64(b)
    scale = 1e-9 * (1.0 + max(np.abs(a).max(initial=0), np.abs(b).max(initial=0)))
    if a.std() <= scale or b.std() <= scale:  # a still face has no lip-sync correlation
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


@dataclass(frozen=True)
class SequenceScores:
    """One (sequence, condition) row of a table, in the protocol's units."""

    name: str
    condition: str | None
    frames: int
    truncated: int  # frames dropped because prediction and ground truth differ in length
    lve: float  # per-sequence mean (the table's value pools frames, see Scores.lve)
    fdd: float  # D_gt - D_pred (signed; physical: its absolute value)
    mve: float
    lip_sync: float


@dataclass(frozen=True)
class Scores:
    """A split's scores: LVE and MVE pooled over all frames, FDD and lip sync over sequences."""

    protocol: str
    lve: float
    fdd: float
    mve: float
    lip_sync: float
    n_sequences: int
    n_frames: int
    rows: list[SequenceScores] = field(default_factory=list)


@dataclass(frozen=True)
class PendingScores:
    """One sequence's scores and the per-frame values that :func:`pool` pools over sequences."""

    row: SequenceScores
    lip_frames: np.ndarray
    mve_frames: np.ndarray


def score_sequence(
    pred: np.ndarray,
    gt: np.ndarray,
    template: np.ndarray,
    lips: np.ndarray,
    upper: np.ndarray,
    protocol: Protocol = "codetalker",
    lip_pairs: np.ndarray | None = None,
    name: str = "",
    condition: str | None = None,
) -> PendingScores:
    """Scores of one sequence, keeping the per-frame values needed for pooling."""
    if protocol not in PROTOCOLS:
        raise TalkmeshError(f"unknown protocol '{protocol}': use one of {', '.join(PROTOCOLS)}")
    n = min(len(pred), len(gt))
    truncated = max(len(pred), len(gt)) - n
    pred, gt = pred[:n], gt[:n]
    squared = protocol == "codetalker"
    lip = lip_max_error(pred, gt, lips, squared)
    mve = mean_vertex_error(pred, gt)
    d = dynamics(gt, template, upper, squared) - dynamics(pred, template, upper, squared)
    fdd = d if squared else abs(d)
    sync = float("nan")
    if lip_pairs is not None and n > 1:
        sync = correlation(lip_opening_pairs(pred, lip_pairs), lip_opening_pairs(gt, lip_pairs))
    row = SequenceScores(
        name, condition, n, truncated, float(lip.mean()), fdd, float(mve.mean()), sync
    )
    return PendingScores(row, lip, mve)


def pool(pending: list[PendingScores], protocol: Protocol) -> Scores:
    """Pool per-sequence results: LVE and MVE over all frames, FDD and lip sync over sequences."""
    if not pending:
        raise TalkmeshError("nothing to score: no prediction matched a sequence of the split")
    lips = np.concatenate([p.lip_frames for p in pending])
    mve = np.concatenate([p.mve_frames for p in pending])
    syncs = np.array([p.row.lip_sync for p in pending])
    return Scores(
        protocol=protocol,
        lve=float(lips.mean()),
        fdd=float(np.mean([p.row.fdd for p in pending])),
        mve=float(mve.mean()),
        lip_sync=float(np.nanmean(syncs)) if np.isfinite(syncs).any() else float("nan"),
        n_sequences=len(pending),
        n_frames=int(len(lips)),
        rows=[p.row for p in pending],
    )


def motion_statistics(sequences: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """CodeTalker Fig. 4: per-vertex mean and std over time of ||x(t+1) - x(t)||, pooled.

    sequences: list of (T, V, 3) -> (V,) mean, (V,) std.
    """
    steps = [np.linalg.norm(np.diff(_f64(s), axis=0), axis=-1) for s in sequences if len(s) > 1]
    if not steps:
        raise TalkmeshError("motion statistics need sequences of at least two frames")
    allsteps = np.concatenate(steps)  # (sum T-1, V)
    return allsteps.mean(axis=0), allsteps.std(axis=0)
