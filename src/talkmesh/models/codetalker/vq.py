"""CodeTalker stage 1 (Xing et al., CVPR 2023, Sec. 3.1, Table 4): a transformer VQ-VAE over
facial motion (vertices - template). Each frame becomes H face-component tokens of C dims, each
snapped to one of N codebook entries (:class:`Quantizer`, ``quantized, codes = q(z)`` and its inverse
``q.lookup(codes)``).

Axis letters: B batch, T frames, V vertices, H face components, C code width, N codebook size.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.errors import TalkmeshError
from talkmesh.models.layers import Block, KVCache, padding_bias, sinusoid, window_bias


@dataclass(frozen=True)
class VQConfig:
    """Stage 1 (Table 4). VOCASET: H=16, C=64; BIWI: H=8, C=128; N=256 codes, P=1 for both."""

    num_vertices: int
    hidden: int = 1024
    layers: int = 6
    heads: int = 8
    ff: int = 1536
    components: int = 16  # H: face-component tokens per frame
    code_dim: int = 64  # C
    codebook_size: int = 256  # N
    temporal_unit: int = 1  # P: frames per token (P > 1 pools P frames into one token)
    instance_norm: bool = False  # the paper's IN over time (Table 5); breaks on 1 frame
    beta: float = 0.25  # commitment weight
    loss: str = "l1"  # reconstruction term: "l1" (the paper) or "mse" (keeps rare motion such as
    # blinks, which an L1 fit treats as outliers), in units of each coordinate's spread
    ema: bool = False  # exponential-moving-average codebook updates instead of the codebook loss
    ema_decay: float = 0.99
    dead_code_restart: bool = False  # re-seed unused codes from the batch (EMA mode)
    codebook_from_data: bool = False  # start the codebook at the first batch's encoder outputs
    # (off: on the synthetic corpus it collapsed usage to 13 of 256 codes)
    causal: bool = False  # streaming decoder: causal conv, causal attention over the last
    # ``causal_window`` frames with relative (ALiBi) positions instead of absolute ones, so frame t
    # never depends on later codes and a cached step equals the full pass (not in the paper)
    causal_window: int = 64
    # official-exact options (on in imported releases, docs/guide/official.md)
    gelu_tanh: bool = False  # the official blocks' tanh-approximated GELU
    final_norm: bool = True  # a LayerNorm after the last block (the official code has none)
    frame_positions: bool = True  # a sinusoid per frame; the official code adds one vector to
    # every frame (folded into ``mid``'s bias on import)

    def __post_init__(self) -> None:
        for name in (
            "num_vertices",
            "hidden",
            "heads",
            "ff",
            "components",
            "code_dim",
            "codebook_size",
            "temporal_unit",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"vq.{name} must be at least 1")
        if self.layers < 0:
            raise ValueError("vq.layers must be >= 0")
        if self.hidden % self.heads:
            raise ValueError("vq.hidden must be divisible by vq.heads")
        if self.loss not in ("l1", "mse"):
            raise ValueError(f"vq.loss must be l1 or mse, got {self.loss!r}")
        if self.causal and (self.instance_norm or self.temporal_unit != 1):
            raise ValueError("vq.causal needs instance_norm: false and temporal_unit: 1")
        if self.causal_window < 1:
            raise ValueError("vq.causal_window must be at least 1")


SCALE_FLOOR = 0.05  # smallest per-coordinate motion scale, relative to the largest


class Quantized(NamedTuple):
    z_q: Tensor  # (B, T, H, C) straight-through quantised features
    codes: Tensor  # (B, T, H) int64
    loss: Tensor  # () codebook + commitment loss


class Quantizer(nn.Module):
    """Nearest-neighbour quantisation into N codes: ``z_q, codes, loss = vq(z)``; ``vq.lookup(codes)``."""

    def __init__(
        self,
        size: int,
        dim: int,
        beta: float,
        ema: bool = False,
        decay: float = 0.99,
        restart: bool = False,
        init_from_data: bool = False,
    ):
        super().__init__()
        self.codebook = nn.Parameter(
            torch.empty(size, dim).uniform_(-1 / size, 1 / size), requires_grad=not ema
        )
        self.beta, self.ema, self.decay, self.restart = beta, ema, decay, restart
        self.register_buffer("usage", torch.zeros(size))  # running code counts, for logging
        # The codebook starts as encoder outputs of the first training batch: a codebook far from
        # them (the usual tiny uniform init) leaves every frame on the same few codes for hundreds
        # of steps while the decoder learns only the mean motion.
        self.register_buffer("initialised", torch.tensor(not init_from_data))
        if ema:
            self.register_buffer("ema_count", torch.ones(size))
            self.register_buffer("ema_sum", self.codebook.detach().clone())

    def forward(self, z: Tensor, mask: Tensor | None = None) -> Quantized:
        """z (B, T, H, C); mask (B, T) -> :class:`Quantized`."""
        flat = z.reshape(-1, z.shape[-1])
        if self.training and not bool(self.initialised):
            self._init_from(
                flat.detach() if mask is None else z.detach()[mask].reshape(-1, z.shape[-1])
            )
        dist = (
            flat.pow(2).sum(1, keepdim=True)
            - 2 * flat @ self.codebook.t()
            + self.codebook.pow(2).sum(1)[None]
        )
        codes = dist.argmin(1)
        q = self.codebook[codes].view_as(z)
        weight = None
        if mask is not None:
            weight = mask[:, :, None, None].expand(*z.shape[:3], 1).to(z.dtype)
        if self.training:
            self._update(flat.detach(), codes, None if weight is None else weight.reshape(-1))
        commit = _masked_mse(z, q.detach(), weight)
        loss = (
            self.beta * commit
            if self.ema
            else _masked_mse(q, z.detach(), weight) + self.beta * commit
        )
        z_q = z + (q - z).detach()  # straight-through estimator
        return Quantized(z_q, codes.view(z.shape[:3]), loss)

    @torch.no_grad()
    def _init_from(self, vectors: Tensor) -> None:
        if not len(vectors):
            return
        pick = torch.randint(len(vectors), (len(self.codebook),), device=vectors.device)
        self.codebook.data.copy_(vectors[pick] + 1e-3 * torch.randn_like(self.codebook))
        if self.ema:
            self.ema_sum.copy_(self.codebook.data)
        self.initialised.fill_(True)

    def lookup(self, codes: Tensor) -> Tensor:
        """codes (..., H) int64 -> (..., H, C) codebook vectors."""
        return self.codebook[codes]

    @torch.no_grad()
    def _update(self, flat: Tensor, codes: Tensor, weight: Tensor | None) -> None:
        w = torch.ones(len(codes), device=flat.device) if weight is None else weight
        counts = torch.zeros_like(self.usage).index_add_(0, codes, w)
        self.usage.mul_(0.99).add_(counts)
        if not self.ema:
            return
        sums = torch.zeros_like(self.ema_sum).index_add_(0, codes, flat * w[:, None])
        self.ema_count.mul_(self.decay).add_(counts, alpha=1 - self.decay)
        self.ema_sum.mul_(self.decay).add_(sums, alpha=1 - self.decay)
        self.codebook.data.copy_(self.ema_sum / self.ema_count.clamp(min=1e-5)[:, None])
        if self.restart:
            dead = self.ema_count < 1e-3
            if dead.any() and len(flat):
                pick = torch.randint(len(flat), (int(dead.sum()),), device=flat.device)
                self.codebook.data[dead] = flat[pick]
                self.ema_sum[dead] = flat[pick]
                self.ema_count[dead] = 1.0

    def perplexity(self) -> float:
        p = self.usage / self.usage.sum().clamp(min=1e-8)
        return float(torch.exp(-(p * (p + 1e-12).log()).sum()))

    def used_codes(self, threshold: float = 1e-3) -> int:
        return int((self.usage > threshold * self.usage.sum()).sum()) if self.usage.sum() > 0 else 0


def _masked_mse(a: Tensor, b: Tensor, weight: Tensor | None) -> Tensor:
    err = (a - b).pow(2)
    if weight is None:
        return err.mean()
    return (err * weight).sum() / (weight.sum() * a.shape[-1]).clamp(min=1.0)


def hold_last_frame(x: Tensor, mask: Tensor | None) -> Tensor:
    """(B, T, D) with padded frames replaced by each sequence's last valid frame, so the convs
    see the same replicate padding as the sequence alone (padded batch = single samples)."""
    if mask is None:
        return x
    lengths = mask.sum(1).clamp(min=1)
    idx = torch.minimum(torch.arange(x.shape[1], device=x.device)[None], (lengths - 1)[:, None])
    return x.gather(1, idx[:, :, None].expand_as(x))


class TemporalConv(nn.Module):
    """Conv1d over time, kernel 5, replicate padding (Table 4); optional InstanceNorm. ``causal``
    pads on the left only, so output t reads inputs t-4..t."""

    def __init__(
        self, dim: int, instance_norm: bool, stride: int = 1, causal: bool = False
    ) -> None:
        super().__init__()
        self.conv = nn.Conv1d(dim, dim, 5, stride=stride)
        self.norm = nn.InstanceNorm1d(dim, affine=False) if instance_norm else None
        self.padding = (4, 0) if causal else (2, 2)
        self.linear: nn.Module | None = None  # the conv as an int8 matrix (quantize_int8)

    def forward(self, x: Tensor) -> Tensor:
        """(B, T, D) -> (B, T / stride, D)."""
        y = self.conv(F.pad(x.transpose(1, 2), self.padding, mode="replicate"))
        y = F.leaky_relu(y, 0.2)
        if self.norm is not None:
            y = self.norm(y)
        return y.transpose(1, 2)

    def step(self, windows: Tensor) -> Tensor:
        """K output frames from the input frames under the kernel, windows (B, K, D, 5) as
        ``x.unfold(1, 5, 1)`` gives them -> (B, K, D): the convolution as one matrix product (no
        instance norm: generation steps have none). The caller pads as the full pass would."""
        windows = windows.flatten(2)  # (B, K, D * 5) in the weight's (in, k) order
        if self.linear is not None:
            y = self.linear(windows)
        else:
            y = F.linear(windows, self.conv.weight.flatten(1), self.conv.bias)
        return F.leaky_relu(y, 0.2)


def _blocks(cfg: VQConfig) -> nn.ModuleList:
    gelu = "tanh" if cfg.gelu_tanh else "none"
    return nn.ModuleList(Block(cfg.hidden, cfg.heads, cfg.ff, gelu) for _ in range(cfg.layers))


class MotionEncoder(nn.Module):
    def __init__(self, cfg: VQConfig) -> None:
        super().__init__()
        self.inp = nn.Linear(cfg.num_vertices * 3, cfg.hidden)
        self.conv = TemporalConv(cfg.hidden, cfg.instance_norm, cfg.temporal_unit)
        self.mid = nn.Linear(cfg.hidden, cfg.hidden)
        self.blocks = _blocks(cfg)
        self.norm = nn.LayerNorm(cfg.hidden) if cfg.final_norm else nn.Identity()
        self.out = nn.Linear(cfg.hidden, cfg.components * cfg.code_dim)
        self.cfg = cfg
        # per-coordinate motion normalisation (set from training data; a buffer, so it travels with
        # the weights): lips and nearly static vertices weigh alike in the L1 loss
        self.register_buffer("scale", torch.ones(cfg.num_vertices * 3))

    def forward(self, motion: Tensor, mask: Tensor | None = None) -> Tensor:
        """motion (B, T, V*3) -> z (B, T/P, H, C)."""
        x = self.conv(hold_last_frame(F.leaky_relu(self.inp(motion / self.scale), 0.2), mask))
        x = self.mid(x)
        if self.cfg.frame_positions:
            x = x + sinusoid(torch.arange(x.shape[1], device=x.device), x.shape[-1])
        bias = padding_bias(
            mask[:, :: self.cfg.temporal_unit] if mask is not None else None, x.dtype
        )
        for block in self.blocks:
            x = block(x, bias)
        return self.out(self.norm(x)).view(*x.shape[:2], self.cfg.components, self.cfg.code_dim)


class MotionDecoder(nn.Module):
    def __init__(self, cfg: VQConfig) -> None:
        super().__init__()
        self.inp = nn.Linear(cfg.components * cfg.code_dim, cfg.hidden)
        self.conv = TemporalConv(cfg.hidden, cfg.instance_norm, causal=cfg.causal)
        self.mid = nn.Linear(cfg.hidden, cfg.hidden)
        self.blocks = _blocks(cfg)
        self.norm = nn.LayerNorm(cfg.hidden) if cfg.final_norm else nn.Identity()
        self.out = nn.Linear(cfg.hidden, cfg.num_vertices * 3)
        self.cfg = cfg
        self.register_buffer("scale", torch.ones(cfg.num_vertices * 3))

    def hidden(
        self, z_q: Tensor, mask: Tensor | None = None, offset: int = 0, face: Tensor | None = None
    ) -> Tensor:
        """z_q (B, T', H, C) -> (B, T, hidden) before the output map (T = T' * P); ``offset`` is
        the position of the first frame (for windows of a longer sequence); ``face`` (B, hidden)
        is added to every frame's input (the head's term, ``CodeTalker.decoder_face``)."""
        if self.cfg.instance_norm and z_q.shape[1] * self.cfg.temporal_unit == 1 and mask is None:
            # instance statistics over one frame do not exist: it is decoded as two copies of
            # itself, as the official generation decodes frame 0
            return self.hidden(z_q.expand(-1, 2, -1, -1), None, offset, face)[:, :1]
        x = self.inputs(z_q, face)
        if self.cfg.temporal_unit > 1:
            x = x.repeat_interleave(self.cfg.temporal_unit, dim=1)
        x = self.mid(self.conv(hold_last_frame(x, mask)))
        bias = padding_bias(mask, x.dtype)
        if self.cfg.causal:
            T = x.shape[1]
            band = window_bias(self.cfg.heads, T, T, self.cfg.causal_window, 1, x.device)
            bias = band[None] if bias is None else bias + band
        elif self.cfg.frame_positions:
            x = x + sinusoid(
                torch.arange(offset, offset + x.shape[1], device=x.device), x.shape[-1]
            )
        for block in self.blocks:
            x = block(x, bias)
        return self.norm(x)

    def inputs(self, z_q: Tensor, face: Tensor | None = None) -> Tensor:
        """z_q (B, T', H, C) -> (B, T', hidden): the input map, plus ``face`` (B, hidden), the
        head's term (``CodeTalker.decoder_face``), where given. Every decoding path starts here."""
        x = self.inp(z_q.flatten(2))
        return x if face is None else x + face[:, None]

    def forward(
        self, z_q: Tensor, mask: Tensor | None = None, offset: int = 0, face: Tensor | None = None
    ) -> Tensor:
        """z_q (B, T', H, C) -> motion (B, T, V*3); ``face`` (B, hidden) as in :meth:`hidden`."""
        return self.out(self.hidden(z_q, mask, offset=offset, face=face)) * self.scale


