"""MeshTalk's autoregressive prior over expression codes (Richard et al., ICCV 2021, Sec. 3.2, Fig. 3).

:class:`AutoregressivePrior`: masked causal temporal convolutions over (time, head) conditioned on
audio, Eq. 8; ``forward`` (teacher-forced logits), ``sample`` (incremental: per-layer ring buffers of
past activations, constant cost per frame), ``sample_uncached`` (reference that recomputes the whole
history), ``perplexity`` (Eq. 9). Its config :class:`PriorConfig` and the presets of
:func:`prior_config` match :func:`talkmesh.models.meshtalk.model.meshtalk_config`'s.

Axis letters: B batch, S audio samples, T motion frames, H heads, C classes, D width.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.constants import MOTION_FPS
from talkmesh.errors import TalkmeshError
from talkmesh.models.mel import LEAKY_SLOPE, MelAudioEncoder, MelConfig

PRESETS = ("paper", "released", "small")


@dataclass(frozen=True)
class PriorConfig:
    """The autoregressive prior over codes (paper Sec. 3.2, Fig. 3).

    Each layer sees ``kernel_size - 1`` past frames at its dilation plus the current frame through a
    head mask; receptive field ``receptive_field`` frames (16 for kernel 2 and dilations 1, 2, 4, 8).
    """

    num_heads: int = 16
    num_classes: int = 128
    width: int = 64  # D per head
    dilations: tuple[int, ...] = (1, 2, 4, 8)
    kernel_size: int = 2
    audio: MelConfig = MelConfig(layer_norm=True)
    fps: float = MOTION_FPS
    # "own": the prior's own mel encoder (``audio``, causal with its look-ahead, paper Eq. 8);
    # "expression": the trained expression space's audio features (as the official code does)
    audio_source: str = "own"
    # "talkmesh" (AutoregressivePrior) or "official" (the released ContextModel's wiring:
    # talkmesh.models.meshtalk.context.OfficialContextPrior; on in imported models)
    layout: str = "talkmesh"

    def __post_init__(self) -> None:
        if self.num_heads < 1 or self.num_classes < 2 or self.width < 1:
            raise TalkmeshError(
                "meshtalk prior config: num_heads >= 1, num_classes >= 2, width >= 1 needed"
            )
        if self.kernel_size < 2 or not self.dilations or min(self.dilations) < 1:
            raise TalkmeshError(
                "meshtalk prior config: kernel_size must be >= 2 and dilations >= 1"
            )
        if self.fps <= 0:
            raise TalkmeshError("meshtalk prior config: fps must be positive")
        if self.audio_source not in ("own", "expression"):
            raise TalkmeshError("meshtalk prior config: audio_source must be own or expression")
        if self.layout not in ("talkmesh", "official"):
            raise TalkmeshError("meshtalk prior config: layout must be talkmesh or official")

    @property
    def receptive_field(self) -> int:
        return 1 + (self.kernel_size - 1) * sum(self.dilations)


def prior_config(preset: str, fps: float = MOTION_FPS) -> PriorConfig:
    """The prior matching :func:`meshtalk_config`'s preset (same H and C)."""
    if preset == "paper":
        return PriorConfig(num_heads=64, num_classes=128, width=32, fps=fps)
    if preset == "released":
        return PriorConfig(num_heads=16, num_classes=128, width=64, fps=fps)
    if preset == "small":
        return PriorConfig(
            num_heads=8,
            num_classes=32,
            width=32,
            audio=MelConfig(width=64, out_dim=64, layer_norm=True),
            fps=fps,
        )
    raise TalkmeshError(f"unknown meshtalk preset '{preset}': choose one of {', '.join(PRESETS)}")


def draw_codes(
    logits: Tensor,
    temperature: float,
    top_k: int | None,
    argmax: bool,
    gumbel: bool,
    generator: torch.Generator | None,
) -> Tensor:
    """(B, C) logits -> (B,) class ids: argmax, or a draw from softmax(logits / temperature)
    (top-k restricted). ``gumbel``: the official draw, argmax(log-softmax + Gumbel noise) with one
    uniform per class, so a seed gives the official code's draws under ``torch.manual_seed``."""
    if argmax:
        return logits.argmax(-1)
    logits = logits / temperature
    if top_k is not None and top_k < logits.shape[-1]:
        kth = torch.topk(logits, top_k, dim=-1).values[:, -1:]
        logits = logits.masked_fill(logits < kth, float("-inf"))
    if gumbel:
        u = torch.rand(logits.shape, generator=generator, device=logits.device)
        noise = -torch.log(-torch.log(u.clamp(min=1e-10, max=1.0)))
        return (torch.log_softmax(logits, dim=-1) + noise.to(logits.dtype)).argmax(-1)
    probs = torch.softmax(logits.double(), dim=-1)
    return torch.multinomial(probs, 1, generator=generator)[:, 0]


