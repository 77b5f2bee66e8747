"""CodeTalker (Xing et al., CVPR 2023): a discrete motion prior and a speech-driven code query.

Stage 1 (paper Sec. 3.1, Table 4): a transformer VQ-VAE over facial motion (vertices - template).
Each frame becomes H face-component tokens of C dims, each snapped to one of N codebook entries.
Stage 2 (Sec. 3.2): a causal transformer decoder reads speech features (one token per motion frame
through the alignment mask), a speaker style and the motion so far, and predicts the next frame's
code features; they are quantised with the frozen codebook and decoded by the frozen decoder.

Fixes of the public code's defects (REFERENCE section 3): the positional encoding differs per frame;
padding masks work for any batch; no length cap; InstanceNorm is optional (off by default: it fails
on one frame and cannot stream); generation caches keys/values (``generate(mode="fast")``) next to
a faithful ``mode="naive"`` that re-runs everything over the whole prefix at each step, like the
paper's loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.errors import TalkmeshError
from talkmesh.models.speech import SpeechEncoderConfig, build_speech_encoder, release_config

GENERATION_MODES = ("fast", "naive", "exact")  # CodeTalker.generate(mode=...)
STEPS_BEFORE_RETRY = 8  # fast mode: frames run one at a time when passes stop paying, at first

# ---------------------------------------------------------------------------------------------
# Configuration


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

    def __post_init__(self) -> None:
        for name in ("num_vertices", "hidden", "heads", "ff", "components", "code_dim",
                     "codebook_size", "temporal_unit"):  # fmt: skip
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


@dataclass(frozen=True)
class Stage2Config:
    """Stage 2. VOCASET: d=1024, 4 heads, FF 2048, 6 layers, period 30; BIWI: 12 layers, period 25,
    two audio tokens per frame."""

    d_model: int = 1024
    heads: int = 4
    ff: int = 2048
    layers: int = 6
    period: int = 30  # frames of the periodic positional encoding and temporal bias
    audio_tokens_per_frame: int = 1
    styles: tuple[str, ...] = ()  # training speakers, in one-hot order
    speech: SpeechEncoderConfig = SpeechEncoderConfig()
    attention_window: int = 600  # frames of self-attention kept in the cache when generating
    history_dropout: float = 0.0  # training: probability that a frame's fed-back motion is
    # withheld (only the style remains), so the decoder cannot lean on the true past alone;
    # 0 is the paper's plain teacher forcing (docs/codetalker.md measures the exposure bias)
    self_feedback: float = 0.0  # training: probability that a frame's fed-back motion is the
    # model's own prediction from a first, teacher-forced pass (no gradient) instead of the truth
    # (parallel scheduled sampling, Duckworth et al. 2019), so it learns from its own feedback

    def __post_init__(self) -> None:
        if self.d_model % self.heads:
            raise ValueError("stage2.d_model must be divisible by stage2.heads")
        if not self.styles:
            raise ValueError("stage2.styles must name at least one training speaker")
        if not 0.0 <= self.history_dropout < 1.0:
            raise ValueError("stage2.history_dropout must be in [0, 1)")
        if not 0.0 <= self.self_feedback <= 1.0:
            raise ValueError("stage2.self_feedback must be in [0, 1]")
        if self.period < 1 or self.audio_tokens_per_frame < 1 or self.attention_window < 1:
            raise ValueError(
                "stage2.period, audio_tokens_per_frame and attention_window must be >= 1"
            )


@dataclass(frozen=True)
class CodeTalkerConfig:
    vq: VQConfig
    stage2: Stage2Config
    motion_fps: float = 30.0


def paper_vocaset_config(
    styles: tuple[str, ...] = tuple(f"speaker{k}" for k in range(8)),
) -> CodeTalkerConfig:
    """Table 4 with the VOCASET settings and the wav2vec 2.0 base speech encoder."""
    return CodeTalkerConfig(
        vq=VQConfig(num_vertices=5023, components=16, code_dim=64),
        stage2=Stage2Config(styles=styles, speech=SpeechEncoderConfig(kind="wav2vec2")),
    )


def paper_biwi_config(
    styles: tuple[str, ...] = tuple(f"speaker{k}" for k in range(6)),
) -> CodeTalkerConfig:
    """Table 4 with the BIWI settings: H=8, C=128; 12 decoder layers, period 25, two wav2vec 2.0
    tokens per frame (BIWI's motion is 25 fps, wav2vec 2.0's features 50 Hz)."""
    return CodeTalkerConfig(
        vq=VQConfig(num_vertices=23370, components=8, code_dim=128),
        stage2=Stage2Config(
            layers=12,
            period=25,
            audio_tokens_per_frame=2,
            styles=styles,
            speech=SpeechEncoderConfig(kind="wav2vec2", frame_rate=50.0),
        ),
        motion_fps=25.0,
    )


def small_synth_config(styles: tuple[str, ...], num_vertices: int = 4766) -> CodeTalkerConfig:
    """A CPU-trainable configuration for the synthetic corpus (mel speech encoder)."""
    return CodeTalkerConfig(
        vq=VQConfig(
            num_vertices=num_vertices,
            hidden=256,
            layers=2,
            heads=4,
            ff=512,
            components=8,
            code_dim=32,
            codebook_size=256,
        ),  # fmt: skip
        stage2=Stage2Config(
            d_model=256,
            heads=4,
            ff=512,
            layers=2,
            styles=styles,
            speech=SpeechEncoderConfig(kind="mel", dim=128),
        ),  # fmt: skip
    )


# ---------------------------------------------------------------------------------------------
# Layers


def sinusoid(positions: Tensor, dim: int) -> Tensor:
    """positions (T,) -> (T, dim) sinusoidal encodings (a different vector per frame)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=positions.device) / half)
    angles = positions.float()[:, None] * freqs[None]
    out = torch.cat([angles.sin(), angles.cos()], dim=-1)
    return F.pad(out, (0, dim - out.shape[-1]))


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
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=bias)
        return self.out(y.transpose(1, 2).reshape(B, T, D))


