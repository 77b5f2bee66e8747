"""The lip-gap loss: an optional training term on the distance between the lips.

The vertex losses of the papers (CodeTalker's Eq. 6, FaceFormer's MSE) weigh every coordinate of
the face alike; a closure of the lips is a millimetre or two of a few vertices among thousands, and
a model can leave it out at almost no cost: the lips of a model trained on them alone stop 2 mm
apart at /p b m/ where its teacher closes them (docs/results/multilingual.md). This term compares
the predicted gap between facing lip vertices with the truth's, so that a gap left open costs what
it looks like.

The pairs are found from the data, for any topology: pairs of lip vertices (the dataset's lip
vertex error region) close together on the template whose distance changes the most over the
training motion: the lips facing each other across the mouth, which part and meet as it speaks.

``train.lip_gap_weight`` in a recipe turns it on (0, the papers' loss, by default).
``train.lip_close_weight`` counts the frames where the truth's lips are shut (one of the
``SHUT_PAIRS`` pairs that part the most within ``CLOSED`` of the lip region's width: 0.5 mm of the
synthetic corpus's 85 mm region) 1 + that weight times: a closure of /p b m/ is a tenth of a
second among seconds of speech, and a model that leaves it 2 mm open loses little on the average
gap. ``train.lip_rest_weight`` does the same for the frames where the truth's mouth is at rest
(every pair's distance within ``AT_REST`` of the lip width of its distance on the template: the
pauses), so that a pause is not left a millimetre open where the face's lips nearly touch.

:class:`CodeChoice` (``train.code_ce_weight``) is the other term kept here: a model that queries a
codebook (CodeTalker's stage 2) regresses its features onto the true code's (Eq. 6), so where the
speech leaves two codes equally likely (the lips shut or just apart) it lands between them, on a
code for the average. The cross-entropy of the codes, with the negative squared distances to
every code as logits (in units of the codebook's typical squared distance between neighbouring
codes, so that the term does not depend on the codebook's scale), rewards picking the likely code
instead.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from talkmesh.errors import TalkmeshError

REACH = 0.08  # candidate pairs: at most this share of the lip region's width apart on the template
SHARE = 0.5  # keep pairs whose gap varies at least this share of the most varying pair's
SAMPLES = 32  # training clips read to find the pairs
CLOSED = 0.006  # the truth's lips are shut where a pair of the middle of the mouth is within
SHUT_PAIRS = 8  # this share of the lip region's width; that many of the pairs parting the most
AT_REST = 0.001  # the truth's mouth is at rest where every pair is this share of the width from
# its distance on the template (0.085 mm of the synthetic corpus's 85 mm lip region)


def lip_width(template: np.ndarray, lips: np.ndarray) -> float:
    """The lip region's width (its largest extent along an axis), in the data's units."""
    return float(np.ptp(template[lips], axis=0).max())


def lip_gap_pairs(dataset, lips: np.ndarray | None) -> np.ndarray:
    """(P, 2) vertex pairs across the lip gap, from the template and the training motion of
    ``dataset`` (a ``MotionDataset``); ``lips``: the lip region's vertex ids."""
    pairs, spread, _ = _pair_spreads(dataset, lips)
    return pairs[spread >= SHARE * spread.max()]


def widest_lip_pairs(dataset, lips: np.ndarray | None, count: int) -> np.ndarray:
    """(count, 2) the pairs across the lip gap whose distance changes the most over the
    training motion of ``dataset``: the lips at the middle of the mouth, which part the most."""
    pairs, spread, _ = _pair_spreads(dataset, lips)
    return pairs[np.argsort(-spread, kind="stable")[:count]]


