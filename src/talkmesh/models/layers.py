"""Transformer layers shared by CodeTalker and FaceFormer: pre-LN blocks with key/value caches
trimmed to a window, the periodic ALiBi bias and periodic positional encoding (FaceFormer, Fan et
al., CVPR 2022, Sec. 3.2), and the folded feedback map of generation steps.

Axis letters: B batch, T frames, D width.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.models.int8 import int8_layers


def sinusoid(positions: Tensor, dim: int) -> Tensor:
    """positions (T,) -> (T, dim) sinusoidal encodings (a different vector per frame)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=positions.device) / half)
    angles = positions.float()[:, None] * freqs[None]
    out = torch.cat([angles.sin(), angles.cos()], dim=-1)
    return F.pad(out, (0, dim - out.shape[-1]))


def aligned_mask(bias: Tensor | None) -> Tensor | None:
    """An attention bias that CUDA's memory-efficient attention kernel can read.

    That kernel needs the mask's rows to start on 16-byte boundaries; a slice of a longer bias (a
    generation step's row of the temporal bias) starts anywhere and fails with "misaligned
    address". On CUDA the bias is copied into a fresh buffer whose rows are padded to 8 values;
    on the CPU it is returned as it is.
    """
    if bias is None or bias.device.type == "cpu":
        return bias
    return padded_rows(bias)


def padded_rows(bias: Tensor) -> Tensor:
    """The same values in a fresh buffer whose rows are padded to a multiple of 8 values."""
    n = bias.shape[-1]
    padded = bias.new_empty(*bias.shape[:-1], n + (-n) % 8)
    padded[..., :n] = bias
    return padded[..., :n]


class KVCache:
    """Keys and values of one attention layer, (B, heads, T, dh), trimmed to a window.

    The buffer holds twice the window and is written in place; when it is full the last window
    is moved to its start, once per ``window`` steps, so appending costs O(1) amortised (a
    ``torch.cat`` per step would copy the whole window every frame).
    """

    def __init__(self, window: int) -> None:
        self.window = window
        self.k: Tensor | None = None  # buffers
        self.v: Tensor | None = None
        self.n = 0  # filled rows of the buffers
        self.offset = 0  # absolute index of the first row of the buffers

    def append(self, k: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """Add ``t`` rows -> the keys and values they see: the last ``window + t - 1`` rows (each
        new row's own window; the caller's bias masks the rows outside it)."""
        t = k.shape[2]
        if self.k is None or self.n + t > self.k.shape[2]:
            keep = min(self.n, self.window - 1)
            shape = (*k.shape[:2], max(2 * self.window, keep + t), k.shape[3])
            new_k, new_v = k.new_empty(shape), v.new_empty(shape)
            if keep:
                new_k[:, :, :keep] = self.k[:, :, self.n - keep : self.n]
                new_v[:, :, :keep] = self.v[:, :, self.n - keep : self.n]
            self.offset += self.n - keep
            self.k, self.v, self.n = new_k, new_v, keep
        self.k[:, :, self.n : self.n + t] = k
        self.v[:, :, self.n : self.n + t] = v
        self.n += t
        start = max(0, self.n - (self.window + t - 1))
        return self.k[:, :, start : self.n], self.v[:, :, start : self.n]

    def drop(self, rows: int) -> None:
        """Forget the last ``rows`` rows (at most as many as the last append added)."""
        self.n -= rows


def window_bias(
    heads: int, q_len: int, k_len: int, window: int, period: int | None, device=None
) -> Tensor:
    """(heads, q_len, k_len) bias of the last ``q_len`` of ``k_len`` positions as queries over all
    of them: each sees the ``window`` positions up to itself (-inf elsewhere), with the periodic
    ALiBi of :func:`temporal_bias` (``period``) or no bias within the window (``None``)."""
    q_offset = k_len - q_len
    if period is None:
        bias = torch.zeros(heads, q_len, k_len, device=device)
    else:
        bias = temporal_bias(heads, q_len, k_len, period, device, q_offset=q_offset)
    i = torch.arange(q_len, device=device)[:, None] + q_offset
    j = torch.arange(k_len, device=device)[None]
    return bias.masked_fill(((j > i) | (j <= i - window))[None], float("-inf"))


class Attention(nn.Module):
    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.out = nn.Linear(dim, dim)

    def forward(
        self, x: Tensor, bias: Tensor | None = None, cache: KVCache | None = None
    ) -> Tensor:
        """x (B, T, D); bias broadcastable to (B, heads, T, T_keys) (additive, -inf = masked)."""
        B, T, D = x.shape
        q, k, v = self.qkv(x).view(B, T, 3, self.heads, D // self.heads).permute(2, 0, 3, 1, 4)
        if cache is not None:
            k, v = cache.append(k, v)
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=aligned_mask(bias))
        return self.out(y.transpose(1, 2).reshape(B, T, D))


class Block(nn.Module):
    """Pre-LN transformer block (self-attention + MLP), optionally with a cross term added."""

    def __init__(self, dim: int, heads: int, ff: int, gelu: str = "none") -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim)
        # gelu "tanh": the tanh approximation (the official CodeTalker stage 1's)
        self.mlp = nn.Sequential(nn.Linear(dim, ff), nn.GELU(gelu), nn.Linear(ff, dim))

    def forward(
        self,
        x: Tensor,
        bias: Tensor | None = None,
        cache: KVCache | None = None,
        cross: Tensor | None = None,
    ) -> Tensor:
        x = x + self.attn(self.norm1(x), bias, cache)
        if cross is not None:
            x = x + cross
        return x + self.mlp(self.norm2(x))