class DecoderStep:
    """The causal VQ decoder a few frames at a time: the last 4 conv inputs and a key/value cache
    of ``causal_window`` frames per block, so each frame costs the same and equals the full pass.
    The last frames can be taken back (:meth:`drop`) to decode other codes in their place.
    ``face`` (B, hidden): the streams' head term, added to every frame's input as in
    :meth:`MotionDecoder.hidden`."""

    def __init__(self, decoder: MotionDecoder, face: Tensor | None = None) -> None:
        if not decoder.cfg.causal:
            raise TalkmeshError("step-wise decoding needs a causal VQ decoder (vq.causal: true)")
        self.decoder, self.face = decoder, face
        cfg = decoder.cfg
        self.window = cfg.causal_window
        self.caches = [KVCache(self.window) for _ in decoder.blocks]
        self.inputs: Tensor | None = None  # (B, <= 4 + K, hidden) the conv's recent inputs
        self.t = 0
        device = decoder.out.weight.device
        self.bias = window_bias(cfg.heads, 1, self.window, self.window, 1, device)[None]

    def hidden(self, z_q: Tensor) -> Tensor:
        """z_q (B, K, H, C) of the next K frames -> (B, K, hidden), their normalised hidden states."""
        dec, K = self.decoder, z_q.shape[1]
        x = dec.inputs(z_q, self.face)
        past = x[:, :1].expand(-1, 4, -1) if self.inputs is None else self.inputs[:, -4:]
        self.inputs = torch.cat([past, x], dim=1)  # replicate padding on the left
        h = dec.mid(dec.conv.step(self.inputs.unfold(1, 5, 1)))
        self.t += K
        if K == 1:
            bias = self.bias[..., self.window - min(self.t, self.window) :]
        else:
            keys = min(self.t, self.window + K - 1)
            bias = window_bias(dec.cfg.heads, K, keys, self.window, 1, x.device)[None]
        for block, cache in zip(dec.blocks, self.caches):
            h = block(h, bias, cache)
        return dec.norm(h)

    def drop(self, frames: int) -> None:
        """Take back the last ``frames`` frames (at most as many as the last call decoded)."""
        if frames:
            for cache in self.caches:
                cache.drop(frames)
            self.t -= frames
            # the left padding repeats frame 0: gone with it
            self.inputs = self.inputs[:, :-frames] if self.t else None


