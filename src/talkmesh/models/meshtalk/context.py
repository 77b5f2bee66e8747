"""MeshTalk's autoregressive prior in the official layout (facebookresearch/meshtalk's
``ContextModel``), for models imported from the released weights (``PriorConfig.layout:
official``); talkmesh's own layout is :class:`talkmesh.models.meshtalk.prior.AutoregressivePrior`.

The official prior differs from talkmesh's in its wiring, not in what it models (Eq. 8):

- the code embedding is a head-masked linear map of the one-hot codes (head h reads heads < h),
  not a lookup per head;
- each of the four context layers adds, to a head-masked map of the current frame (heads < h:
  strict in every layer), the audio code and a convolution over the frames t-1 and t-1-d
  (kernel 2, dilation d) of its input; no residual connections;
- the classifier is a head-masked map too (heads < h), not one classifier per head.

Both classes have the same surface (``forward``, ``loss``, ``perplexity``, ``sample``,
``sample_uncached``), so :class:`talkmesh.models.meshtalk.model.MeshTalkModel` uses either.

Axis letters: B batch, T motion frames, H heads, C classes, D width, Da audio width.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.errors import TalkmeshError
from talkmesh.models.mel import LEAKY_SLOPE
from talkmesh.models.meshtalk.prior import (
    AutoregressivePrior,
    PriorConfig,
    PriorLoss,
    draw_codes,
    prior_loss,
)


def build_prior(cfg: PriorConfig) -> nn.Module:
    """The prior of ``cfg.layout``: talkmesh's or the official one."""
    return OfficialContextPrior(cfg) if cfg.layout == "official" else AutoregressivePrior(cfg)


def head_mask(num_heads: int, d_out: int, d_in: int) -> Tensor:
    """(H*Dout, H*Din) 0/1: output head h reads input heads < h (the official mask)."""
    heads = torch.arange(num_heads)
    allowed = heads[None, :] < heads[:, None]
    return allowed.repeat_interleave(d_out, 0).repeat_interleave(d_in, 1).float()


class MaskedHeads(nn.Module):
    """Head-masked linear map of the current frame: (B, T, H*Din) -> (B, T, H*Dout); with
    ``audio_dim`` and ``dilation`` also the audio code and the past frames t-1, t-1-d."""

    def __init__(
        self, num_heads: int, d_in: int, d_out: int, audio_dim: int = 0, dilation: int = 0
    ) -> None:
        super().__init__()
        self.num_heads, self.d_in, self.d_out, self.dilation = num_heads, d_in, d_out, dilation
        H = num_heads
        self.masked = nn.Linear(H * d_in, H * d_out)
        self.register_buffer("mask", head_mask(H, d_out, d_in), persistent=False)
        self.audio = nn.Linear(audio_dim, H * d_out) if audio_dim else None
        # taps[..., 0] reads frame t-1-d, taps[..., 1] frame t-1 (the official Conv1d's kernel)
        self.historic = nn.Conv1d(H * d_in, H * d_out, 2, dilation=dilation) if dilation else None

    @property
    def history(self) -> int:
        """Past input frames this layer reads (0 for the embedding and the classifier)."""
        return self.dilation + 1 if self.historic is not None else 0

    def forward(self, x: Tensor, audio: Tensor | None = None) -> Tensor:
        """Teacher forcing: x (B, T, H*Din), audio (B, T, Da) -> pre-activation (B, T, H*Dout)."""
        out = F.linear(x, self.masked.weight * self.mask, self.masked.bias)
        if self.audio is not None:
            out = out + self.audio(audio)
        if self.historic is not None:
            past = F.pad(x.transpose(1, 2)[:, :, :-1], (self.dilation + 1, 0))
            out = out + self.historic(past).transpose(1, 2)
        return out

    def past_term(self, ring: Tensor, t: int, audio_t: Tensor | None) -> Tensor:
        """Frame t's pre-activation without the current-frame term: bias, audio, past frames.

        ring (B, history, H*Din) holds input frame t' at slot t' % history -> (B, H*Dout).
        """
        out = self.masked.bias.expand(ring.shape[0], -1)
        if self.audio is not None:
            out = out + self.audio(audio_t)
        if self.historic is not None:  # one matmul over [far, near] interleaved as the taps
            far, near = (ring[:, (t - k) % self.history] for k in (self.dilation + 1, 1))
            taps = torch.stack([far, near], dim=-1).flatten(1)
            out = out + F.linear(taps, self.historic.weight.flatten(1), self.historic.bias)
        return out

    def current_term(self, current: Tensor, h: int) -> Tensor:
        """Head h's masked contribution from frame t's inputs current (B, H*Din) -> (B, Dout)."""
        rows = slice(h * self.d_out, (h + 1) * self.d_out)
        n = h * self.d_in
        if n == 0:
            return current.new_zeros(current.shape[0], self.d_out)
        return F.linear(current[:, :n], self.masked.weight[rows, :n])