class PriorLoss(NamedTuple):
    """loss: mean cross-entropy (nats); perplexity: exp(loss) (Eq. 9); accuracy: argmax hit rate."""

    loss: Tensor
    perplexity: Tensor
    accuracy: Tensor


def prior_loss(logits: Tensor, codes: Tensor, mask: Tensor | None = None) -> PriorLoss:
    """logits (B, T, H, C), codes (B, T, H), mask (B, T) bool or None -> :class:`PriorLoss`."""
    nll = F.cross_entropy(logits.flatten(0, 2), codes.flatten(), reduction="none")
    hit = (logits.argmax(-1) == codes).flatten().to(nll.dtype)
    if mask is None:
        weight = torch.ones_like(nll)
    else:
        weight = mask[:, :, None].expand_as(codes).flatten().to(nll.dtype)
    count = weight.sum().clamp(min=1.0)
    loss = (nll * weight).sum() / count
    return PriorLoss(loss, loss.detach().exp(), (hit * weight).sum() / count)


class MaskedTemporalLayer(nn.Module):
    """One masked causal layer over (time, head), paper Fig. 3.

    out(t, h) = b + A(t) + sum_k P_k x(t - k*d, all heads) + M x(t, heads < h), or heads <= h when
    ``include_current``: the first layer must not see c_{t,h} itself; later layers' inputs at (t, h)
    only carry c_{t,<h}, so they may. x is (B, T, H*Din) with heads as contiguous blocks.
    """

    def __init__(
        self,
        num_heads: int,
        d_in: int,
        d_out: int,
        audio_dim: int,
        taps: int,
        dilation: int,
        include_current: bool,
    ) -> None:
        super().__init__()
        self.num_heads, self.d_in, self.d_out = num_heads, d_in, d_out
        self.dilation, self.include_current = dilation, include_current
        H = num_heads
        self.past = nn.ParameterList(
            nn.Parameter(torch.randn(H * d_out, H * d_in) / math.sqrt(H * d_in * taps))
            for _ in range(taps)
        )
        self.current = nn.Parameter(torch.randn(H * d_out, H * d_in) / math.sqrt(H * d_in))
        self.audio = nn.Linear(audio_dim, H * d_out)
        heads = torch.arange(H)
        allowed = (
            heads[None, :] <= heads[:, None] if include_current else heads[None, :] < heads[:, None]
        )
        mask = allowed.repeat_interleave(d_out, 0).repeat_interleave(d_in, 1).float()
        self.register_buffer("mask", mask, persistent=False)

    @property
    def history(self) -> int:
        """Past frames this layer reads."""
        return len(self.past) * self.dilation

    def forward(self, x: Tensor, audio: Tensor) -> Tensor:
        """x (B, T, H*Din), audio (B, T, Da) -> pre-activation (B, T, H*Dout)."""
        out = self.audio(audio) + F.linear(x, self.current * self.mask)
        for k, weight in enumerate(self.past, start=1):
            shift = k * self.dilation
            past = F.pad(x, (0, 0, shift, 0))[:, : x.shape[1]]
            out = out + F.linear(past, weight)
        return out

    def past_term(self, ring: Tensor, t: int, audio_t: Tensor) -> Tensor:
        """The part of frame t's pre-activation that depends only on earlier frames and audio.

        ring (B, history, H*Din) holds frame t' at slot t' % history -> (B, H*Dout).
        """
        out = audio_t
        for k, weight in enumerate(self.past, start=1):
            out = out + F.linear(ring[:, (t - k * self.dilation) % self.history], weight)
        return out

    def current_term(self, current: Tensor, h: int) -> Tensor:
        """Head h's masked contribution from frame t's inputs current (B, H*Din) -> (B, Dout)."""
        n = (h + 1 if self.include_current else h) * self.d_in
        rows = slice(h * self.d_out, (h + 1) * self.d_out)
        if n == 0:
            return current.new_zeros(current.shape[0], self.d_out)
        return F.linear(current[:, :n], self.current[rows, :n])


