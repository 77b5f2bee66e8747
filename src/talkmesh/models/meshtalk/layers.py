"""MeshTalk's expression-space layers (Richard et al., ICCV 2021, Sec. 3.1, Fig. 2), used by
:class:`talkmesh.models.meshtalk.model.MeshTalk`:

1. :class:`ExpressionEncoder`: per-frame MLP + LSTM over the mesh sequence.
2. :class:`FusionQuantizer` and :func:`gumbel_one_hot`: MLP to H heads of C logits, hard
   straight-through Gumbel-softmax (Eq. 1-2).
3. :class:`TemplateDecoder`: U-Net over the template with additive skips, the code concatenated at
   the bottleneck, two LSTM layers, back to vertices (Eq. 3).

Each carries the official-exact switches (``official`` / ``output_dim``) that imported models
turn on (docs/guide/official.md lists them next to talkmesh's defaults).

Axis letters: B batch, T motion frames, V vertices, H heads, C classes, D width.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.models.mel import LEAKY_SLOPE

# ---------------------------------------------------------------------------------------------
# 1. Expression encoder


class ExpressionEncoder(nn.Module):
    """(B, T, V*3) normalised vertices -> (B, T, D): FC layers and one LSTM (Sec. 3.1); with
    ``output_dim`` a Linear to that width after the LSTM (the official ``code`` layer)."""

    def __init__(self, in_dim: int, widths: tuple[int, ...], output_dim: int = 0) -> None:
        super().__init__()
        dims = (in_dim, *widths)
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.lstm = nn.LSTM(widths[-1], widths[-1], batch_first=True)
        self.code = nn.Linear(widths[-1], output_dim) if output_dim else nn.Identity()

    def forward(self, x: Tensor) -> Tensor:
        for layer in self.layers:
            x = F.leaky_relu(layer(x), LEAKY_SLOPE)
        return self.code(self.lstm(x)[0])


# ---------------------------------------------------------------------------------------------
# 2. Fusion and Gumbel quantiser


class Quantized(NamedTuple):
    """logits (B, T, H, C); codes (B, T, H) int64; one_hot (B, T, H, C), straight-through in training."""

    logits: Tensor
    codes: Tensor
    one_hot: Tensor


def gumbel_one_hot(
    logits: Tensor, tau: float, sample: bool, generator: torch.Generator | None = None
) -> Quantized:
    """Hard straight-through Gumbel-softmax over the last axis (Eq. 2); argmax when not sampling."""
    if sample:
        u = torch.rand(logits.shape, generator=generator, device=logits.device, dtype=logits.dtype)
        noisy = logits - torch.log(-torch.log(u.clamp(min=1e-10, max=1.0 - 1e-7)))
        soft = torch.softmax(noisy / tau, dim=-1)
        codes = noisy.argmax(-1)
        hard = F.one_hot(codes, logits.shape[-1]).to(logits.dtype)
        return Quantized(logits, codes, hard - soft.detach() + soft)
    codes = logits.argmax(-1)
    return Quantized(logits, codes, F.one_hot(codes, logits.shape[-1]).to(logits.dtype))


class FusionQuantizer(nn.Module):
    """Three-layer MLP over [audio, expression] features -> H x C logits, then Gumbel (Eq. 1-2)."""

    def __init__(self, in_dim: int, width: int, num_heads: int, num_classes: int) -> None:
        super().__init__()
        self.num_heads, self.num_classes = num_heads, num_classes
        self.layers = nn.ModuleList(
            [
                nn.Linear(in_dim, width),
                nn.Linear(width, width),
                nn.Linear(width, num_heads * num_classes),
            ]
        )

    def forward(self, features: Tensor) -> Tensor:
        """(B, T, D) -> (B, T, H, C) logits."""
        x = features
        for layer in self.layers[:-1]:
            x = F.leaky_relu(layer(x), LEAKY_SLOPE)
        x = self.layers[-1](x)
        return x.view(*x.shape[:-1], self.num_heads, self.num_classes)


# ---------------------------------------------------------------------------------------------
# 3. Template-conditioned decoder


class TemplateDecoder(nn.Module):
    """U-Net over the template (Fig. 2): template encoder with additive skips, codes concatenated at
    the bottleneck, LSTMs over time, FC layers back to vertex offsets (zero-initialised last layer, so an
    untrained decoder returns the template).

    ``official`` (the released ``VertexUnet``): no skip around the LSTMs, the last layer is
    activated too (LeakyReLU, with torch's default init instead of zeros) and a per-coordinate
    ``vertex_bias`` is added after it; the official skip of the normalised template itself is the
    caller's ``template + offsets``.
    """

    def __init__(
        self,
        num_vertices: int,
        code_dim: int,
        widths: tuple[int, ...],
        lstm_layers: int,
        official: bool = False,
    ):
        super().__init__()
        self.official = official
        dims = (num_vertices * 3, *widths)
        self.encoder = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.bottleneck = nn.Linear(widths[-1] + code_dim, widths[-1])
        self.lstm = nn.LSTM(widths[-1], widths[-1], num_layers=lstm_layers, batch_first=True)
        up = dims[::-1]  # widths[-1] ... widths[0], V*3
        self.decoder = nn.ModuleList(nn.Linear(a, b) for a, b in zip(up[:-2], up[1:-1]))
        self.output = nn.Linear(widths[0], num_vertices * 3)
        if official:  # torch's default init, as officially: a zero weight under the LeakyReLU
            # would pass no gradient to the layers before it
            self.vertex_bias = nn.Parameter(torch.zeros(num_vertices * 3))
        else:
            nn.init.zeros_(self.output.weight)
            nn.init.zeros_(self.output.bias)

    def forward(self, template: Tensor, code: Tensor) -> Tensor:
        """template (B, V*3) normalised, code (B, T, H*C) -> (B, T, V*3) normalised offsets."""
        skips = []
        x = template
        for layer in self.encoder:
            x = F.leaky_relu(layer(x), LEAKY_SLOPE)
            skips.append(x)
        x = x[:, None].expand(-1, code.shape[1], -1)
        x = F.leaky_relu(self.bottleneck(torch.cat([x, code], dim=-1)), LEAKY_SLOPE)
        x = self.lstm(x)[0]
        if not self.official:
            x = x + skips[-1][:, None]
        for layer, skip in zip(self.decoder, reversed(skips[:-1])):
            x = F.leaky_relu(layer(x), LEAKY_SLOPE) + skip[:, None]
        if self.official:
            return F.leaky_relu(self.output(x), LEAKY_SLOPE) + self.vertex_bias
        return self.output(x)