class OfficialContextPrior(nn.Module):
    """p(c_{t,h} | c_{<t}, c_{t,<h}, audio) (Eq. 8) wired as the official ``ContextModel``:
    masked embedding (one-hot codes -> D per head), one context layer per dilation, masked
    classifier. Audio features come from the expression space (``audio_source: expression``)."""

    def __init__(self, config: PriorConfig) -> None:
        super().__init__()
        if config.audio_source != "expression" or config.kernel_size != 2:
            raise TalkmeshError(
                "meshtalk prior: the official layout reads the expression space's audio "
                "(audio_source: expression) with kernel_size 2"
            )
        self.config = cfg = config
        H, C, D, A = cfg.num_heads, cfg.num_classes, cfg.width, cfg.audio.out_dim
        self.audio_encoder = None
        self.embedding = MaskedHeads(H, C, D)
        self.layers = nn.ModuleList(MaskedHeads(H, D, D, A, d) for d in cfg.dilations)
        self.classifier = MaskedHeads(H, D, C)

    def audio_features(self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int):
        raise TalkmeshError(
            "meshtalk prior: the official layout reads the expression space's audio: "
            "use MeshTalkModel.audio_features"
        )

    def _check(self, audio_features: Tensor, codes: Tensor | None = None) -> None:
        AutoregressivePrior._check(self, audio_features, codes)

    def forward(self, codes: Tensor, audio_features: Tensor) -> Tensor:
        """Teacher forcing: codes (B, T, H), audio_features (B, T, Da) -> logits (B, T, H, C)."""
        self._check(audio_features, codes)
        cfg = self.config
        audio_features = audio_features[:, : codes.shape[1]]
        x = F.one_hot(codes, cfg.num_classes).to(audio_features.dtype).flatten(-2)
        x = self.embedding(x)
        for layer in self.layers:
            x = F.leaky_relu(layer(x, audio_features), LEAKY_SLOPE)
        logits = self.classifier(x)
        return logits.view(*logits.shape[:-1], cfg.num_heads, cfg.num_classes)

    def loss(self, codes: Tensor, audio_features: Tensor, mask: Tensor | None = None) -> PriorLoss:
        """Cross-entropy with teacher forcing (the official step 2)."""
        return prior_loss(self(codes, audio_features), codes, mask)

    @torch.no_grad()
    def perplexity(
        self, codes: Tensor, audio_features: Tensor, mask: Tensor | None = None
    ) -> Tensor:
        return self.loss(codes, audio_features, mask).perplexity

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
        """Codes (B, T, H) for audio_features (B, T, Da), frame by frame, head by head, as the
        official ``ContextModel.sample`` (which keeps each layer's whole history; here each layer
        keeps the last ``history`` frames of its input, so a frame costs the same at any t)."""
        P = AutoregressivePrior._check_sampling(self, audio_features, temperature, top_k, prompt)
        cfg = self.config
        B, T = audio_features.shape[:2]
        H, C = cfg.num_heads, cfg.num_classes
        stages = [self.embedding, *self.layers, self.classifier]
        codes = torch.zeros(B, T, H, dtype=torch.long, device=audio_features.device)
        # inputs of every stage at the current frame; rings of past inputs for the layers
        rings = [
            audio_features.new_zeros(B, max(1, s.history), s.num_heads * s.d_in) for s in stages
        ]
        steps = range(T)
        if progress:
            from tqdm import tqdm

            steps = tqdm(steps, desc="meshtalk prior", unit="frame")
        for t in steps:
            audio_t = audio_features[:, t]
            past = [s.past_term(r, t, audio_t if s.audio else None) for s, r in zip(stages, rings)]
            current = [audio_features.new_zeros(B, s.num_heads * s.d_in) for s in stages]
            for h in range(H):
                for i, stage in enumerate(stages):
                    rows = slice(h * stage.d_out, (h + 1) * stage.d_out)
                    pre = past[i][:, rows] + stage.current_term(current[i], h)
                    if stage is self.classifier:
                        logits = pre
                    else:
                        y = pre if i == 0 else F.leaky_relu(pre, LEAKY_SLOPE)
                        current[i + 1][:, rows] = y
                if t < P:
                    c = prompt[:, t, h]
                else:
                    c = draw_codes(logits, temperature, top_k, argmax, gumbel, generator)
                codes[:, t, h] = c
                current[0][torch.arange(B), h * C + c] = 1.0
            for stage, ring, x in zip(stages, rings, current):
                if stage.history:
                    ring[:, t % stage.history] = x
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
        (frame, head); same draws as :meth:`sample` under the same generator."""
        P = AutoregressivePrior._check_sampling(self, audio_features, temperature, top_k, prompt)
        B, T = audio_features.shape[:2]
        H = self.config.num_heads
        codes = torch.zeros(B, T, H, dtype=torch.long, device=audio_features.device)
        if P:
            codes[:, :P] = prompt
        for t in range(P, T):
            for h in range(H):
                logits = self(codes[:, : t + 1], audio_features[:, : t + 1])[:, t, h]
                codes[:, t, h] = draw_codes(logits, temperature, top_k, argmax, gumbel, generator)
        return codes