class AutoregressivePrior(nn.Module):
    """p(c_{t,h} | c_{<t}, c_{t,<h}, audio) (Eq. 8): code embeddings, masked causal temporal layers
    with dilations (1, 2, 4, 8), audio added in every layer, a classifier per head.

    Audio look-ahead is ``config.audio.lookahead_ms`` (the paper states 100 ms); features come from
    :meth:`audio_features` (or any (B, T, audio.out_dim) speech features).
    """

    def __init__(self, config: PriorConfig) -> None:
        super().__init__()
        self.config = cfg = config
        H, C, D = cfg.num_heads, cfg.num_classes, cfg.width
        self.audio_encoder = (
            MelAudioEncoder(cfg.audio, cfg.fps) if cfg.audio_source == "own" else None
        )
        self.embedding = nn.Embedding(H * C, D)  # a separate table per head
        self.layers = nn.ModuleList(
            MaskedTemporalLayer(H, D, D, cfg.audio.out_dim, cfg.kernel_size - 1, d, i > 0)
            for i, d in enumerate(cfg.dilations)
        )
        self.head_weight = nn.Parameter(torch.randn(H, C, D) / math.sqrt(D))
        self.head_bias = nn.Parameter(torch.zeros(H, C))
        self.register_buffer("head_offsets", torch.arange(H) * C, persistent=False)

    def audio_features(
        self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int
    ) -> Tensor:
        """(B, S) -> (B, T, Da) conditioning features (own encoder; with ``audio_source:
        expression`` the caller passes the expression space's: MeshTalkModel.audio_features)."""
        if self.audio_encoder is None:
            raise TalkmeshError(
                "meshtalk prior: audio_source is expression: use MeshTalkModel.audio_features"
            )
        return self.audio_encoder(audio, audio_lengths, num_frames)

    def _check(self, audio_features: Tensor, codes: Tensor | None = None) -> None:
        cfg = self.config
        if audio_features.ndim != 3 or audio_features.shape[-1] != cfg.audio.out_dim:
            raise TalkmeshError(
                f"meshtalk prior: audio features must be (B, T, {cfg.audio.out_dim}), "
                f"got {tuple(audio_features.shape)}"
            )
        if codes is not None:
            if codes.ndim != 3 or codes.shape[-1] != cfg.num_heads or codes.is_floating_point():
                raise TalkmeshError(
                    f"meshtalk prior: codes must be int (B, T, {cfg.num_heads}), got {tuple(codes.shape)}"
                )
            if codes.numel() and (int(codes.min()) < 0 or int(codes.max()) >= cfg.num_classes):
                raise TalkmeshError(f"meshtalk prior: codes must lie in [0, {cfg.num_classes})")
            if (
                codes.shape[0] != audio_features.shape[0]
                or codes.shape[1] > audio_features.shape[1]
            ):
                raise TalkmeshError(
                    "meshtalk prior: codes need audio features for the same batch and frames"
                )

    def _embed(self, codes: Tensor) -> Tensor:
        """(B, T, H) -> (B, T, H*D)."""
        return self.embedding(codes + self.head_offsets).flatten(-2)

    def _classify(self, x: Tensor) -> Tensor:
        """(B, T, H*D) -> (B, T, H, C)."""
        x = x.view(*x.shape[:-1], self.config.num_heads, self.config.width)
        return torch.einsum("bthd,hcd->bthc", x, self.head_weight) + self.head_bias

    def _layer_inputs(self, codes: Tensor, audio_features: Tensor) -> list[Tensor]:
        """Teacher-forced activations: the input of every layer and the classifier's, (B, T, H*D)."""
        x = self._embed(codes)
        inputs = [x]
        for i, layer in enumerate(self.layers):
            y = F.leaky_relu(layer(x, audio_features), LEAKY_SLOPE)
            x = y if i == 0 else x + y  # no residual from the first layer's input: it holds c_{t,h}
            inputs.append(x)
        return inputs

    def forward(self, codes: Tensor, audio_features: Tensor) -> Tensor:
        """Teacher forcing: codes (B, T, H), audio_features (B, T, Da) -> logits (B, T, H, C)."""
        self._check(audio_features, codes)
        audio_features = audio_features[:, : codes.shape[1]]
        return self._classify(self._layer_inputs(codes, audio_features)[-1])

    def loss(self, codes: Tensor, audio_features: Tensor, mask: Tensor | None = None) -> PriorLoss:
        """Cross-entropy with teacher forcing (Sec. 3.2)."""
        return prior_loss(self(codes, audio_features), codes, mask)

    @torch.no_grad()
    def perplexity(
        self, codes: Tensor, audio_features: Tensor, mask: Tensor | None = None
    ) -> Tensor:
        """Eq. 9: p(c | a)^(-1 / (T*H)) over all valid frames of the batch -> ()."""
        return self.loss(codes, audio_features, mask).perplexity

    # -- sampling ---------------------------------------------------------------------------------

    def _check_sampling(
        self, audio_features: Tensor, temperature: float, top_k: int | None, prompt: Tensor | None
    ) -> int:
        self._check(audio_features, prompt)
        if temperature <= 0:
            raise TalkmeshError(
                "meshtalk prior: temperature must be positive (use argmax=True for greedy)"
            )
        if top_k is not None and top_k < 1:
            raise TalkmeshError("meshtalk prior: top_k must be at least 1")
        return 0 if prompt is None else prompt.shape[1]

    @torch.inference_mode()
    def sample(
        self,
        audio_features: Tensor,
        *,
        temperature: float = 1.0,
        top_k: int | None = None,
        argmax: bool = False,
        gumbel: bool = False,
        generator: torch.Generator | None = None,
        prompt: Tensor | None = None,
        progress: bool = False,
    ) -> Tensor:
        """Codes (B, T, H) for audio_features (B, T, Da), head by head, frame by frame.

        Each layer keeps a ring buffer of its last ``history`` input frames, so frame t costs the same
        at any t: the past terms of all heads once per frame, then per head only its masked row.
        ``prompt`` (B, P, H) fixes the first P frames (prefilled in one teacher-forced pass).
        """
        P = self._check_sampling(audio_features, temperature, top_k, prompt)
        cfg = self.config
        B, T = audio_features.shape[:2]
        H, D = cfg.num_heads, cfg.width
        codes = torch.zeros(B, T, H, dtype=torch.long, device=audio_features.device)
        audio_terms = [
            layer.audio(audio_features) for layer in self.layers
        ]  # (B, T, H*D) each: non-autoregressive, computed once
        rings = [audio_features.new_zeros(B, layer.history, H * D) for layer in self.layers]
        if P:
            codes[:, :P] = prompt
            inputs = self._layer_inputs(prompt, audio_features[:, :P])
            for layer, ring, x in zip(self.layers, rings, inputs):
                for t in range(max(0, P - layer.history), P):
                    ring[:, t % layer.history] = x[:, t]
        steps = range(P, T)
        if progress:
            from tqdm import tqdm

            steps = tqdm(steps, desc="meshtalk prior", unit="frame")
        for t in steps:
            past = [
                layer.past_term(ring, t, audio[:, t])
                for layer, ring, audio in zip(self.layers, rings, audio_terms)
            ]
            current = [audio_features.new_zeros(B, H * D) for _ in range(len(self.layers) + 1)]
            for h in range(H):
                block = slice(h * D, (h + 1) * D)
                for i, layer in enumerate(self.layers):
                    pre = past[i][:, block] + layer.current_term(current[i], h)
                    y = F.leaky_relu(pre, LEAKY_SLOPE)
                    current[i + 1][:, block] = y if i == 0 else current[i][:, block] + y
                logits = F.linear(current[-1][:, block], self.head_weight[h]) + self.head_bias[h]
                c = draw_codes(logits, temperature, top_k, argmax, gumbel, generator)
                codes[:, t, h] = c
                current[0][:, block] = self.embedding(c + h * cfg.num_classes)
            for layer, ring, x in zip(self.layers, rings, current):
                ring[:, t % layer.history] = x
        return codes

    @torch.inference_mode()
    def sample_uncached(
        self,
        audio_features: Tensor,
        *,
        temperature: float = 1.0,
        top_k: int | None = None,
        argmax: bool = False,
        gumbel: bool = False,
        generator: torch.Generator | None = None,
        prompt: Tensor | None = None,
    ) -> Tensor:
        """Reference sampler: the teacher-forced :meth:`forward` over the whole history for every
        (frame, head). Same draws as :meth:`sample` under the same generator; cost grows with T."""
        P = self._check_sampling(audio_features, temperature, top_k, prompt)
        B, T = audio_features.shape[:2]
        codes = torch.zeros(
            B, T, self.config.num_heads, dtype=torch.long, device=audio_features.device
        )
        if P:
            codes[:, :P] = prompt
        for t in range(P, T):
            for h in range(self.config.num_heads):
                logits = self(codes[:, : t + 1], audio_features[:, : t + 1])[:, t, h]
                codes[:, t, h] = draw_codes(logits, temperature, top_k, argmax, gumbel, generator)
        return codes