class VQOutput(NamedTuple):
    motion: Tensor  # (B, T, V*3) reconstructed motion
    codes: Tensor  # (B, T', H)
    loss: Tensor  # () L_VQ (Eq. 3): L1 reconstruction + codebook + commitment
    reconstruction: Tensor
    quantization: Tensor


class MotionVQVAE(nn.Module):
    """Stage 1: motion (B, T, V*3) -> codes (B, T/P, H) -> motion."""

    def __init__(self, cfg: VQConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = MotionEncoder(cfg)
        self.quantizer = Quantizer(
            cfg.codebook_size,
            cfg.code_dim,
            cfg.beta,
            cfg.ema,
            cfg.ema_decay,
            cfg.dead_code_restart,
            cfg.codebook_from_data,
        )
        self.decoder = MotionDecoder(cfg)

    def forward(
        self, motion: Tensor, mask: Tensor | None = None, face: Tensor | None = None
    ) -> VQOutput:
        """motion (B, T, V*3); ``face`` (B, hidden) the decoder's head term
        (:meth:`MotionDecoder.hidden`)."""
        P = self.cfg.temporal_unit
        T = motion.shape[1]
        if T % P:
            motion = F.pad(motion, (0, 0, 0, P - T % P), mode="replicate" if T else "constant")
            if mask is not None:
                mask = F.pad(mask, (0, P - T % P))
        z = self.encoder(motion, mask)
        q = self.quantizer(z, mask[:, ::P] if mask is not None else None)
        recon = self.decoder(q.z_q, mask, face=face)
        err = (recon - motion) / self.decoder.scale  # in units of each coordinate's spread
        err = err.abs() if self.cfg.loss == "l1" else err.square()
        if mask is not None:
            rec = (err * mask[:, :, None]).sum() / (mask.sum() * err.shape[-1]).clamp(min=1)
        else:
            rec = err.mean()
        return VQOutput(recon[:, :T], q.codes, rec + q.loss, rec, q.loss)

    @torch.no_grad()
    def set_scale(self, motion: Tensor, floor: float = SCALE_FLOOR) -> None:
        """Per-coordinate standard deviation of training motion (N, V*3), floored at ``floor`` x the
        largest one, so nearly static vertices are not amplified into noise."""
        std = motion.float().reshape(-1, motion.shape[-1]).std(0)
        scale = std.clamp(min=float(std.max()) * floor)
        self.encoder.scale.copy_(scale)
        self.decoder.scale.copy_(scale)

    def encode(self, motion: Tensor, mask: Tensor | None = None) -> Quantized:
        return self.quantizer(self.encoder(motion, mask), mask)

    def decode(
        self,
        codes: Tensor,
        window: int | None = None,
        context: int = 30,
        face: Tensor | None = None,
    ) -> Tensor:
        """codes (B, T', H) -> motion (B, T, V*3); ``face`` (B, hidden) the decoder's head term
        (:meth:`MotionDecoder.hidden`).

        With ``window`` (in tokens), sequences longer than it are decoded in windows of that many
        tokens, each with ``context`` tokens of neighbours on both sides that are decoded and then
        dropped, so memory stays bounded for any length (the decoder attends over whole windows).
        """
        z_q = self.quantizer.lookup(codes)
        T = z_q.shape[1]
        if window is None or T <= window + 2 * context:
            return self.decoder(z_q, face=face)
        P = self.cfg.temporal_unit
        result = z_q.new_empty(z_q.shape[0], T * P, self.cfg.num_vertices * 3)
        for start in range(0, T, window):
            a, b = max(0, start - context), min(T, start + window + context)
            out = self.decoder(z_q[:, a:b], offset=a * P, face=face)
            result[:, start * P : min(start + window, T) * P] = out[
                :, (start - a) * P : (min(start + window, T) - a) * P
            ]
        return result