def padding_bias(mask: Tensor | None, dtype: torch.dtype) -> Tensor | None:
    """(B, T) bool valid-frame mask -> (B, 1, 1, T) additive bias hiding padded keys."""
    if mask is None:
        return None
    bias = torch.zeros(mask.shape, dtype=dtype, device=mask.device)
    return bias.masked_fill(~mask, float("-inf"))[:, None, None, :]


def temporal_bias(
    num_heads: int, q_len: int, k_len: int, period: int, device=None, q_offset: int = 0
) -> Tensor:
    """(heads, q_len, k_len): -slope_h * floor((i - j) / period) for j <= i, -inf above (causal).

    Slopes 1/4, 1/16, 1/64, 1/256, ... (the geometric ALiBi sequence used by FaceFormer/CodeTalker).
    """
    slopes = torch.tensor([2.0 ** (-2 * (h + 1)) for h in range(num_heads)], device=device)
    i = torch.arange(q_len, device=device)[:, None] + q_offset
    j = torch.arange(k_len, device=device)[None]
    dist = torch.div(i - j, period, rounding_mode="floor").float()
    bias = -slopes[:, None, None] * dist[None]
    return bias.masked_fill((j > i)[None], float("-inf"))


def periodic_encoding(
    num_frames: int, dim: int, period: int, device=None, offset: int = 0
) -> Tensor:
    """PPE (FaceFormer): the sinusoid of (t mod period) -> (T, dim)."""
    t = (torch.arange(num_frames, device=device) + offset) % period
    return sinusoid(t, dim)


def folded_linear(
    owner: nn.Module, inner: nn.Linear, outer: nn.Linear, *, int8: bool = False
) -> nn.Module:
    """``outer(inner(x))`` as one linear map, for generation steps: at paper size the product
    reads a V*3-wide dimension (about 0.25 s on 2 cores), so it is kept on ``owner`` (outside its
    state dict) and rebuilt only when one of the four tensors changes (moved or updated in place)."""
    tensors = (inner.weight, inner.bias, outer.weight, outer.bias)
    try:
        key = (int8, *((t.data_ptr(), t._version) for t in tensors))
    except RuntimeError:  # inference tensors keep no version counter: nothing to key a cache on
        key = None
    cached = owner.__dict__.get("_folded")
    if key is not None and cached is not None and cached[0] == key:
        return cached[1]
    with torch.inference_mode(False), torch.no_grad():
        # a plain Linear (its small random init overwritten), not nn.utils.skip_init, whose
        # meta-device pass imports sympy: 0.8 s of a `talkmesh animate` run
        fold = nn.Linear(
            inner.in_features,
            outer.out_features,
            device=inner.weight.device,
            dtype=inner.weight.dtype,
        )
        fold.weight.copy_(outer.weight @ inner.weight)
        fold.bias.copy_(outer.weight @ inner.bias + outer.bias)
    fold.requires_grad_(False)
    if int8:
        fold = int8_layers(fold)
    owner.__dict__["_folded"] = (key, fold)  # a plain attribute: not a submodule
    return fold
