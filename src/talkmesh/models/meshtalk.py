"""MeshTalk (Richard et al., ICCV 2021): a categorical expression space and an audio-conditioned prior.

Read top to bottom:

1. Configs: :class:`MelConfig`, :class:`MeshTalkConfig`, :class:`PriorConfig` and the presets
   ``paper`` (H=64, C=128), ``released`` (the official code, H=16, C=128) and ``small`` (a synthetic
   corpus on 2 CPU cores).
2. :class:`MelAudioEncoder`: log-mel spectrogram (torch.stft + a mel filterbank buffer, 80 bins,
   16 kHz) and dilated convolutions whose receptive field is exactly a window of mel frames around each
   motion frame (``context`` before, ``lookahead`` after). Same call as talkmesh's shared speech
   encoders: ``forward(audio (B, S), audio_lengths (B,) | None, num_frames) -> (B, T, D)``.
3. :class:`ExpressionEncoder`: per-frame MLP + LSTM over the mesh sequence.
4. :class:`FusionQuantizer`: MLP to H heads of C logits, hard straight-through Gumbel-softmax (Eq. 1-2).
5. :class:`TemplateDecoder`: U-Net over the template with additive skips, the code concatenated at the
   bottleneck, two LSTM layers, back to vertices (Eq. 3). Any neutral mesh of the topology can be animated.
6. Losses as functions returning NamedTuples: :func:`meshtalk_loss` (reconstruction, cross-modality
   Eq. 6 with the soft mouth and upper-face maps, eyelid Eq. 7) and :func:`prior_loss`.
7. :class:`MeshTalk`: ``forward`` (teacher-forced graph with the two cross-modal decodes), ``encode``,
   ``decode``, ``retarget`` (Sec. 4.3), ``dub`` (Sec. 4.4), ``loss``, ``set_statistics``.
8. :class:`AutoregressivePrior`: masked causal temporal convolutions over (time, head) conditioned on
   audio, Eq. 8; ``forward`` (teacher-forced logits), ``sample`` (incremental: per-layer ring buffers of
   past activations, constant cost per frame), ``sample_uncached`` (reference that recomputes the whole
   history), ``perplexity`` (Eq. 9).
9. :class:`MeshTalkModel` (+ :class:`MeshTalkModelConfig`, :class:`SamplingConfig`): the release,
   expression space + prior behind talkmesh's common model surface (``generate(audio, template,
   seed=)``: prior codes decoded on the template).

Axis letters: B batch, S audio samples, T motion frames, M mel frames, V vertices, H heads, C classes
(the codebook size K of the issue), D width.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.errors import TalkmeshError
from talkmesh.models.speech import SpeechEncoderConfig

SAMPLE_RATE = (
    16_000  # Hz; the paper's audio rate and talkmesh's (talkmesh.audio.loading.SAMPLE_RATE)
)
LEAKY_SLOPE = 0.2  # LeakyReLU slope used throughout, as in the official code
LOG_FLOOR = 1e-5  # power floor before the log: silence maps to log(LOG_FLOOR)
DEFAULT_MEL_MEAN = -4.0  # rough log-mel statistics of speech; replace with data via set_statistics
DEFAULT_MEL_STD = 4.0
MS_PER_S = 1000.0


def _fail(message: str) -> None:
    raise TalkmeshError(message)


# ---------------------------------------------------------------------------------------------
# 1. Configs


@dataclass(frozen=True)
class MelConfig:
    """Log-mel audio encoder. The paper: 80 mel bins every 10 ms, n_fft 2048 (1024 bins), window 800.

    The conv stack (kernel ``kernel_size``, one layer per dilation) has a receptive field of
    ``receptive_field`` mel frames; ``lookahead_ms`` of it lies after the motion frame, the rest
    before (defaults: 61 frames = 500 ms before + 100 ms after, the paper's 600 ms snippet).
    """

    sample_rate: int = SAMPLE_RATE
    n_mels: int = 80
    n_fft: int = 2048
    win_length: int = 800
    hop_length: int = 160  # 10 ms at 16 kHz
    width: int = 128
    kernel_size: int = 5
    dilations: tuple[int, ...] = (1, 2, 4, 8)  # four layers (paper Sec. 3.1)
    lookahead_ms: float = 100.0
    out_dim: int = 128
    # LayerNorm on the output (not in the paper; on in MeshTalk's configs): without it the audio
    # activations grew to ~700x the expression features in training, the fusion logits saturated
    # the softmax and the Gumbel gradients to the expression path vanished (docs/meshtalk.md)
    layer_norm: bool = False

    def __post_init__(self) -> None:
        if self.sample_rate <= 0 or self.hop_length <= 0 or self.n_mels <= 0:
            _fail("meshtalk audio config: sample_rate, hop_length and n_mels must be positive")
        if not 0 < self.win_length <= self.n_fft:
            _fail("meshtalk audio config: win_length must be in (0, n_fft]")
        if self.kernel_size < 1 or not self.dilations or min(self.dilations) < 1:
            _fail("meshtalk audio config: kernel_size and dilations must be >= 1")
        if self.lookahead_frames > self.receptive_field - 1 or self.lookahead_ms < 0:
            _fail(
                f"meshtalk audio config: lookahead_ms={self.lookahead_ms} needs "
                f"{self.lookahead_frames} mel frames but the receptive field is "
                f"{self.receptive_field}: lower it or add dilations"
            )

    @property
    def mel_rate(self) -> float:
        """Mel frames per second."""
        return self.sample_rate / self.hop_length

    @property
    def receptive_field(self) -> int:
        """Mel frames seen per motion frame."""
        return 1 + (self.kernel_size - 1) * sum(self.dilations)

    @property
    def lookahead_frames(self) -> int:
        return int(round(self.lookahead_ms / MS_PER_S * self.mel_rate))

    @property
    def context_frames(self) -> int:
        return self.receptive_field - 1 - self.lookahead_frames


@dataclass(frozen=True)
class LossWeights:
    """Weights of :func:`meshtalk_loss`. The paper optimises L_xMod + L_eyelid with equal weights."""

    mouth: float = 1.0  # audio-driven decode, mouth map (Eq. 6, second term)
    upper: float = 1.0  # expression-driven decode, upper-face map (Eq. 6, first term)
    eyelid: float = 1.0  # Eq. 7
    reconstruction: float = 0.0  # plain l2 on the (x, a) decode: logged, off in the paper


@dataclass(frozen=True)
class MeshTalkConfig:
    """The expression space: encoders, Gumbel quantiser and template-conditioned decoder."""

    num_vertices: int
    fps: float = 30.0
    num_heads: int = 16  # H
    num_classes: int = 128  # C
    audio: MelConfig = MelConfig(layer_norm=True)
    expression_widths: tuple[int, ...] = (
        256,
        128,
        128,
    )  # three FC layers, then an LSTM of the last
    fusion_width: int = 256  # three-layer MLP
    decoder_widths: tuple[int, ...] = (
        512,
        256,
        128,
    )  # U-Net encoder widths; the last is the LSTMs'
    decoder_lstm_layers: int = 2
    gumbel_tau: float = 1.0
    # standardise each head's C logits (zero mean, unit variance; not in the paper): the largest
    # class probability is then at most ~0.9 for C=32, so the straight-through Gumbel gradients
    # cannot vanish through a saturated softmax (what stalled the first small training)
    logit_norm: bool = False
    loss: LossWeights = LossWeights()
    # encoder inputs (paper Table 1): "both" (expression and audio) or "expression" (the audio
    # features are zeroed before the fusion; the expression-only latent space of row one)
    inputs: str = "both"
    # audio encoder: None = the paper's mel convolutions (``audio``); or any talkmesh speech
    # encoder (talkmesh.models.speech, e.g. frozen Whisper) mapped to ``audio.out_dim`` + LayerNorm
    speech: SpeechEncoderConfig | None = None

    def __post_init__(self) -> None:
        if self.num_vertices < 1:
            _fail("meshtalk config: num_vertices must be at least 1")
        if self.fps <= 0:
            _fail("meshtalk config: fps must be positive")
        if self.num_heads < 1 or self.num_classes < 2:
            _fail("meshtalk config: num_heads must be >= 1 and num_classes >= 2")
        if not self.expression_widths or not self.decoder_widths:
            _fail("meshtalk config: expression_widths and decoder_widths must not be empty")
        if min(self.expression_widths + self.decoder_widths) < 1 or self.fusion_width < 1:
            _fail("meshtalk config: layer widths must be positive")
        if self.gumbel_tau <= 0:
            _fail("meshtalk config: gumbel_tau must be positive")
        if self.inputs not in ("both", "expression"):
            _fail(f"meshtalk config: inputs must be both or expression, got {self.inputs!r}")


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
    fps: float = 30.0
    # "own": the prior's own mel encoder (``audio``, causal with its look-ahead, paper Eq. 8);
    # "expression": the trained expression space's audio features (as the official code does)
    audio_source: str = "own"

    def __post_init__(self) -> None:
        if self.num_heads < 1 or self.num_classes < 2 or self.width < 1:
            _fail("meshtalk prior config: num_heads >= 1, num_classes >= 2, width >= 1 needed")
        if self.kernel_size < 2 or not self.dilations or min(self.dilations) < 1:
            _fail("meshtalk prior config: kernel_size must be >= 2 and dilations >= 1")
        if self.fps <= 0:
            _fail("meshtalk prior config: fps must be positive")
        if self.audio_source not in ("own", "expression"):
            _fail("meshtalk prior config: audio_source must be own or expression")

    @property
    def receptive_field(self) -> int:
        return 1 + (self.kernel_size - 1) * sum(self.dilations)


PRESETS = ("paper", "released", "small")


def meshtalk_config(preset: str, num_vertices: int, fps: float = 30.0) -> MeshTalkConfig:
    """``paper`` (H=64, C=128), ``released`` (official code: H=16, C=128) or ``small``."""
    if preset == "paper":
        return MeshTalkConfig(num_vertices, fps, num_heads=64, num_classes=128)
    if preset == "released":
        return MeshTalkConfig(num_vertices, fps, num_heads=16, num_classes=128)
    if preset == "small":  # the synthetic corpus: few thousand vertices, 2 CPU cores
        return MeshTalkConfig(
            num_vertices,
            fps,
            num_heads=8,
            num_classes=32,
            audio=MelConfig(width=64, out_dim=64, layer_norm=True),
            expression_widths=(128, 64, 64),
            fusion_width=128,
            decoder_widths=(128, 64, 64),
        )
    raise TalkmeshError(f"unknown meshtalk preset '{preset}': choose one of {', '.join(PRESETS)}")


def prior_config(preset: str, fps: float = 30.0) -> PriorConfig:
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


# ---------------------------------------------------------------------------------------------
# 2. Audio encoder


def mel_filterbank(n_freqs: int, n_mels: int, sample_rate: int) -> Tensor:
    """(n_freqs, n_mels) triangular HTK-mel filters from 0 Hz to Nyquist (torchaudio's default)."""
    freqs = torch.linspace(0.0, sample_rate / 2, n_freqs, dtype=torch.float64)
    mel_max = 2595.0 * math.log10(1.0 + sample_rate / 2 / 700.0)
    mel_points = torch.linspace(0.0, mel_max, n_mels + 2, dtype=torch.float64)
    hz_points = 700.0 * (10.0 ** (mel_points / 2595.0) - 1.0)
    widths = hz_points[1:] - hz_points[:-1]
    slopes = hz_points[None, :] - freqs[:, None]
    down = -slopes[:, :-2] / widths[:-1]
    up = slopes[:, 2:] / widths[1:]
    return torch.clamp(torch.minimum(down, up), min=0.0).float()


class MelAudioEncoder(nn.Module):
    """Raw audio -> one feature vector per motion frame from a window of log-mel frames.

    The convs run once over the whole spectrogram ("valid", no padding inside the stack); output
    position m sees exactly mel frames [m - context, m + lookahead], so a motion frame's feature is
    read at its mel index. Same result as the official per-window network, linear in length.
    """

    def __init__(self, cfg: MelConfig, fps: float) -> None:
        super().__init__()
        self.cfg = cfg
        self.fps = fps
        self.register_buffer("window", torch.hann_window(cfg.win_length), persistent=False)
        filters = mel_filterbank(cfg.n_fft // 2 + 1, cfg.n_mels, cfg.sample_rate)
        self.register_buffer("filterbank", filters, persistent=False)
        self.register_buffer("mel_mean", torch.full((cfg.n_mels,), DEFAULT_MEL_MEAN))
        self.register_buffer("mel_std", torch.full((cfg.n_mels,), DEFAULT_MEL_STD))
        self.input = nn.Conv1d(cfg.n_mels, cfg.width, kernel_size=1)
        self.convs = nn.ModuleList(
            nn.Conv1d(cfg.width, cfg.width, cfg.kernel_size, dilation=d) for d in cfg.dilations
        )
        self.output = nn.Linear(cfg.width, cfg.out_dim)
        self.norm = nn.LayerNorm(cfg.out_dim) if cfg.layer_norm else nn.Identity()

    def log_mel(self, audio: Tensor, center: bool = True) -> Tensor:
        """(B, S) -> (B, n_mels, M) log power, M = S // hop + 1 (frame m centred on sample m*hop);
        ``center=False``: frame m starts at sample m*hop (the caller pads, as streaming does)."""
        cfg = self.cfg
        spec = torch.stft(
            audio.to(self.window.dtype),
            n_fft=cfg.n_fft,
            hop_length=cfg.hop_length,
            win_length=cfg.win_length,
            window=self.window,
            center=center,
            pad_mode="constant",
            return_complex=True,
        )
        power = spec.real.square() + spec.imag.square()
        mel = torch.einsum("bfm,fn->bnm", power, self.filterbank)
        return torch.log(mel.clamp(min=LOG_FLOOR))

    @torch.no_grad()
    def set_statistics(self, audio: Tensor) -> None:
        """Per-bin log-mel mean and std from training audio (B, S) (buffers: saved with the weights)."""
        mel = self.log_mel(audio).transpose(0, 1).flatten(1)  # (n_mels, B*M)
        self.mel_mean.copy_(mel.mean(1))
        self.mel_std.copy_(mel.std(1).clamp(min=1e-3))

    def frame_indices(self, num_frames: int) -> Tensor:
        """(T,) mel frame index of each motion frame."""
        t = torch.arange(num_frames, dtype=torch.float64)
        return torch.round(t * (self.cfg.mel_rate / self.fps)).long()

    def forward(
        self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int, shift: int = 0
    ) -> Tensor:
        """(B, S) audio at ``cfg.sample_rate``, (B,) valid lengths or None -> (B, T, out_dim).

        ``shift`` (mel frames) reads each motion frame's feature that many frames later, so it sees
        ``shift`` more frames of look-ahead (a runtime look-ahead for streaming models)."""
        cfg = self.cfg
        if audio.ndim != 2:
            _fail(f"meshtalk audio encoder: audio must be (B, S), got {tuple(audio.shape)}")
        if num_frames < 1:
            _fail("meshtalk audio encoder: num_frames must be at least 1")
        if audio_lengths is not None:  # padded batches: silence past each sample's end
            valid = torch.arange(audio.shape[1], device=audio.device)[None] < audio_lengths[:, None]
            audio = audio * valid
        centres = self.frame_indices(num_frames).to(audio.device) + shift
        last_mel = (
            int(centres[-1]) + cfg.lookahead_frames
        )  # the last mel frame any motion frame sees
        # exactly the samples those mel frames read, zero-padded when the audio ends early, so a
        # sample gives the same features alone or padded in a batch
        needed = last_mel * cfg.hop_length + cfg.n_fft // 2 + 1
        audio = F.pad(audio[:, :needed], (0, max(0, needed - audio.shape[1])))
        mel = self.log_mel(audio)[:, :, : last_mel + 1]
        mel = F.pad(mel, (cfg.context_frames, 0), value=math.log(LOG_FLOOR))  # silence before t=0
        x = self.convolve(mel)[:, :, centres]  # (B, width, T)
        return self.norm(self.output(x.transpose(1, 2)))

    def convolve(self, mel: Tensor) -> Tensor:
        """(B, n_mels, M + receptive_field - 1) log-mel -> (B, width, M): output m reads the
        input frames m .. m + receptive_field - 1 ("valid" convolutions)."""
        x = (mel - self.mel_mean[:, None]) / self.mel_std[:, None]
        x = F.leaky_relu(self.input(x), LEAKY_SLOPE)
        for conv in self.convs:
            y = F.leaky_relu(conv(x), LEAKY_SLOPE)
            crop = (x.shape[-1] - y.shape[-1]) // 2  # centred residual stays inside the window
            x = (x[:, :, crop : crop + y.shape[-1]] + y) / 2
        return x


class SpeechFeatures(nn.Module):
    """A talkmesh speech encoder (mel, wav2vec2, Whisper; ``talkmesh.models.speech``) behind the
    audio encoder's call, mapped to ``out_dim`` with a LayerNorm."""

    def __init__(self, cfg: SpeechEncoderConfig, out_dim: int) -> None:
        super().__init__()
        from talkmesh.models.speech import build_speech_encoder

        self.encoder = build_speech_encoder(cfg)
        self.output = nn.Linear(self.encoder.dim, out_dim)
        self.norm = nn.LayerNorm(out_dim)

    def forward(self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int) -> Tensor:
        return self.norm(self.output(self.encoder(audio, audio_lengths, num_frames)))

    def set_statistics(self, audio: Tensor) -> None:
        if hasattr(self.encoder, "set_statistics"):
            self.encoder.set_statistics(audio)


# ---------------------------------------------------------------------------------------------
# 3. Expression encoder


class ExpressionEncoder(nn.Module):
    """(B, T, V*3) normalised vertex offsets -> (B, T, D): three FC layers and one LSTM (Sec. 3.1)."""

    def __init__(self, in_dim: int, widths: tuple[int, ...]) -> None:
        super().__init__()
        dims = (in_dim, *widths)
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.lstm = nn.LSTM(widths[-1], widths[-1], batch_first=True)

    def forward(self, x: Tensor) -> Tensor:
        for layer in self.layers:
            x = F.leaky_relu(layer(x), LEAKY_SLOPE)
        return self.lstm(x)[0]


# ---------------------------------------------------------------------------------------------
# 4. Fusion and Gumbel quantiser


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
# 5. Template-conditioned decoder


class TemplateDecoder(nn.Module):
    """U-Net over the template (Fig. 2): template encoder with additive skips, codes concatenated at
    the bottleneck, LSTMs over time, FC layers back to vertex offsets (zero-initialised last layer, so an
    untrained decoder returns the template)."""

    def __init__(self, num_vertices: int, code_dim: int, widths: tuple[int, ...], lstm_layers: int):
        super().__init__()
        dims = (num_vertices * 3, *widths)
        self.encoder = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.bottleneck = nn.Linear(widths[-1] + code_dim, widths[-1])
        self.lstm = nn.LSTM(widths[-1], widths[-1], num_layers=lstm_layers, batch_first=True)
        up = dims[::-1]  # widths[-1] ... widths[0], V*3
        self.decoder = nn.ModuleList(nn.Linear(a, b) for a, b in zip(up[:-2], up[1:-1]))
        self.output = nn.Linear(widths[0], num_vertices * 3)
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
        x = self.lstm(x)[0] + skips[-1][:, None]
        for layer, skip in zip(self.decoder, reversed(skips[:-1])):
            x = F.leaky_relu(layer(x), LEAKY_SLOPE) + skip[:, None]
        return self.output(x)


# ---------------------------------------------------------------------------------------------
# 6. Losses


class MeshTalkForward(NamedTuple):
    """Teacher-forced outputs, all (B, T, V, 3) except the quantised codes.

    reconstruction: D(h_x, E(x, a)); audio_driven: D(h_x, E(x~, a)) (Eq. 4);
    expression_driven: D(h_x, E(x, a~)) (Eq. 5); quantized: the codes of E(x, a).
    """

    reconstruction: Tensor
    audio_driven: Tensor
    expression_driven: Tensor
    quantized: Quantized


class MeshTalkLoss(NamedTuple):
    """total = weighted sum; each term a () mean squared error in units of ``scale``."""

    total: Tensor
    reconstruction: Tensor
    mouth: Tensor
    upper: Tensor
    eyelid: Tensor


def region_error(
    pred: Tensor, target: Tensor, weight: Tensor, mask: Tensor | None, scale: Tensor | float
) -> Tensor:
    """Weighted mean over vertices, mean over valid frames, of ||pred - target||^2 / scale^2.

    pred, target (B, T, V, 3); weight (V,); mask (B, T) bool or None -> ().
    """
    err = ((pred - target) / scale).square().sum(-1)  # (B, T, V)
    per_frame = (err * weight).sum(-1) / weight.sum().clamp(min=1e-8)
    if mask is None:
        return per_frame.mean()
    mask = mask.to(per_frame.dtype)
    return (per_frame * mask).sum() / mask.sum().clamp(min=1.0)


def meshtalk_loss(
    out: MeshTalkForward,
    vertices: Tensor,
    mouth_weight: Tensor,
    upper_weight: Tensor,
    eyelid_mask: Tensor,
    motion_mask: Tensor | None = None,
    scale: Tensor | float = 1.0,
    weights: LossWeights = LossWeights(),
) -> MeshTalkLoss:
    """Eq. 6 (cross-modality: upper map on the expression-driven decode, mouth map on the audio-driven
    one), Eq. 7 (eyelids, on the reconstruction) and plain reconstruction; weighted means, not sums."""
    full = torch.ones_like(mouth_weight)
    recon = region_error(out.reconstruction, vertices, full, motion_mask, scale)
    mouth = region_error(out.audio_driven, vertices, mouth_weight, motion_mask, scale)
    upper = region_error(out.expression_driven, vertices, upper_weight, motion_mask, scale)
    if bool(eyelid_mask.any()):
        eyelid = region_error(out.reconstruction, vertices, eyelid_mask, motion_mask, scale)
    else:
        eyelid = recon.new_zeros(())
    total = (
        weights.mouth * mouth
        + weights.upper * upper
        + weights.eyelid * eyelid
        + weights.reconstruction * recon
    )
    return MeshTalkLoss(total, recon, mouth, upper, eyelid)


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


# ---------------------------------------------------------------------------------------------
# 7. The expression-space model


def _check_mesh(name: str, x: Tensor, num_vertices: int, ndim: int) -> None:
    want = "(B, T, V, 3)" if ndim == 4 else "(B, V, 3)"
    if x.ndim != ndim or x.shape[-2:] != (num_vertices, 3):
        _fail(
            f"meshtalk: {name} must be {want} with V={num_vertices}, got {tuple(x.shape)}: "
            "use meshes of the topology the model was built for"
        )


class MeshTalk(nn.Module):
    """Categorical expression space: E(x, a) -> codes, D(h, codes) -> animated template.

    Region maps (the dataset's, e.g. ``talkmesh.face.assets.load_head().regions``) are buffers saved with
    the weights: ``mouth_weight`` and ``upper_weight`` soft (V,) maps, ``eyelids`` vertex ids. Missing
    maps default to uniform weights and no eyelids. Normalisation statistics are buffers too.
    """

    def __init__(
        self,
        config: MeshTalkConfig,
        mouth_weight: Tensor | None = None,
        upper_weight: Tensor | None = None,
        eyelids: Tensor | None = None,
    ) -> None:
        super().__init__()
        self.config = cfg = config
        V, H, C = cfg.num_vertices, cfg.num_heads, cfg.num_classes
        if cfg.speech is None:
            self.audio_encoder = MelAudioEncoder(cfg.audio, cfg.fps)
        else:
            from talkmesh.models.speech import release_config

            self.audio_encoder = SpeechFeatures(cfg.speech, cfg.audio.out_dim)
            # a pretrained encoder loaded from a path: the release keeps its config, not the path
            speech = release_config(cfg.speech, self.audio_encoder.encoder)
            if speech is not cfg.speech:
                self.config = cfg = replace(cfg, speech=speech)
        self.expression_encoder = ExpressionEncoder(V * 3, cfg.expression_widths)
        self.fusion = FusionQuantizer(
            cfg.audio.out_dim + cfg.expression_widths[-1], cfg.fusion_width, H, C
        )
        self.decoder = TemplateDecoder(V, H * C, cfg.decoder_widths, cfg.decoder_lstm_layers)
        self.register_buffer("mouth_weight", self._vertex_map(mouth_weight, 1.0))
        self.register_buffer("upper_weight", self._vertex_map(upper_weight, 1.0))
        eyelid_mask = torch.zeros(V)
        if eyelids is not None:
            ids = torch.as_tensor(eyelids).long()
            if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= V):
                _fail(f"meshtalk: eyelid ids must lie in [0, {V}), the model's vertex count")
            eyelid_mask[ids] = 1.0
        self.register_buffer("eyelid_mask", eyelid_mask)
        # normalisation (set_statistics): templates and offsets are scaled to unit spread
        self.register_buffer("template_mean", torch.zeros(V, 3))
        self.register_buffer("template_scale", torch.ones(()))
        self.register_buffer("offset_scale", torch.ones(()))

    def _vertex_map(self, values: Tensor | None, default: float) -> Tensor:
        V = self.config.num_vertices
        if values is None:
            return torch.full((V,), default)
        values = torch.as_tensor(values, dtype=torch.float32).flatten()
        if values.shape != (V,):
            _fail(f"meshtalk: region maps must have {V} values, got {values.numel()}")
        return values

    @torch.no_grad()
    def set_statistics(self, templates: Tensor, offsets: Tensor) -> None:
        """Normalisation from training data: templates (N, V, 3), offsets = vertices - template (..., V, 3)."""
        _check_mesh("templates", templates, self.config.num_vertices, 3)
        mean = templates.mean(0)
        self.template_mean.copy_(mean)
        self.template_scale.copy_((templates - mean).std().clamp(min=1e-8))
        self.offset_scale.copy_(offsets.std().clamp(min=1e-8))

    # -- encoder --------------------------------------------------------------------------------

    def features(
        self, vertices: Tensor, templates: Tensor, audio: Tensor, audio_lengths: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """(B, T, V, 3), (B, V, 3), (B, S) -> audio (B, T, Da) and expression (B, T, De) features."""
        _check_mesh("vertices", vertices, self.config.num_vertices, 4)
        _check_mesh("templates", templates, self.config.num_vertices, 3)
        B, T = vertices.shape[:2]
        offsets = (vertices - templates[:, None]) / self.offset_scale
        expr = self.expression_encoder(offsets.reshape(B, T, -1))
        aud = self.audio_encoder(audio, audio_lengths, T)
        return aud, expr

    def quantize(
        self,
        audio_features: Tensor,
        expression_features: Tensor,
        sample: bool,
        generator: torch.Generator | None = None,
    ) -> Quantized:
        if self.config.inputs == "expression":
            audio_features = torch.zeros_like(audio_features)
        logits = self.fusion(torch.cat([audio_features, expression_features], dim=-1))
        if self.config.logit_norm:
            logits = F.layer_norm(logits, logits.shape[-1:])
        return gumbel_one_hot(logits, self.config.gumbel_tau, sample, generator)

    def encode(
        self,
        vertices: Tensor,
        templates: Tensor,
        audio: Tensor,
        audio_lengths: Tensor | None = None,
        sample: bool | None = None,
        generator: torch.Generator | None = None,
    ) -> Quantized:
        """E(x, a) (Eq. 1-2): (B, T, V, 3), (B, V, 3), (B, S) -> codes (B, T, H).

        ``sample`` draws Gumbel noise (default: in training mode); otherwise the argmax code.
        """
        aud, expr = self.features(vertices, templates, audio, audio_lengths)
        return self.quantize(aud, expr, self.training if sample is None else sample, generator)

    # -- decoder --------------------------------------------------------------------------------

    def decode(self, templates: Tensor, codes: Tensor) -> Tensor:
        """D(h, c) (Eq. 3): templates (B, V, 3), codes (B, T, H) int64 or one-hot (B, T, H, C)
        -> vertices (B, T, V, 3)."""
        cfg = self.config
        _check_mesh("templates", templates, cfg.num_vertices, 3)
        if not codes.is_floating_point():
            if codes.ndim != 3 or codes.shape[-1] != cfg.num_heads:
                _fail(f"meshtalk: codes must be (B, T, {cfg.num_heads}), got {tuple(codes.shape)}")
            if int(codes.min()) < 0 or int(codes.max()) >= cfg.num_classes:
                _fail(f"meshtalk: codes must lie in [0, {cfg.num_classes})")
            codes = F.one_hot(codes, cfg.num_classes).to(templates.dtype)
        if codes.ndim != 4 or codes.shape[-2:] != (cfg.num_heads, cfg.num_classes):
            _fail(f"meshtalk: one-hot codes must be (B, T, H, C), got {tuple(codes.shape)}")
        if codes.shape[0] != templates.shape[0]:
            _fail("meshtalk: codes and templates must have the same batch size")
        B, T = codes.shape[:2]
        h = ((templates - self.template_mean) / self.template_scale).reshape(B, -1)
        offsets = self.decoder(h, codes.reshape(B, T, -1)).view(B, T, -1, 3)
        return templates[:, None] + offsets * self.offset_scale

    # -- training graph -------------------------------------------------------------------------

    def forward(
        self,
        vertices: Tensor,
        templates: Tensor,
        audio: Tensor,
        audio_lengths: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> MeshTalkForward:
        """The teacher-forced graph with both cross-modal decodes (Eq. 4-5).

        The "random other" sequence of the paper is the next sample in the batch (``roll`` by one);
        with batch 1 it is the same sequence shifted by half its length in time. Features are computed
        once and rolled, so the cost is one encoder pass and three fusions and decodes.
        """
        aud, expr = self.features(vertices, templates, audio, audio_lengths)
        sample = self.training
        own = self.quantize(aud, expr, sample, generator)
        reconstruction = self.decode(templates, own.one_hot)
        w = self.config.loss
        if w.mouth == 0 and w.upper == 0:  # plain l2 (Table 1 rows one and two): no cross decodes
            return MeshTalkForward(reconstruction, reconstruction, reconstruction, own)
        if vertices.shape[0] > 1:
            other_aud, other_expr = aud.roll(1, dims=0), expr.roll(1, dims=0)
        else:
            shift = max(1, vertices.shape[1] // 2)
            other_aud, other_expr = aud.roll(shift, dims=1), expr.roll(shift, dims=1)
        audio_side = self.quantize(aud, other_expr, sample, generator)
        expr_side = self.quantize(other_aud, expr, sample, generator)
        return MeshTalkForward(
            reconstruction,
            self.decode(templates, audio_side.one_hot),
            self.decode(templates, expr_side.one_hot),
            own,
        )

    def loss(
        self, out: MeshTalkForward, vertices: Tensor, motion_mask: Tensor | None = None
    ) -> MeshTalkLoss:
        """:func:`meshtalk_loss` with this model's region maps, scale and weights."""
        return meshtalk_loss(
            out,
            vertices,
            self.mouth_weight,
            self.upper_weight,
            self.eyelid_mask,
            motion_mask,
            self.offset_scale,
            self.config.loss,
        )

    # -- applications (paper Sec. 4.3-4.4) ------------------------------------------------------

    @torch.inference_mode()
    def retarget(
        self,
        vertices: Tensor,
        source_templates: Tensor,
        audio: Tensor,
        target_templates: Tensor,
        audio_lengths: Tensor | None = None,
    ) -> Tensor:
        """Re-targeting: encode the source animation (B, T, V, 3) with its audio, decode on other
        neutral meshes (B, V, 3) -> (B, T, V, 3). No prior needed."""
        codes = self.encode(vertices, source_templates, audio, audio_lengths, sample=False).codes
        return self.decode(target_templates, codes)

    @torch.inference_mode()
    def dub(
        self,
        vertices: Tensor,
        templates: Tensor,
        audio: Tensor,
        audio_lengths: Tensor | None = None,
    ) -> Tensor:
        """Mesh dubbing: the original animation (B, T, V, 3) supplies the expression input (upper face:
        blinks, brows), the new audio (B, S) drives the mouth; decoded on ``templates`` (B, V, 3).

        The new audio is read at the animation's T frames; it should cover them (frames past its end
        see silence).
        """
        codes = self.encode(vertices, templates, audio, audio_lengths, sample=False).codes
        return self.decode(templates, codes)


# ---------------------------------------------------------------------------------------------
# 8. Autoregressive prior


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
            _fail("meshtalk prior: audio_source is expression: use MeshTalkModel.audio_features")
        return self.audio_encoder(audio, audio_lengths, num_frames)

    def _check(self, audio_features: Tensor, codes: Tensor | None = None) -> None:
        cfg = self.config
        if audio_features.ndim != 3 or audio_features.shape[-1] != cfg.audio.out_dim:
            _fail(
                f"meshtalk prior: audio features must be (B, T, {cfg.audio.out_dim}), "
                f"got {tuple(audio_features.shape)}"
            )
        if codes is not None:
            if codes.ndim != 3 or codes.shape[-1] != cfg.num_heads or codes.is_floating_point():
                _fail(
                    f"meshtalk prior: codes must be int (B, T, {cfg.num_heads}), got {tuple(codes.shape)}"
                )
            if codes.numel() and (int(codes.min()) < 0 or int(codes.max()) >= cfg.num_classes):
                _fail(f"meshtalk prior: codes must lie in [0, {cfg.num_classes})")
            if (
                codes.shape[0] != audio_features.shape[0]
                or codes.shape[1] > audio_features.shape[1]
            ):
                _fail("meshtalk prior: codes need audio features for the same batch and frames")

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

    @staticmethod
    def _draw(
        logits: Tensor,
        temperature: float,
        top_k: int | None,
        argmax: bool,
        generator: torch.Generator | None,
    ) -> Tensor:
        """(B, C) logits -> (B,) class ids."""
        if argmax:
            return logits.argmax(-1)
        logits = logits / temperature
        if top_k is not None and top_k < logits.shape[-1]:
            kth = torch.topk(logits, top_k, dim=-1).values[:, -1:]
            logits = logits.masked_fill(logits < kth, float("-inf"))
        probs = torch.softmax(logits.double(), dim=-1)
        return torch.multinomial(probs, 1, generator=generator)[:, 0]

    def _check_sampling(
        self, audio_features: Tensor, temperature: float, top_k: int | None, prompt: Tensor | None
    ) -> int:
        self._check(audio_features, prompt)
        if temperature <= 0:
            _fail("meshtalk prior: temperature must be positive (use argmax=True for greedy)")
        if top_k is not None and top_k < 1:
            _fail("meshtalk prior: top_k must be at least 1")
        return 0 if prompt is None else prompt.shape[1]

    @torch.inference_mode()
    def sample(
        self,
        audio_features: Tensor,
        *,
        temperature: float = 1.0,
        top_k: int | None = None,
        argmax: bool = False,
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
                c = self._draw(logits, temperature, top_k, argmax, generator)
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
                codes[:, t, h] = self._draw(logits, temperature, top_k, argmax, generator)
        return codes


# ---------------------------------------------------------------------------------------------
# 9. The released model: expression space + prior behind talkmesh's common model surface


@dataclass(frozen=True)
class SamplingConfig:
    """How :meth:`MeshTalkModel.generate` draws codes from the prior (defaults of a release)."""

    temperature: float = 1.0
    top_k: int | None = None
    argmax: bool = False

    def __post_init__(self) -> None:
        if self.temperature <= 0:
            _fail("meshtalk sampling: temperature must be positive (argmax: true for greedy)")
        if self.top_k is not None and self.top_k < 1:
            _fail("meshtalk sampling: top_k must be at least 1")


@dataclass(frozen=True)
class MeshTalkModelConfig:
    """A MeshTalk release: the expression space, the prior (None while only the expression space
    is trained: re-targeting and dubbing need no prior) and the sampling defaults."""

    model: MeshTalkConfig
    prior: PriorConfig | None = None
    sampling: SamplingConfig = SamplingConfig()

    def __post_init__(self) -> None:
        p, m = self.prior, self.model
        if p is not None and (p.num_heads, p.num_classes) != (m.num_heads, m.num_classes):
            _fail("meshtalk: the prior's num_heads/num_classes must match the expression space")
        if p is not None and p.audio_source == "expression" and p.audio.out_dim != m.audio.out_dim:
            _fail("meshtalk: a prior on the expression space's audio needs its audio.out_dim")


class MeshTalkModel(nn.Module):
    """MeshTalk as ``talkmesh animate`` uses it: audio -> prior codes -> decoded template.

    Same surface as the other families (``talkmesh.models.release``); no speaker styles
    (``styles == ()``): what is not in the audio is sampled, so ``seed`` changes blinks and brows.
    """

    family = "meshtalk"

    def __init__(self, cfg: MeshTalkModelConfig, maps=(None, None, None)) -> None:
        super().__init__()
        self.model = MeshTalk(cfg.model, *maps)
        self.prior = AutoregressivePrior(cfg.prior) if cfg.prior is not None else None
        self.cfg = replace(cfg, model=self.model.config)  # a pretrained speech encoder's release

    def audio_features(
        self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int
    ) -> Tensor:
        """(B, S) -> (B, T, Da): the prior's conditioning (its own encoder, or the expression
        space's audio encoder, frozen, when ``prior.audio_source`` is expression)."""
        if self.prior is not None and self.prior.audio_encoder is not None:
            return self.prior.audio_features(audio, audio_lengths, num_frames)
        with torch.no_grad():
            return self.model.audio_encoder(audio, audio_lengths, num_frames)

    @property
    def num_vertices(self) -> int:
        return self.cfg.model.num_vertices

    @property
    def motion_fps(self) -> float:
        return self.cfg.model.fps

    @property
    def styles(self) -> tuple[str, ...]:
        return ()

    @torch.inference_mode()
    def sample_codes(
        self,
        audio: Tensor,
        *,
        audio_lengths: Tensor | None = None,
        num_frames: int | None = None,
        seed: int = 0,
        temperature: float | None = None,
        top_k: int | None = None,
        argmax: bool | None = None,
        cached: bool = True,
        progress: bool = False,
    ) -> Tensor:
        """(B, S) audio at 16 kHz -> codes (B, T, H) from the prior; ``cached=False`` uses the
        reference sampler that recomputes the whole history (same draws, for checks and timing)."""
        if self.prior is None:
            _fail(
                "this MeshTalk release has no prior (expression space only): train the "
                "meshtalk-prior stage, or use it for retarget/dub"
            )
        if audio.ndim != 2:
            _fail(f"meshtalk: audio must be (B, S), got {tuple(audio.shape)}")
        s = self.cfg.sampling
        if num_frames is None:
            num_frames = max(1, round(audio.shape[1] / SAMPLE_RATE * self.motion_fps))
        features = self.audio_features(audio, audio_lengths, num_frames)
        generator = torch.Generator(device=audio.device).manual_seed(int(seed))
        kwargs = dict(
            temperature=s.temperature if temperature is None else temperature,
            top_k=s.top_k if top_k is None else top_k,
            argmax=s.argmax if argmax is None else argmax,
            generator=generator,
        )
        if cached:
            return self.prior.sample(features, progress=progress, **kwargs)
        return self.prior.sample_uncached(features, **kwargs)

    @torch.inference_mode()
    def generate(
        self,
        audio: Tensor,
        template: Tensor,
        *,
        style_weights: Tensor | None = None,
        audio_lengths: Tensor | None = None,
        num_frames: int | None = None,
        seed: int = 0,
        **sampling,
    ) -> Tensor:
        """audio (B, S) at 16 kHz, template (B, V, 3) -> vertices (B, T, V, 3). ``style_weights``
        must be None (MeshTalk has no speaker styles); ``sampling``: see :meth:`sample_codes`."""
        if style_weights is not None:
            _fail("MeshTalk has no speaker styles: drop --style")
        _check_mesh("template", template, self.num_vertices, 3)
        codes = self.sample_codes(
            audio, audio_lengths=audio_lengths, num_frames=num_frames, seed=seed, **sampling
        )
        return self.model.decode(template.to(audio.dtype), codes)