class Block(nn.Module):
    """Pre-LN transformer block (self-attention + MLP), optionally with a cross term added."""

    def __init__(self, dim: int, heads: int, ff: int) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, ff), nn.GELU(), nn.Linear(ff, dim))

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


# ---------------------------------------------------------------------------------------------
# Stage 1: the motion VQ-VAE

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


class MotionEncoder(nn.Module):
    def __init__(self, cfg: VQConfig) -> None:
        super().__init__()
        self.inp = nn.Linear(cfg.num_vertices * 3, cfg.hidden)
        self.conv = TemporalConv(cfg.hidden, cfg.instance_norm, cfg.temporal_unit)
        self.mid = nn.Linear(cfg.hidden, cfg.hidden)
        self.blocks = nn.ModuleList(Block(cfg.hidden, cfg.heads, cfg.ff) for _ in range(cfg.layers))
        self.norm = nn.LayerNorm(cfg.hidden)
        self.out = nn.Linear(cfg.hidden, cfg.components * cfg.code_dim)
        self.cfg = cfg
        # per-coordinate motion normalisation (set from training data; a buffer, so it travels with
        # the weights): lips and nearly static vertices weigh alike in the L1 loss
        self.register_buffer("scale", torch.ones(cfg.num_vertices * 3))

    def forward(self, motion: Tensor, mask: Tensor | None = None) -> Tensor:
        """motion (B, T, V*3) -> z (B, T/P, H, C)."""
        x = self.conv(hold_last_frame(F.leaky_relu(self.inp(motion / self.scale), 0.2), mask))
        x = self.mid(x)
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
        self.blocks = nn.ModuleList(Block(cfg.hidden, cfg.heads, cfg.ff) for _ in range(cfg.layers))
        self.norm = nn.LayerNorm(cfg.hidden)
        self.out = nn.Linear(cfg.hidden, cfg.num_vertices * 3)
        self.cfg = cfg
        self.register_buffer("scale", torch.ones(cfg.num_vertices * 3))

    def hidden(self, z_q: Tensor, mask: Tensor | None = None, offset: int = 0) -> Tensor:
        """z_q (B, T', H, C) -> (B, T, hidden) before the output map (T = T' * P); ``offset`` is
        the position of the first frame (for windows of a longer sequence)."""
        x = self.inp(z_q.flatten(2))
        if self.cfg.temporal_unit > 1:
            x = x.repeat_interleave(self.cfg.temporal_unit, dim=1)
        x = self.mid(self.conv(hold_last_frame(x, mask)))
        bias = padding_bias(mask, x.dtype)
        if self.cfg.causal:
            T = x.shape[1]
            band = window_bias(self.cfg.heads, T, T, self.cfg.causal_window, 1, x.device)
            bias = band[None] if bias is None else bias + band
        else:
            x = x + sinusoid(
                torch.arange(offset, offset + x.shape[1], device=x.device), x.shape[-1]
            )
        for block in self.blocks:
            x = block(x, bias)
        return self.norm(x)

    def forward(self, z_q: Tensor, mask: Tensor | None = None, offset: int = 0) -> Tensor:
        """z_q (B, T', H, C) -> motion (B, T, V*3)."""
        return self.out(self.hidden(z_q, mask, offset=offset)) * self.scale


