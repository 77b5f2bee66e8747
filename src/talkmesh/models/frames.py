"""Speech features at any rate fitted to motion frames: shared by every speech encoder
(:mod:`talkmesh.models.speech`, :mod:`talkmesh.models.whisper`).

Axis letters: B batch, N feature frames, T motion frames, D width.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def interpolate_frames(features: Tensor, num_frames: int) -> Tensor:
    """(B, N, D) features at any rate -> (B, T, D), linear interpolation over time."""
    return F.interpolate(
        features.transpose(1, 2), size=num_frames, mode="linear", align_corners=True
    ).transpose(1, 2)


def fit_sample_frames(
    features: Tensor, valid_samples: int, total_samples: int, num_frames: int
) -> Tensor:
    """One padded-batch sample's features (N, D) over its own audio -> (num_frames, D).

    The batch's ``num_frames`` motion frames span ``total_samples`` audio samples; this sample
    has ``valid_samples`` of them, so its features are interpolated over its share of the frames
    and the rest repeat its last frame (padding, masked by the caller). Stretching them over all
    ``num_frames`` instead would misalign every sample shorter than the batch's longest.
    """
    n = num_frames
    if valid_samples < total_samples:
        n = min(num_frames, max(1, int(round(num_frames * valid_samples / total_samples))))
    out = interpolate_frames(features[None], n)[0]
    if n < num_frames:
        out = torch.cat([out, out[-1:].expand(num_frames - n, -1)])
    return out