def _pair_spreads(dataset, lips: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, list]:
    """(P, 2) candidate pairs of lip vertices close together on the template, (P,) the
    standard deviation of their distance over the training motion, and the clips it read."""
    if lips is None or len(lips) < 2:
        raise TalkmeshError(
            "train.lip_gap_weight needs the data's lip region (regions/lve.txt): add it or set "
            "lip_gap_weight to 0"
        )
    lips = np.asarray(lips, np.int64)
    step = max(1, len(dataset) // SAMPLES)
    clips = [dataset[i] for i in range(0, len(dataset), step)]
    template = clips[0].template.astype(np.float64)
    candidates = cKDTree(template[lips]).query_pairs(
        REACH * lip_width(template, lips), output_type="ndarray"
    )
    if not len(candidates):
        raise TalkmeshError("the lip region's vertices are too far apart to find the lip gap")
    i, j = lips[candidates[:, 0]], lips[candidates[:, 1]]
    gaps = np.concatenate(
        [np.linalg.norm(c.vertices[:, i] - c.vertices[:, j], axis=-1) for c in clips]
    )
    return np.stack([i, j], axis=1), gaps.std(axis=0), clips


def lip_gap_loss(
    motion: torch.Tensor,
    vertices: torch.Tensor,
    templates: torch.Tensor,
    pairs: torch.Tensor,
    width: float,
    mask: torch.Tensor | None = None,
    close_weight: float = 0.0,
    shut_pairs: torch.Tensor | None = None,
    rest_weight: float = 0.0,
) -> torch.Tensor:
    """Mean squared error of the gap vectors between ``pairs`` (P, 2), in per cent of the lip
    region's ``width``: motion (B, T, V*3) predicted offsets, vertices (B, T, V, 3) the truth,
    templates (B, V, 3), mask (B, T) the real frames; the frames where the truth's lips are
    shut (:func:`shut_frames` of ``shut_pairs``) count ``1 + close_weight`` times, those where
    its mouth is at rest (:func:`rest_frames`) ``1 + rest_weight`` times."""
    B, T = vertices.shape[:2]
    pred = motion.reshape(B, T, -1, 3)
    true = vertices - templates[:, None]
    a, b = pairs[:, 0], pairs[:, 1]
    err = ((pred[:, :, a] - pred[:, :, b]) - (true[:, :, a] - true[:, :, b])) * (100.0 / width)
    per_frame = err.pow(2).sum(-1).mean(-1)  # (B, T)
    if close_weight:
        shut = shut_frames(vertices, pairs if shut_pairs is None else shut_pairs, width)
        per_frame = per_frame * (1.0 + close_weight * shut.to(per_frame.dtype))
    if rest_weight:
        still = rest_frames(vertices, templates, pairs, width)
        per_frame = per_frame * (1.0 + rest_weight * still.to(per_frame.dtype))
    if mask is None:
        return per_frame.mean()
    w = mask.to(per_frame.dtype)
    return (per_frame * w).sum() / w.sum().clamp(min=1)


def shut_frames(vertices: torch.Tensor, pairs: torch.Tensor, width: float) -> torch.Tensor:
    """(B, T) bool: the frames of vertices (B, T, V, 3) where one of ``pairs`` (P, 2) is within
    ``CLOSED`` of the lip ``width``: the lips shut."""
    gap = (vertices[:, :, pairs[:, 0]] - vertices[:, :, pairs[:, 1]]).norm(dim=-1)
    return gap.min(dim=-1).values <= CLOSED * width


def rest_frames(
    vertices: torch.Tensor, templates: torch.Tensor, pairs: torch.Tensor, width: float
) -> torch.Tensor:
    """(B, T) bool: the frames of vertices (B, T, V, 3) where every one of ``pairs`` (P, 2) is
    within ``AT_REST`` of the lip ``width`` of its distance on templates (B, V, 3): at rest."""
    a, b = pairs[:, 0], pairs[:, 1]
    gap = (vertices[:, :, a] - vertices[:, :, b]).norm(dim=-1)
    rest = (templates[:, a] - templates[:, b]).norm(dim=-1)[:, None]
    return (gap - rest).abs().max(dim=-1).values <= AT_REST * width


class LipGap:
    """The term as a recipe adds it to a task's loss: ``weight`` x :func:`lip_gap_loss`."""

    def __init__(
        self,
        pairs: np.ndarray,
        width: float,
        weight: float,
        close_weight: float = 0.0,
        shut_pairs: np.ndarray | None = None,
        rest_weight: float = 0.0,
    ) -> None:
        self.pairs = torch.from_numpy(np.asarray(pairs, np.int64))
        self.width = width
        self.weight = weight
        self.close_weight = close_weight
        self.rest_weight = rest_weight
        self.shut_pairs = None if shut_pairs is None else torch.from_numpy(shut_pairs)

    @classmethod
    def from_data(
        cls, dataset, regions, weight: float, close_weight: float = 0.0, rest_weight: float = 0.0
    ) -> LipGap:
        lips = getattr(regions, "lve", None)
        candidates, spread, clips = _pair_spreads(dataset, lips)
        order = np.argsort(-spread, kind="stable")
        pairs = candidates[order[spread[order] >= SHARE * spread.max()]]  # lip_gap_pairs
        width = lip_width(clips[0].template, np.asarray(lips, np.int64))
        note, shut_pairs = "", None

        def share(frames) -> float:  # of the clips the pairs were found on
            return float(torch.cat([frames(c) for c in clips], dim=1).float().mean())

        if close_weight:  # the pairs parting the most, among those that part at all
            shut_pairs = pairs[:SHUT_PAIRS]
            shut = share(lambda c: shut_frames(_t(c.vertices), torch.from_numpy(shut_pairs), width))
            note = f"; the truth's shut frames ({shut:.1%} of them) weigh {1 + close_weight:g}"
        if rest_weight:
            still = share(
                lambda c: rest_frames(
                    _t(c.vertices), _t(c.template), torch.from_numpy(pairs), width
                )
            )
            note += f"; its frames at rest ({still:.1%}) weigh {1 + rest_weight:g}"
        print(f"lip-gap loss on {len(pairs)} vertex pairs (weight {weight}){note}")
        return cls(pairs, width, weight, close_weight, shut_pairs, rest_weight)

    def add(self, loss, logs, out, batch, task: str) -> tuple[torch.Tensor, dict[str, float]]:
        """(``loss`` plus this term, ``logs`` with it) for a task's StepOutput ``out``."""
        if out.motion is None:
            raise TalkmeshError(f"task {task} has no lip-gap loss: set train.lip_gap_weight to 0")
        gap = lip_gap_loss(
            out.motion,
            batch.vertices,
            batch.templates,
            self.pairs.to(out.motion.device),
            self.width,
            batch.motion_mask,
            self.close_weight,
            None if self.shut_pairs is None else self.shut_pairs.to(out.motion.device),
            self.rest_weight,
        )
        return loss + self.weight * gap, {**logs, "lip_gap": float(gap.detach())}


def _t(array: np.ndarray) -> torch.Tensor:
    """One clip's array as a batch of one."""
    return torch.from_numpy(np.asarray(array))[None]


class CodeChoice:
    """``weight`` x the cross-entropy of the true codes under logits -|feature - code|^2."""

    def __init__(self, weight: float) -> None:
        self.weight = weight

    def add(self, loss, logs, out, batch, task: str) -> tuple[torch.Tensor, dict[str, float]]:
        if out.codes is None:
            raise TalkmeshError(f"task {task} queries no codebook: set train.code_ce_weight to 0")
        features, codes, codebook = out.codes
        ce = code_cross_entropy(features, codes, codebook, batch.motion_mask)
        return loss + self.weight * ce, {**logs, "code_ce": float(ce.detach())}


def code_cross_entropy(
    features: torch.Tensor,
    codes: torch.Tensor,
    codebook: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """features (B, T, H, C), codes (B, T, H), codebook (K, C), mask (B, T) -> mean CE."""
    flat = features.reshape(-1, features.shape[-1])
    between = torch.cdist(codebook.detach(), codebook.detach()).pow(2)
    between.fill_diagonal_(float("inf"))
    unit = between.min(1).values.median().clamp(min=1e-12)  # neighbouring codes' distance
    dist = flat.pow(2).sum(1, keepdim=True) - 2 * flat @ codebook.t() + codebook.pow(2).sum(1)[None]
    logits = -dist / unit
    ce = torch.nn.functional.cross_entropy(logits, codes.reshape(-1), reduction="none")
    ce = ce.view(codes.shape).mean(-1)  # (B, T)
    if mask is None:
        return ce.mean()
    w = mask.to(ce.dtype)
    return (ce * w).sum() / w.sum().clamp(min=1)


def optional_terms(train, dataset, info) -> list:
    """The terms a recipe's ``train`` section turns on, for its training ``dataset``."""
    terms: list = []
    for name in ("lip_close_weight", "lip_rest_weight"):
        if getattr(train, name) > 0 and not train.lip_gap_weight > 0:
            raise TalkmeshError(f"train.{name} weighs the lip-gap loss: set lip_gap_weight too")
    if train.lip_gap_weight > 0:
        terms.append(
            LipGap.from_data(
                dataset,
                info.regions,
                train.lip_gap_weight,
                train.lip_close_weight,
                train.lip_rest_weight,
            )
        )
    if train.code_ce_weight > 0:
        terms.append(CodeChoice(train.code_ce_weight))
    return terms
