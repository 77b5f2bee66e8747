"""The decoder layer and positional encoding of the official FaceFormer and CodeTalker code, for
models imported from the papers' released weights (``talkmesh import-checkpoint``).

* :class:`PostNormDecoderLayer`: the computation of ``torch.nn.TransformerDecoderLayer`` as the
  official stage 2 uses it (post-norm, ReLU, dropout 0.1, ``batch_first``), with the same
  parameter names (``self_attn.in_proj_weight``, ``multihead_attn.*``, ``linear1``, ``norm1``...)
  so released tensors map one to one. Unlike torch's layer it takes an additive self-attention
  bias, a :class:`~talkmesh.models.layers.KVCache` for one-frame steps, and the audio tokens
  aligned with each frame as ``(B, T, k, D)``: the official alignment mask lets frame t attend to
  its own k tokens only (VOCASET k = 1, BIWI k = 2), which is this per-frame attention without a
  (T, T*k) matrix.
* :func:`interleaved_encoding`: the official periodic positional encoding (sin in even, cos in odd
  channels); talkmesh's own models put the sines first (:func:`~talkmesh.models.layers.sinusoid`).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.models.layers import aligned_mask


def interleaved_encoding(
    num_frames: int, dim: int, period: int, device=None, offset: int = 0
) -> Tensor:
    """(T, dim) periodic positional encoding of frames ``offset..offset+T-1``: channel 2i is
    sin((t mod period) w_i), channel 2i+1 cos(...), w_i = 10000^(-2i/dim) (FaceFormer's PPE)."""
    t = ((torch.arange(num_frames, device=device) + offset) % period).float()[:, None]
    freqs = torch.exp(torch.arange(0, dim, 2, device=device).float() * (-math.log(10000.0) / dim))
    out = torch.zeros(num_frames, dim, device=device)
    out[:, 0::2] = torch.sin(t * freqs)
    out[:, 1::2] = torch.cos(t * freqs)
    return out


def _heads(x: Tensor, heads: int) -> Tensor:
    """(..., D) -> (..., heads, D / heads)."""
    return x.view(*x.shape[:-1], heads, x.shape[-1] // heads)


class PostNormDecoderLayer(nn.Module):
    """x = norm1(x + SelfAttn(x)); x = norm2(x + AlignedCrossAttn(x, audio)); x = norm3(x + FF(x))."""

    def __init__(self, dim: int, heads: int, ff: int, dropout: float = 0.1) -> None:
        super().__init__()
        self.heads, self.p = heads, dropout
        # parameter containers with torch's names; the attention itself is computed below
        self.self_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.multihead_attn = nn.MultiheadAttention(dim, heads, dropout=dropout, batch_first=True)
        self.linear1 = nn.Linear(dim, ff)
        self.linear2 = nn.Linear(ff, dim)
        self.norm1 = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)
        self.norm3 = nn.LayerNorm(dim)
        self.dropout = nn.Dropout(dropout)

    def _self(self, x: Tensor, bias: Tensor | None, cache) -> Tensor:
        """x (B, T, D), bias broadcastable to (B, heads, T, T_keys) -> (B, T, D)."""
        B, T, D = x.shape
        a = self.self_attn
        q, k, v = F.linear(x, a.in_proj_weight, a.in_proj_bias).chunk(3, dim=-1)
        q, k, v = (_heads(t, self.heads).transpose(1, 2) for t in (q, k, v))
        if cache is not None:
            k, v = cache.append(k, v)
        p = self.p if self.training else 0.0
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=aligned_mask(bias), dropout_p=p)
        return a.out_proj(y.transpose(1, 2).reshape(B, T, D))

    def _aligned(self, x: Tensor, audio: Tensor) -> Tensor:
        """x (B, T, D), audio (B, T, k, D): frame t attends to its own k tokens -> (B, T, D)."""
        a = self.multihead_attn
        wq, wk, wv = a.in_proj_weight.chunk(3)
        bq, bk, bv = a.in_proj_bias.chunk(3)
        q = _heads(F.linear(x, wq, bq), self.heads)  # (B, T, h, dh)
        k = _heads(F.linear(audio, wk, bk), self.heads)  # (B, T, k, h, dh)
        v = _heads(F.linear(audio, wv, bv), self.heads)
        scores = torch.einsum("bthd,btkhd->bthk", q, k) / math.sqrt(q.shape[-1])
        w = F.dropout(scores.softmax(-1), self.p, self.training)
        y = torch.einsum("bthk,btkhd->bthd", w, v)
        return a.out_proj(y.flatten(2))

    def forward(
        self, x: Tensor, bias: Tensor | None = None, cache=None, audio: Tensor | None = None
    ) -> Tensor:
        """x (B, T, D); bias (additive, -inf = hidden) broadcastable to (B, heads, T, T_keys);
        cache: a KVCache for stepwise decoding; audio (B, T, k, D) each frame's aligned tokens."""
        if audio is None or audio.shape[:2] != x.shape[:2]:
            raise ValueError("audio must be (B, T, k, D) aligned with x (B, T, D)")
        x = self.norm1(x + F.dropout(self._self(x, bias, cache), self.p, self.training))
        x = self.norm2(x + F.dropout(self._aligned(x, audio), self.p, self.training))
        ff = self.linear2(self.dropout(F.relu(self.linear1(x))))
        return self.norm3(x + F.dropout(ff, self.p, self.training))