class DecoderStep:
    """The causal VQ decoder a few frames at a time: the last 4 conv inputs and a key/value cache
    of ``causal_window`` frames per block, so each frame costs the same and equals the full pass.
    The last frames can be taken back (:meth:`drop`) to decode other codes in their place."""

    def __init__(self, decoder: MotionDecoder) -> None:
        if not decoder.cfg.causal:
            raise TalkmeshError("step-wise decoding needs a causal VQ decoder (vq.causal: true)")
        self.decoder = decoder
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
        x = dec.inp(z_q.flatten(2))
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

    def forward(self, motion: Tensor, mask: Tensor | None = None) -> VQOutput:
        P = self.cfg.temporal_unit
        T = motion.shape[1]
        if T % P:
            motion = F.pad(motion, (0, 0, 0, P - T % P), mode="replicate" if T else "constant")
            if mask is not None:
                mask = F.pad(mask, (0, P - T % P))
        z = self.encoder(motion, mask)
        q = self.quantizer(z, mask[:, ::P] if mask is not None else None)
        recon = self.decoder(q.z_q, mask)
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

    def decode(self, codes: Tensor, window: int | None = None, context: int = 30) -> Tensor:
        """codes (B, T', H) -> motion (B, T, V*3).

        With ``window`` (in tokens), sequences longer than it are decoded in windows of that many
        tokens, each with ``context`` tokens of neighbours on both sides that are decoded and then
        dropped, so memory stays bounded for any length (the decoder attends over whole windows).
        """
        z_q = self.quantizer.lookup(codes)
        T = z_q.shape[1]
        if window is None or T <= window + 2 * context:
            return self.decoder(z_q)
        P = self.cfg.temporal_unit
        result = z_q.new_empty(z_q.shape[0], T * P, self.cfg.num_vertices * 3)
        for start in range(0, T, window):
            a, b = max(0, start - context), min(T, start + window + context)
            out = self.decoder(z_q[:, a:b], offset=a * P)
            result[:, start * P : min(start + window, T) * P] = out[
                :, (start - a) * P : (min(start + window, T) - a) * P
            ]
        return result


# ---------------------------------------------------------------------------------------------
# Stage 2: speech-driven code query


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


class Stage2Output(NamedTuple):
    motion: Tensor  # (B, T, V*3) predicted motion (teacher forced)
    loss: Tensor  # () Eq. 6
    feature_loss: Tensor
    motion_loss: Tensor


class CodeTalker(nn.Module):
    """Both stages; stage 1 is frozen while stage 2 trains."""

    family = "codetalker"
    generate_block = 128  # most frames per pass of fast generation (see FrameGenerator.block)

    def __init__(self, cfg: CodeTalkerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        s2, vq = cfg.stage2, cfg.vq
        self.vqvae = MotionVQVAE(vq)
        self.speech = build_speech_encoder(s2.speech)
        # a pretrained encoder loaded from a path: the release keeps its config, not the path
        speech_cfg = release_config(s2.speech, self.speech)
        if speech_cfg is not s2.speech:
            self.cfg = replace(cfg, stage2=replace(s2, speech=speech_cfg))
        self.audio_map = nn.Linear(self.speech.dim, s2.d_model)
        self.style = nn.Embedding(len(s2.styles), s2.d_model)
        self.motion_map = nn.Linear(vq.num_vertices * 3, s2.d_model)  # vertice_map
        self.blocks = nn.ModuleList(Block(s2.d_model, s2.heads, s2.ff) for _ in range(s2.layers))
        self.cross = nn.ModuleList(nn.Linear(s2.d_model, s2.d_model) for _ in range(s2.layers))
        self.norm = nn.LayerNorm(s2.d_model)
        self.feat_map = nn.Linear(s2.d_model, vq.components * vq.code_dim)
        nn.init.zeros_(self.feat_map.weight)  # zero-initialised output map (Sec. 3.2)
        nn.init.zeros_(self.feat_map.bias)

    @property
    def num_vertices(self) -> int:
        return self.cfg.vq.num_vertices

    @property
    def motion_fps(self) -> float:
        return self.cfg.motion_fps

    @property
    def styles(self) -> tuple[str, ...]:
        return tuple(self.cfg.stage2.styles)

    # -- pieces ---------------------------------------------------------------------------------

    def style_vector(self, styles: Tensor | None, weights: Tensor | None = None) -> Tensor:
        """(B,) style ids, or (B, S) weights over the training styles (Eq. 4) -> (B, d)."""
        if weights is not None:
            return weights.to(self.style.weight.dtype) @ self.style.weight
        if styles is None or (styles < 0).any():
            raise TalkmeshError("an unseen speaker needs style weights (e.g. --style A:0.5,B:0.5)")
        return self.style(styles)

    def audio_tokens(self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int) -> Tensor:
        """(B, S) -> (B, T, d) one token per motion frame (the alignment mask: frame t sees token t;
        with k tokens per frame their mean, which equals attending uniformly to them)."""
        k = self.cfg.stage2.audio_tokens_per_frame
        feats = self.speech(audio, audio_lengths, num_frames * k)
        feats = self.audio_map(feats)
        if k > 1:
            feats = feats.view(feats.shape[0], num_frames, k, -1).mean(2)
        return feats

    def _cross(self, audio_tokens: Tensor) -> list[Tensor]:
        """Cross-attention of frame t onto its own audio token(s) only: with one key the softmax is
        1, so the output is a linear map of the token - exact and computed for all frames at once."""
        return [layer(audio_tokens) for layer in self.cross]

    def _decoder(
        self, x: Tensor, cross: list[Tensor], bias: Tensor, caches: list[KVCache] | None = None
    ) -> Tensor:
        for n, block in enumerate(self.blocks):
            x = block(x, bias, caches[n] if caches else None, cross[n])
        return self.feat_map(self.norm(x))

    # -- training (teacher forcing) ------------------------------------------------------------

    def forward(
        self,
        audio: Tensor,
        audio_lengths: Tensor | None,
        vertices: Tensor,
        templates: Tensor,
        styles: Tensor,
        motion_mask: Tensor | None = None,
    ) -> Stage2Output:
        """audio (B, S), vertices (B, T, V, 3), templates (B, V, 3), styles (B,) -> Eq. 6 loss."""
        B, T = vertices.shape[:2]
        motion = (vertices - templates[:, None]).flatten(2)
        with torch.no_grad():
            target = self.vqvae.encode(motion, motion_mask).z_q  # (B, T, H, C)
        # validation speakers outside the training set get the mean style (as in generation)
        seen = styles.clamp(min=0)
        style = torch.where(
            (styles >= 0)[:, None], self.style(seen), self.style.weight.mean(0)[None]
        )
        s2 = self.cfg.stage2
        cross = self._cross(self.audio_tokens(audio, audio_lengths, T))
        bias = temporal_bias(s2.heads, T, T, s2.period, motion.device)[None]
        if motion_mask is not None:
            bias = bias + padding_bias(motion_mask, motion.dtype)

        def run(fed_back: Tensor) -> tuple[Tensor, Quantized, Tensor]:
            # the motion map reads normalised motion
            history = self.motion_map(fed_back[:, :-1] / self.vqvae.decoder.scale)
            if self.training and s2.history_dropout > 0:
                keep = torch.rand(B, T - 1, 1, device=history.device) >= s2.history_dropout
                history = history * keep
            prev = torch.cat([style[:, None], history + style[:, None]], dim=1)
            x = prev + periodic_encoding(T, s2.d_model, s2.period, prev.device)
            feats = self._decoder(x, cross, bias)
            feats = feats.view(B, T, self.cfg.vq.components, self.cfg.vq.code_dim)
            q = self.vqvae.quantizer(feats)
            return feats, q, self.vqvae.decoder(q.z_q, motion_mask)

        fed_back = motion
        if self.training and s2.self_feedback > 0:
            with torch.no_grad():
                own = run(motion)[2]
            pick = torch.rand(B, T, 1, device=motion.device) < s2.self_feedback
            fed_back = torch.where(pick, own, motion)
        feats, q, pred = run(fed_back)
        w = (
            motion_mask[:, :, None].to(feats.dtype)
            if motion_mask is not None
            else torch.ones(B, T, 1, device=feats.device)
        )
        f_loss = ((feats - target).pow(2).flatten(2) * w).sum() / (
            w.sum() * feats[0, 0].numel()
        ).clamp(min=1)
        scale = self.vqvae.decoder.scale
        m_loss = (((pred - motion) / scale).pow(2) * w).sum() / (w.sum() * motion.shape[-1]).clamp(
            min=1
        )
        return Stage2Output(pred, f_loss + m_loss, f_loss, m_loss)

    # -- generation -----------------------------------------------------------------------------

    @torch.inference_mode()
    def generate(
        self,
        audio: Tensor,
        template: Tensor,
        *,
        styles: Tensor | None = None,
        style_weights: Tensor | None = None,
        audio_lengths: Tensor | None = None,
        num_frames: int | None = None,
        mode: str = "fast",
        seed: int = 0,
        block: int | None = None,
    ) -> Tensor:
        """audio (B, S) at 16 kHz, template (B, V, 3) -> vertices (B, T, V, 3) (deterministic:
        ``seed`` is accepted for the common model surface and unused).

        ``mode="naive"`` is the paper's loop: at every step the whole decoder runs over the whole
        prefix (every sub-layer, the cross-attention onto the prefix's audio tokens included), the
        whole quantised prefix is decoded by the VQ decoder and its last frame fed back.
        ``mode="fast"`` keeps key/value caches: the stage-2 decoder sees exactly the same inputs
        (causal), but the VQ decoder's feedback frame comes from a causal, cached pass (its frame t
        attends to frames <= t as computed when they were last, instead of re-running bidirectional
        attention over the prefix); final vertices come from a bidirectional decode of all codes,
        in windows of ``attention_window`` frames (with 30 frames of context each side) when the
        audio is longer, so that memory stays bounded. Fast mode runs up to ``block`` frames per
        pass (default ``generate_block``) from guesses of their codes and keeps the frames whose
        guesses held (:meth:`FrameGenerator.block`): the same codes as one frame at a time
        (``block=1``), up to float rounding, which a tie between two codes could turn.
        ``mode="exact"`` is the naive loop's computation with the stage-2 caches: one frame at a
        time, the fed-back frame decoded by the bidirectional VQ decoder over the whole prefix
        (its last ``attention_window`` frames past that length), as the paper's loop does; with a
        causal VQ decoder it is fast mode, which is exact there.
        """
        if mode not in GENERATION_MODES:
            raise TalkmeshError(
                f"unknown generation mode '{mode}': use {', '.join(GENERATION_MODES)}"
            )
        if mode == "exact" and self.cfg.vq.causal:
            mode = "fast"
        B = audio.shape[0]
        fps = self.cfg.motion_fps
        if num_frames is None:
            num_frames = max(1, round(audio.shape[1] / 16_000 * fps))
        s2, vq = self.cfg.stage2, self.cfg.vq
        style = self.style_vector(styles, style_weights)
        tokens = self.audio_tokens(audio, audio_lengths, num_frames)
        H, C = vq.components, vq.code_dim
        if mode == "naive":
            inputs = style[:, None]
            codes = []
            for t in range(num_frames):
                x = inputs + periodic_encoding(t + 1, s2.d_model, s2.period, inputs.device)
                bias = temporal_bias(s2.heads, t + 1, t + 1, s2.period, x.device)[None]
                # as the paper's decoder: its cross-attention runs over the prefix at every step
                feats = self._decoder(x, self._cross(tokens[:, : t + 1]), bias)
                q = self.vqvae.quantizer(feats.view(B, t + 1, H, C))
                motion = self.vqvae.decoder(q.z_q)
                codes.append(q.codes[:, -1])
                nxt = self.motion_map(motion[:, -1] / self.vqvae.decoder.scale) + style
                inputs = torch.cat([inputs, nxt[:, None]], dim=1)
            all_codes = torch.stack(codes, dim=1)
        elif mode == "exact":
            all_codes, motion = self._generate_exact(style, self._cross(tokens), num_frames), None
        else:
            all_codes, motion = self._generate_fast(style, self._cross(tokens), num_frames, block)
        if mode == "naive" or motion is None:  # a causal decoder's steps are already final
            window = None if mode == "naive" else max(1, s2.attention_window // vq.temporal_unit)
            motion = self.vqvae.decode(all_codes, window)[:, :num_frames]
        motion = motion.reshape(B, num_frames, vq.num_vertices, 3)  # a view: no copy
        return motion.add_(template[:, None])  # in place: 10 minutes are about 1 GB

    def _generate_exact(self, style: Tensor, cross: list[Tensor], num_frames: int) -> Tensor:
        """-> codes (B, T, H) of the naive loop, one frame at a time: the stage-2 decoder with
        its caches (the same computation: it is causal), the fed-back frame from the
        bidirectional VQ decoder over the prefix, re-run at every step as in the paper's loop
        (only its hidden states: the output and motion maps are folded into one)."""
        gen = FrameGenerator(self, style)
        vq = self.cfg.vq
        B, window = style.shape[0], max(1, self.cfg.stage2.attention_window // vq.temporal_unit)
        codes = torch.empty(B, num_frames, vq.components, dtype=torch.long, device=style.device)
        for t in range(num_frames):
            q = gen._stage2(gen.x_in, [c[:, t : t + 1] for c in cross])
            gen.t += 1
            codes[:, t] = q.codes[:, 0]
            if t + 1 < num_frames:
                start = max(0, t + 1 - window)
                z_q = self.vqvae.quantizer.lookup(codes[:, start : t + 1])
                h = self.vqvae.decoder.hidden(z_q, offset=start * vq.temporal_unit)[:, -1:]
                gen.x_in = gen.fold(h) + style[:, None]
        return codes

    def _generate_fast(
        self, style: Tensor, cross: list[Tensor], num_frames: int, block: int | None = None
    ) -> tuple[Tensor, Tensor | None]:
        """-> codes (B, T, H), and with a causal VQ decoder the motion (B, T, V*3) as well.

        Frames go through :meth:`FrameGenerator.block` up to ``block`` at a time (default
        ``generate_block``), each pass guessing its codes from the previous one; ``block=1`` is
        the plain frame-by-frame loop. Either way the codes are those of the frame-by-frame loop.
        """
        gen = FrameGenerator(self, style)
        vq = self.cfg.vq
        B, most = style.shape[0], max(1, block or self.generate_block)
        codes = torch.empty(B, num_frames, vq.components, dtype=torch.long, device=style.device)
        motion = None
        if gen.causal:
            motion = style.new_empty(B, num_frames, vq.num_vertices * 3)
        done = moved = 0  # frames whose codes are final; frames whose motion is written
        guesses = codes[:, :0]  # the latest codes passes gave for the frames after ``done``
        run = float(most)  # how many frames passes keep when a guess fails (running mean)
        alone = 0  # frames to run one at a time before passes are tried again ...
        wait = STEPS_BEFORE_RETRY  # ... the next time passes keep one frame only
        while done < num_frames:
            K = min(most, max(2, round(4 * run)), num_frames - done)
            if done == 0 or alone:  # frame 0 needs no guess: its input has no motion
                K, alone = 1, max(0, alone - 1)
            drafts = guesses[:, : K - 1]
            used = drafts.shape[1]
            kept, after, frames = gen.block([c[:, done : done + K] for c in cross], drafts)
            guesses = torch.cat([after, guesses[:, K:]], dim=1)  # older ones past this pass stay
            codes[:, done : done + kept.shape[1]] = kept
            done += kept.shape[1]
            if frames is not None:
                motion[:, moved : moved + frames.shape[1]] = frames
                moved += frames.shape[1]
            if K == 1:
                continue
            # guesses that fail early again and again make long passes a waste: shorten them
            run = most if kept.shape[1] > used else (run + kept.shape[1]) / 2
            if run < 1.5:  # passes keep one frame, and each costs more than a step: steps for a
                alone, wait = wait, min(2 * wait, 16 * STEPS_BEFORE_RETRY)  # while (longer each
                run = 2.0  # time), then a short pass
            elif kept.shape[1] > 1:
                wait = STEPS_BEFORE_RETRY
        if gen.causal:  # the last frame's motion; a bidirectional decoder's feedback is not needed
            motion[:, moved:] = gen.flush()
        return codes, motion


class FrameGenerator:
    """Stage 2 and the VQ decoder over the next frames with key/value caches (``generate``'s fast
    mode, and streaming): every frame costs the same, whatever the length.

    :meth:`step` runs one frame. :meth:`block` runs K frames in one pass from guesses of their
    codes and keeps those it got right (Jacobi decoding of the autoregressive loop): generating a
    frame reads all the weights for one small matrix-vector product per layer, so a pass over K
    frames costs little more than one, and a frame's codes depend mostly on its audio, so most
    guesses taken from the previous pass hold.

    With a causal VQ decoder (``vq.causal``) the motion of each frame is returned as well, exactly
    what a full pass would give. Otherwise the fed-back frame comes from a causal, cached pass
    through the bidirectional decoder (see :meth:`CodeTalker.generate`) and no motion is returned.
    """

    def __init__(self, model: CodeTalker, style: Tensor) -> None:
        s2, vq = model.cfg.stage2, model.cfg.vq
        self.model, self.style = model, style
        self.window = s2.attention_window
        self.caches = [KVCache(self.window) for _ in model.blocks]
        dec = model.vqvae.decoder
        self.causal = vq.causal
        self.vq_step = DecoderStep(dec) if vq.causal else None
        # the bidirectional decoder's cached causal pass (unused with a causal decoder)
        self.vq_caches = [] if vq.causal else [KVCache(self.window) for _ in dec.blocks]
        self.conv_inputs: Tensor | None = None  # (B, 2 + K, hidden) its conv's recent inputs
        # the VQ decoder's output map followed by the motion map is one linear map: fold them
        # (normalised motion in, so the decoder's scale cancels)
        self.fold = folded_linear(
            model, dec.out, model.motion_map, int8=getattr(model, "int8", False)
        )
        device = style.device
        self.ppe = periodic_encoding(s2.period, s2.d_model, s2.period, device)
        self.step_bias = window_bias(s2.heads, 1, self.window, self.window, s2.period, device)[None]
        self.x_in: Tensor | None = style[:, None]  # (B, 1, d) the next frame's input ...
        self.pending: Tensor | None = None  # ... or (B, H) codes of the last frame, not yet
        # through the VQ decoder (after ``block``)
        self.t = 0  # frames whose codes are final
        self.vq_t = 0  # frames through the VQ decoder

    def _stage2(self, x: Tensor, cross: list[Tensor]) -> Quantized:
        """x (B, K, d) fed-back inputs of frames t..t+K-1 -> their codes; the rows join the cache."""
        model, t = self.model, self.t
        s2, vq = model.cfg.stage2, model.cfg.vq
        B, K = x.shape[:2]
        x = x + self.ppe[torch.arange(t, t + K, device=x.device) % len(self.ppe)]
        if K == 1:
            bias = self.step_bias[..., self.window - min(t + 1, self.window) :]
        else:
            keys = min(t + K, self.window + K - 1)
            bias = window_bias(s2.heads, K, keys, self.window, s2.period, x.device)[None]
        feats = model._decoder(x, cross, bias, self.caches)
        return model.vqvae.quantizer(feats.view(B, K, vq.components, vq.code_dim))

    def _vq_hidden(self, codes: Tensor) -> Tensor:
        """codes (B, K, H) of the next K frames -> (B, K, hidden), the VQ decoder's normalised
        hidden states before its output map; the rows join the caches."""
        dec, K = self.model.vqvae.decoder, codes.shape[1]
        z_q = self.model.vqvae.quantizer.lookup(codes)
        if self.vq_step is not None:
            h = self.vq_step.hidden(z_q)
        else:
            x = dec.inp(z_q.flatten(2))
            past = x[:, :1].expand(-1, 2, -1) if self.conv_inputs is None else self.conv_inputs
            seq = self.conv_inputs = torch.cat([past[:, -2:], x], dim=1)
            # the kernel sees t-2..t+2; t+1 and t+2 are not decoded yet, so they repeat t
            now = seq[:, 2:]
            windows = torch.stack([seq[:, :K], seq[:, 1 : K + 1], now, now, now], dim=-1)
            pos = torch.arange(self.vq_t, self.vq_t + K, device=x.device)
            h = dec.mid(dec.conv.step(windows)) + sinusoid(pos, dec.cfg.hidden)
            bias = None
            if K > 1:
                keys = min(self.vq_t + K, self.window + K - 1)
                bias = window_bias(dec.cfg.heads, K, keys, self.window, None, x.device)[None]
            for block, cache in zip(dec.blocks, self.vq_caches):
                h = block(h, bias, cache)
            h = dec.norm(h)
        self.vq_t += K
        return h

    def _vq_drop(self, frames: int) -> None:
        if not frames:
            return
        if self.vq_step is not None:
            self.vq_step.drop(frames)
        else:
            for cache in self.vq_caches:
                cache.drop(frames)
            self.conv_inputs = self.conv_inputs[:, :-frames]
        self.vq_t -= frames
        if not self.vq_t:  # the conv's left padding repeats frame 0: gone with it
            self.conv_inputs = None

    def _motion(self, h: Tensor) -> Tensor | None:
        dec = self.model.vqvae.decoder
        return dec.out(h) * dec.scale if self.causal else None

    def step(self, cross: list[Tensor]) -> tuple[Tensor, Tensor | None]:
        """cross: per decoder layer the (B, 1, d) audio term of this frame -> codes (B, H) and,
        with a causal VQ decoder, motion (B, V*3)."""
        self.flush()
        q = self._stage2(self.x_in, cross)
        self.t += 1
        h = self._vq_hidden(q.codes)
        self.x_in = self.fold(h) + self.style[:, None]
        motion = self._motion(h)
        return q.codes[:, 0], None if motion is None else motion[:, 0]

    def block(self, cross: list[Tensor], drafts: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """The next K frames in one pass; cross: per decoder layer their (B, K, d) audio terms;
        ``drafts`` (B, G, H), G < K, guess the codes of the first G of them.

        Each frame is computed from the guessed codes before it, so the frames up to the first
        wrong guess, and that one (its inputs were right), are exactly what K steps would give:
        they are kept, the rest are taken back out of the caches. A pass without any guesses
        guesses that the codes of the last kept frame hold still, so that every frame is fed
        motion that the VQ decoder made from real codes, as in the next pass (on random
        weights, codes computed from such motion hold there; from a repeated input they do
        not). Frames after the G + 1 that follow guesses are only drafts: they repeat the last
        input that a guess gave, so they cost no VQ decoder step, and their codes serve as
        guesses for the next pass. The last kept frame's codes wait for the next pass (or
        :meth:`flush`) to go through the VQ decoder.
        -> codes (B, A, H) of the A >= 1 frames kept; this pass's codes (B, K - A, H) for the
        frames after them (guesses for the next pass); with a causal VQ decoder the motion
        (B, M, V*3) of the frames that went through it for good, else None.
        """
        K = cross[0].shape[1]
        if drafts.shape[1] >= K:
            raise ValueError(f"{drafts.shape[1]} guesses for a pass of {K} frames: at most K - 1")
        if not drafts.shape[1] and self.pending is not None:
            drafts = self.pending[:, None].expand(-1, K - 1, -1)
        G = drafts.shape[1]
        rows = drafts if self.pending is None else torch.cat([self.pending[:, None], drafts], 1)
        x, h = self.x_in, None
        if rows.shape[1]:
            h = self._vq_hidden(rows)
            fed = self.fold(h) + self.style[:, None]
            x = fed if self.pending is not None else torch.cat([self.x_in, fed], dim=1)
        if K > G + 1:
            x = torch.cat([x, x[:, -1:].expand(-1, K - G - 1, -1)], dim=1)
        codes = self._stage2(x, cross).codes
        right = (codes[:, :G] == drafts).all(-1).all(0)
        A = 1 + int(right.long().cumprod(0).sum())
        for cache in self.caches:
            cache.drop(K - A)
        wrong = G + 1 - A  # VQ decoder rows from guesses that did not hold
        self._vq_drop(wrong)
        self.t += A
        self.pending, self.x_in = codes[:, A - 1], None
        exact = rows.shape[1] - wrong
        motion = self._motion(h[:, :exact]) if exact else None
        return codes[:, :A], codes[:, A:], motion

    def flush(self) -> Tensor | None:
        """Run the last frame's codes through the VQ decoder if :meth:`block` left them waiting
        -> with a causal VQ decoder their motion (B, 1, V*3), else None."""
        if self.pending is None:
            return None
        h = self._vq_hidden(self.pending[:, None])
        self.pending, self.x_in = None, self.fold(h) + self.style[:, None]
        return self._motion(h)


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
        fold = nn.utils.skip_init(nn.Linear, inner.in_features, outer.out_features,
                                  device=inner.weight.device, dtype=inner.weight.dtype)  # fmt: skip
        fold.weight.copy_(outer.weight @ inner.weight)
        fold.bias.copy_(outer.weight @ inner.bias + outer.bias)
    fold.requires_grad_(False)
    if int8:
        fold = _int8(fold)
    owner.__dict__["_folded"] = (key, fold)  # a plain attribute: not a submodule
    return fold


class Int8Linear(nn.Module):
    """A linear map read as int8: the weight with one scale per output row, the input quantised
    row by row (each row its own scale), integer products summed exactly in int32
    (``torch._int_mm``), then rescaled. A row's result depends on that row alone, never on the
    other rows of the batch, so a pass of fast generation quantises each frame as one frame at a
    time would (PyTorch's dynamic int8 scales the whole input together, which does not).
    ``weight`` (out, in), ``bias`` (out,) or None: the float originals are not kept."""

    def __init__(self, weight: Tensor, bias: Tensor | None) -> None:
        super().__init__()
        w = weight.detach().float()
        self.out_features, self.in_features = w.shape
        scale = w.abs().amax(1).clamp(min=1e-12) / 127
        # (in, out) as a transposed view of a contiguous (out, in) matrix: the layout
        # torch._int_mm reads fastest for one or two rows
        self.register_buffer("weight_int8", (w / scale[:, None]).round_().to(torch.int8).t())
        self.register_buffer("weight_scale", scale)
        self.register_buffer("bias", None if bias is None else bias.detach().float())

    def forward(self, x: Tensor) -> Tensor:
        rows = x.reshape(-1, self.in_features).float()
        scale = rows.abs().amax(1, keepdim=True).clamp_(min=1e-12) / 127
        y = torch._int_mm(torch.round(rows / scale).to(torch.int8), self.weight_int8).float()
        y.mul_(scale).mul_(self.weight_scale)
        if self.bias is not None:
            y.add_(self.bias)
        return y.view(*x.shape[:-1], self.out_features)

    def extra_repr(self) -> str:
        return f"in_features={self.in_features}, out_features={self.out_features}, int8"


class Int8Conv1d(nn.Module):
    """A Conv1d (zero padding, no groups or dilation) as :class:`Int8Linear` over the windows
    under its kernel: each output frame is one row, quantised on its own."""

    def __init__(self, conv: nn.Conv1d) -> None:
        super().__init__()
        # Conv1d's own attributes, which callers read (Whisper checks its stem's strides)
        self.in_channels, self.out_channels = conv.in_channels, conv.out_channels
        self.kernel_size, self.stride, self.padding = conv.kernel_size, conv.stride, conv.padding
        self.linear = Int8Linear(conv.weight.flatten(1), conv.bias)  # inputs in (c, k) order

    def forward(self, x: Tensor) -> Tensor:
        """(B, C, L) -> (B, O, L')."""
        if self.padding[0]:
            x = F.pad(x, (self.padding[0], self.padding[0]))
        windows = x.unfold(2, self.kernel_size[0], self.stride[0]).transpose(1, 2)  # (B, L', C, k)
        return self.linear(windows.flatten(2)).transpose(1, 2)


def _plain_conv1d(module: nn.Module) -> bool:
    return (
        type(module) is nn.Conv1d
        and module.groups == 1
        and module.dilation[0] == 1
        and module.padding_mode == "zeros"
        and isinstance(module.padding, tuple)
    )


def _int8(module: nn.Module) -> nn.Module:
    """``module`` with its linear layers as :class:`Int8Linear` and its plain convolutions as
    :class:`Int8Conv1d` (a bare layer is converted itself); the float weights are not kept."""
    if type(module) is nn.Linear:
        return Int8Linear(module.weight, module.bias)
    if _plain_conv1d(module):
        return Int8Conv1d(module)
    for name, child in module.named_children():
        setattr(module, name, _int8(child))
    return module


def quantize_int8(model: CodeTalker, *, speech: bool = False, decoders: bool = True) -> CodeTalker:
    """A copy of ``model`` for CPU generation whose linear layers run in int8 (:class:`Int8Linear`).

    Generating a frame at a time is bound by reading the weights; a pass over many frames by
    arithmetic. int8 helps both: 4x fewer bytes per weight, and integer products that this
    machine's CPU runs several times faster than float32 ones (VNNI). Replaced: the stage-2
    decoder blocks and output map, the VQ decoder's blocks, input and middle maps, its temporal
    convolution's per-frame step (as one matrix) and the folded feedback map; with ``speech``,
    the speech encoder's linear layers and plain convolutions (:class:`Int8Conv1d`) too. The
    per-sequence maps (audio map, cross terms, motion map) and the final vertex output map stay
    float32. Each row is quantised on its own, so a linear layer's result for a frame does not
    depend on the other frames of its pass (attention's float rounding still can, which int8
    rounding may turn into another code now and then). ``decoders=False`` with
    ``speech=True`` quantises the speech encoder alone (the decoders stay float32). Not exact:
    the effect on accuracy is measured by ``bench/fast_vs_naive.py --int8``.
    """
    import copy

    out = copy.deepcopy(model).eval()
    if speech:
        out.speech = _int8(out.speech)
    if not decoders:
        return out
    dec = out.vqvae.decoder
    # one at a time, so that each float32 original is freed before the next copy is made
    out.blocks = _int8(out.blocks)
    dec.blocks = _int8(dec.blocks)
    out.feat_map = _int8(out.feat_map)
    dec.inp = _int8(dec.inp)
    dec.mid = _int8(dec.mid)
    conv = dec.conv.conv  # its per-frame step as one matrix, inputs in the (c, k) order
    dec.conv.linear = Int8Linear(conv.weight.flatten(1), conv.bias)
    out.int8 = True  # FrameGenerator quantises its folded feedback map too
    return out
