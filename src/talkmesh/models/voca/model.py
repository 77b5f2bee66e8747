"""VOCA (Cudeiro et al., CVPR 2019, "Capture, Learning, and Synthesis of 3D Speaking Styles").

A per-frame regressor from a window of speech features to vertex offsets; no recurrence, no
autoregression, so every motion frame is predicted independently of the others:

1. Speech features at ``tokens_per_frame`` x the motion rate (60 Hz for 30 fps motion, the rate
   VOCA's windows were cut at) from a talkmesh speech encoder, normalised per channel with fixed
   statistics of the training data (buffers set by :meth:`VOCA.set_feature_statistics`).
2. For motion frame t, the window of ``window_before`` tokens before the frame's token and
   ``window_after`` from it on (8 + 8 = 16 tokens, the paper's 16-frame window), zero-padded at
   the ends; the speaker one-hot (or, for unseen speakers, weights over the training speakers) is
   concatenated to every token as extra channels (the paper's first "identity concat").
3. Encoder (paper Fig. 2 / Table 1): four temporal convolutions (kernel 3, stride 2: 16 -> 8 -> 4
   -> 2 -> 1 tokens; 32, 32, 64, 64 channels, ReLU), the speaker vector concatenated again, FC 128
   with tanh, FC to a 50-d latent (linear).
4. Decoder: one linear layer latent -> V*3 offsets, initialised from a PCA of the training offsets
   (vertices - template) with each direction scaled by its standard deviation (singular value /
   sqrt(frames)), so unit-variance latents span the data's motion (:meth:`VOCA.set_basis`); the
   offsets are added to the template.
5. Loss (Sec. 4): position term ||y - y_hat||^2 plus velocity term
   ||(y_t - y_{t-1}) - (y_hat_t - y_hat_{t-1})||^2, squared distances summed over vertices and
   averaged over the valid frames (pairs), weighted 1 and 10 by default (:func:`voca_loss`).

Differences from the original:

* Speech features: VOCA used DeepSpeech 0.1 character logits (29-d, 50 Hz, resampled to the video
  rate). They are not available here; any talkmesh speech encoder (``mel`` trained from scratch,
  ``wav2vec2``, ``whisper``; see :mod:`talkmesh.models.speech`) is used instead, at
  ``motion_fps * tokens_per_frame`` tokens per second. A frozen ASR encoder (Whisper, or
  wav2vec 2.0 fine-tuned for ASR) is the closest to DeepSpeech.
* The input batch normalisation is replaced by fixed per-channel statistics of the training
  features, so the output of a sample never depends on the rest of its batch (a padded batch gives
  the same result per sample as running it alone).
* Training batches are cropped sequences (masked) instead of random pairs of consecutive frames;
  the velocity term uses every valid pair of consecutive frames.
* The PCA is centred and the decoder bias starts at the mean offset (the original starts it at
  zero); the basis is computed exactly from a subsample of training frames.
* Frames are at the dataset's motion rate (30 fps for VOCASET as the field reads it), not 60 fps.

Axis letters: B batch, S audio samples, T motion frames, N speech tokens, V vertices, K training
speakers, D feature width, W window length (tokens), L latent width.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.constants import MOTION_FPS, SAMPLE_RATE
from talkmesh.errors import TalkmeshError
from talkmesh.models.base import MotionModel, frames_for_audio
from talkmesh.models.speech import SpeechEncoderConfig, build_speech_encoder, release_config

GENERATE_CHUNK = 4096  # frames whose windows are encoded at once when generating (bounds memory)
STD_FLOOR = 1e-5  # feature channels with less spread than this are only centred

# ---------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True)
class VOCAConfig:
    """VOCA's sizes (paper Table 1) plus the talkmesh speech encoder it reads.

    ``speech.frame_rate`` is derived: ``motion_fps * tokens_per_frame``.
    """

    num_vertices: int
    styles: tuple[str, ...] = ()  # training speakers, in one-hot order (() : no conditioning)
    motion_fps: float = MOTION_FPS
    speech: SpeechEncoderConfig = SpeechEncoderConfig()
    tokens_per_frame: int = 2  # speech tokens per motion frame: 60 Hz windows at 30 fps, as VOCA
    window_before: int = 8  # tokens before the frame's own token
    window_after: int = 8  # tokens from the frame's token on (8 + 8 = the paper's 16)
    conv_channels: tuple[int, ...] = (32, 32, 64, 64)  # stride-2 temporal convolutions
    kernel_size: int = 3
    hidden: int = 128  # the FC layer after the convolutions (tanh)
    latent: int = 50  # the expression latent: PCA components of the decoder
    position_weight: float = 1.0
    velocity_weight: float = 10.0  # the released training config's velocity weight

    def __post_init__(self) -> None:
        if self.num_vertices < 1:
            raise ValueError("num_vertices must be at least 1")
        if self.motion_fps <= 0:
            raise ValueError("motion_fps must be positive")
        if self.tokens_per_frame < 1:
            raise ValueError("tokens_per_frame must be at least 1")
        if self.window_before < 0 or self.window_after < 1:
            raise ValueError("window_before must be >= 0 and window_after >= 1")
        if not self.conv_channels or min(self.conv_channels) < 1:
            raise ValueError("conv_channels must list at least one positive width")
        if self.kernel_size < 1 or self.hidden < 1 or self.latent < 1:
            raise ValueError("kernel_size, hidden and latent must be at least 1")
        if self.position_weight < 0 or self.velocity_weight < 0:
            raise ValueError("position_weight and velocity_weight must be >= 0")
        if len(set(self.styles)) != len(self.styles):
            raise ValueError("styles must be distinct speaker names")
        rate = self.motion_fps * self.tokens_per_frame
        if self.speech.frame_rate != rate:
            object.__setattr__(self, "speech", replace(self.speech, frame_rate=rate))

    @property
    def window(self) -> int:
        """W: tokens per frame window."""
        return self.window_before + self.window_after


def small_config(
    styles: tuple[str, ...], num_vertices: int, motion_fps: float = MOTION_FPS
) -> VOCAConfig:
    """The paper's network sizes on a mel encoder trained from scratch (CPU-trainable)."""
    return VOCAConfig(
        num_vertices=num_vertices,
        styles=styles,
        motion_fps=motion_fps,
        speech=SpeechEncoderConfig(kind="mel", dim=128),
    )


def paper_vocaset_config(
    styles: tuple[str, ...] = tuple(f"speaker{k}" for k in range(8)),
) -> VOCAConfig:
    """Table 1 on VOCASET's FLAME topology, reading a frozen ASR encoder in place of DeepSpeech
    (wav2vec 2.0 base fine-tuned for ASR; set ``speech.source``)."""
    return VOCAConfig(
        num_vertices=5023,
        styles=styles,
        speech=SpeechEncoderConfig(kind="wav2vec2", frozen=True),
    )


# ---------------------------------------------------------------------------------------------
# Loss


class VOCALoss(NamedTuple):
    loss: Tensor  # () weighted sum
    position: Tensor  # () mean over valid frames of the summed squared vertex error
    velocity: Tensor  # () mean over valid consecutive pairs of the summed squared velocity error


def voca_loss(
    pred: Tensor,
    target: Tensor,
    mask: Tensor | None = None,
    *,
    position_weight: float = 1.0,
    velocity_weight: float = 10.0,
) -> VOCALoss:
    """pred, target (B, T, V*3) offsets, mask (B, T) bool (None: all valid) -> VOCA's loss.

    Position: ||y_t - y_hat_t||^2 per frame; velocity: ||(y_t - y_{t-1}) - (y_hat_t - y_hat_{t-1})||^2
    per pair of consecutive valid frames (VOCA Sec. 4, "Loss function").
    """
    if pred.shape != target.shape or pred.dim() != 3:
        raise TalkmeshError(
            f"voca loss: pred and target must both be (B, T, V*3), got {tuple(pred.shape)} "
            f"and {tuple(target.shape)}"
        )
    if mask is None:
        mask = torch.ones(pred.shape[:2], dtype=torch.bool, device=pred.device)
    w = mask.to(pred.dtype)
    err = pred - target
    position = ((err.square().sum(-1)) * w).sum() / w.sum().clamp(min=1)
    pairs = w[:, 1:] * w[:, :-1]
    velocity = ((err[:, 1:] - err[:, :-1]).square().sum(-1) * pairs).sum() / pairs.sum().clamp(
        min=1
    )
    return VOCALoss(position_weight * position + velocity_weight * velocity, position, velocity)


# ---------------------------------------------------------------------------------------------
# PCA of the training motion


def principal_directions(x: Tensor, k: int) -> tuple[Tensor, Tensor, Tensor]:
    """x (N, D) rows of data -> (mean (D,), directions (k', D) orthonormal rows, singular values
    (k',)) of the centred data, largest first, k' = min(k, rank). Exact: an eigendecomposition of
    the smaller of the two Gram matrices, in float64."""
    x = x.to(torch.float64)
    mean = x.mean(0)
    xc = x - mean
    n, d = xc.shape
    if n <= d:  # xc xc^T = U S^2 U^T; directions V = xc^T U / S
        evals, evecs = torch.linalg.eigh(xc @ xc.T)
    else:  # xc^T xc = V S^2 V^T
        evals, evecs = torch.linalg.eigh(xc.T @ xc)
    evals, evecs = evals.flip(0), evecs.flip(1)
    keep = evals > evals[0].clamp(min=0) * 1e-12  # drop the null space (rank < k)
    keep[k:] = False
    s = evals[keep].sqrt()
    dirs = (xc.T @ evecs[:, keep] / s).T if n <= d else evecs[:, keep].T
    return mean, dirs, s


# ---------------------------------------------------------------------------------------------
# Model


class VOCAOutput(NamedTuple):
    vertices: Tensor  # (B, T, V, 3) predicted vertices
    loss: Tensor  # () weighted position + velocity loss
    position_loss: Tensor
    velocity_loss: Tensor


class SpeechWindowEncoder(nn.Module):
    """(N, C_in, W) windows of speech tokens + speaker channels, (N, K) speaker vectors -> (N, L)."""

    def __init__(
        self,
        in_channels: int,
        num_styles: int,
        window: int,
        channels: tuple[int, ...],
        kernel_size: int,
        hidden: int,
        latent: int,
    ) -> None:
        super().__init__()
        dims = (in_channels, *channels)
        self.convs = nn.ModuleList(
            nn.Conv1d(a, b, kernel_size, stride=2, padding=kernel_size // 2)
            for a, b in zip(dims[:-1], dims[1:])
        )
        length = window
        for _ in channels:  # each stride-2 conv: L -> floor((L + 2 pad - k) / 2) + 1
            length = (length + 2 * (kernel_size // 2) - kernel_size) // 2 + 1
        if length < 1:
            raise TalkmeshError(
                f"voca: a window of {window} tokens is too short for {len(channels)} stride-2 "
                f"convolutions of kernel {kernel_size}"
            )
        self.fc = nn.Linear(channels[-1] * length + num_styles, hidden)
        self.out = nn.Linear(hidden, latent)

    def forward(self, windows: Tensor, style: Tensor) -> Tensor:
        x = windows
        for conv in self.convs:
            x = F.relu(conv(x))
        x = torch.cat([x.flatten(1), style], dim=1)  # the second "identity concat"
        return self.out(torch.tanh(self.fc(x)))


class VOCA(MotionModel):
    """Speech window + speaker -> per-frame vertex offsets (module docstring)."""

    family = "voca"
    config_class = VOCAConfig

    def __init__(self, cfg: VOCAConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.speech = build_speech_encoder(cfg.speech)
        # a pretrained encoder loaded from a path: the release keeps its config, not the path
        speech_cfg = release_config(cfg.speech, self.speech)
        if speech_cfg is not cfg.speech:
            self.cfg = replace(cfg, speech=speech_cfg)
        dim, k = self.speech.dim, len(cfg.styles)
        self.register_buffer("feature_mean", torch.zeros(dim))
        self.register_buffer("feature_std", torch.ones(dim))
        self.encoder = SpeechWindowEncoder(
            dim + k, k, cfg.window, cfg.conv_channels, cfg.kernel_size, cfg.hidden, cfg.latent
        )
        self.decoder = nn.Linear(cfg.latent, cfg.num_vertices * 3)
        # until set_basis: the template, unmoved
        nn.init.zeros_(self.decoder.weight)
        nn.init.zeros_(self.decoder.bias)

    @property
    def num_vertices(self) -> int:
        return self.cfg.num_vertices

    @property
    def motion_fps(self) -> float:
        return self.cfg.motion_fps

    @property
    def styles(self) -> tuple[str, ...]:
        return tuple(self.cfg.styles)

    @classmethod
    def tiny_config(
        cls, num_vertices: int = 30, styles: tuple[str, ...] = ("a", "b")
    ) -> VOCAConfig:
        return VOCAConfig(
            num_vertices=num_vertices,
            styles=styles,
            speech=SpeechEncoderConfig(kind="mel", dim=16),
            conv_channels=(8, 8, 16, 16),
            hidden=16,
            latent=6,
        )

    # -- preparation from training data ---------------------------------------------------------

    @torch.no_grad()
    def set_basis(self, offsets: Tensor) -> None:
        """Initialise the decoder from a PCA of training offsets (N, V*3) (vertices - template).

        Column l of the weight is the l-th principal direction times its standard deviation
        (singular value / sqrt(N)); the bias is the mean offset. Components beyond the data's rank
        stay zero.
        """
        V3 = self.cfg.num_vertices * 3
        if offsets.dim() != 2 or offsets.shape[1] != V3:
            raise TalkmeshError(
                f"voca: PCA offsets must be (frames, {V3}), got {tuple(offsets.shape)}"
            )
        mean, dirs, s = principal_directions(offsets, self.cfg.latent)
        scale = s / offsets.shape[0] ** 0.5
        weight = torch.zeros_like(self.decoder.weight, dtype=torch.float64)
        weight[:, : len(s)] = (dirs * scale[:, None]).T
        self.decoder.weight.copy_(weight)
        self.decoder.bias.copy_(mean)

    @torch.no_grad()
    def set_feature_statistics(self, features: Tensor) -> None:
        """Per-channel mean and std of speech features (..., D) from the training audio: VOCA's
        input batch normalisation, frozen (buffers travel with the weights)."""
        flat = features.reshape(-1, features.shape[-1]).to(torch.float64)
        self.feature_mean.copy_(flat.mean(0))
        self.feature_std.copy_(flat.std(0, unbiased=False).clamp(min=STD_FLOOR))

    # -- pieces ---------------------------------------------------------------------------------

    def speaker_vectors(self, styles: Tensor | None, weights: Tensor | None, batch: int) -> Tensor:
        """(B,) style ids or (B, K) weights over the training speakers -> (B, K) speaker vectors
        (the one-hot, or a mix of speakers for an unseen one)."""
        K = len(self.cfg.styles)
        dtype = self.decoder.weight.dtype
        if weights is not None:
            if weights.shape != (batch, K):
                raise TalkmeshError(
                    f"style weights must be (batch, {K}) = ({batch}, {K}) (one per training "
                    f"speaker: {', '.join(self.styles)}), got {tuple(weights.shape)}"
                )
            return weights.to(dtype)
        if K == 0:
            return self.decoder.weight.new_zeros(batch, 0)
        if styles is None or (styles < 0).any() or (styles >= K).any():
            raise TalkmeshError("an unseen speaker needs style weights (e.g. --style A:0.5,B:0.5)")
        return F.one_hot(styles.long(), K).to(dtype)

    def speech_tokens(self, audio: Tensor, audio_lengths: Tensor | None, frames: Tensor) -> Tensor:
        """audio (B, S), valid samples (B,) or None (then each sample's audio ends with its last
        valid frame), valid frames (B,) -> normalised tokens (B, T * tokens_per_frame, D), zero
        past each sample's valid tokens, T = frames.max().

        The encoders resample each sample's own features to the requested count (Whisper,
        wav2vec 2.0), so samples of different lengths are encoded in groups of equal length:
        a sample gets the same tokens in any padded batch as alone.
        """
        B, S = audio.shape
        k = self.cfg.tokens_per_frame
        T = int(frames.max())
        counts = frames.tolist()
        if audio_lengths is not None:
            lengths = audio_lengths.tolist()
        else:  # a sample's audio ends with its last valid frame
            per_frame = SAMPLE_RATE / self.cfg.motion_fps
            lengths = [S if t == T else min(S, round(t * per_frame)) for t in counts]
        if all(n == S for n in lengths) and all(t == T for t in counts):
            feats = self.speech(audio, None, T * k)
        else:
            feats = None
            groups: dict[tuple[int, int], list[int]] = {}
            for b, key in enumerate(zip(lengths, counts)):
                groups.setdefault((int(key[0]), int(key[1])), []).append(b)
            for (n, t), ids in groups.items():
                part = self.speech(audio[ids, :n], None, t * k)
                if feats is None:
                    feats = part.new_zeros(B, T * k, part.shape[-1])
                feats[ids, : t * k] = part
        tokens = (feats - self.feature_mean) / self.feature_std
        valid = torch.arange(T * k, device=audio.device)[None] < (frames * k)[:, None]
        return tokens * valid[..., None].to(tokens.dtype)

    def offsets(
        self, tokens: Tensor, style: Tensor, start: int = 0, stop: int | None = None
    ) -> Tensor:
        """tokens (B, N, D), speaker vectors (B, K) -> offsets (B, T', V*3) of frames
        [start, stop) (default all N // tokens_per_frame frames)."""
        cfg = self.cfg
        k, W = cfg.tokens_per_frame, cfg.window
        B, N, _ = tokens.shape
        stop = N // k if stop is None else stop
        # frame t's window: tokens t*k - before .. t*k + after - 1, zeros outside the sequence
        a, b = start * k - cfg.window_before, (stop - 1) * k + cfg.window_after
        part = tokens[:, max(0, a) : min(N, b)]
        part = F.pad(part, (0, 0, max(0, -a), max(0, b - N)))
        windows = part.unfold(1, W, k)  # (B, T', D, W)
        Tn = windows.shape[1]
        speaker = style[:, None, :, None].expand(B, Tn, style.shape[1], W)
        x = torch.cat([windows, speaker], dim=2).flatten(0, 1)  # (B*T', D+K, W)
        latent = self.encoder(x, style.repeat_interleave(Tn, dim=0))
        return self.decoder(latent).view(B, Tn, -1)

    def _check_template(self, templates: Tensor) -> None:
        V = self.cfg.num_vertices
        if templates.dim() != 3 or templates.shape[1:] != (V, 3):
            raise TalkmeshError(
                f"template has shape {tuple(templates.shape)}: this VOCA model animates meshes "
                f"of {V} vertices, (B, {V}, 3); use a template of the training topology"
            )

    # -- training -------------------------------------------------------------------------------

    def forward(
        self,
        audio: Tensor,
        audio_lengths: Tensor | None,
        vertices: Tensor,
        templates: Tensor,
        styles: Tensor,
        motion_mask: Tensor | None = None,
    ) -> VOCAOutput:
        """audio (B, S), audio_lengths (B,) | None, vertices (B, T, V, 3), templates (B, V, 3),
        styles (B,) (-1: a speaker outside the training set, who gets equal weights over the
        training speakers), motion_mask (B, T) bool | None -> predictions and VOCA's loss."""
        self._check_template(templates)
        B, T = vertices.shape[:2]
        if vertices.shape[2:] != templates.shape[1:] or templates.shape[0] != B:
            raise TalkmeshError(
                f"vertices {tuple(vertices.shape)} do not match templates {tuple(templates.shape)}"
            )
        K = len(self.cfg.styles)
        seen = styles.clamp(min=0)
        if K:
            onehot = F.one_hot(seen.long(), K).to(vertices.dtype)
            style = torch.where((styles >= 0)[:, None], onehot, torch.full_like(onehot, 1 / K))
        else:
            style = vertices.new_zeros(B, 0)
        frames = (
            motion_mask.sum(1).clamp(min=1)
            if motion_mask is not None
            else torch.full((B,), T, device=vertices.device)
        )
        tokens = self.speech_tokens(audio, audio_lengths, frames)
        if tokens.shape[1] < T * self.cfg.tokens_per_frame:  # every sample shorter than T
            tokens = F.pad(tokens, (0, 0, 0, T * self.cfg.tokens_per_frame - tokens.shape[1]))
        pred = self.offsets(tokens, style, 0, T)
        target = (vertices - templates[:, None]).flatten(2)
        loss = voca_loss(
            pred,
            target,
            motion_mask,
            position_weight=self.cfg.position_weight,
            velocity_weight=self.cfg.velocity_weight,
        )
        out = templates[:, None] + pred.view(B, T, -1, 3)
        return VOCAOutput(out, loss.loss, loss.position, loss.velocity)

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
        seed: int = 0,
        mode: str = "fast",
    ) -> Tensor:
        """audio (B, S) at 16 kHz, template (B, V, 3) -> vertices (B, T, V, 3).

        Deterministic and non-autoregressive (one mode, ``fast``) (``seed`` is accepted for the common model surface
        and unused). T = ``num_frames`` or the audio's duration at ``motion_fps``; with
        ``audio_lengths`` each sample has round(length * fps / 16000) frames (at most T) and rests
        at its template after them.
        """
        self.check_mode(mode)
        if audio.dim() != 2:
            raise TalkmeshError(f"audio must be (B, S), got {tuple(audio.shape)}")
        self._check_template(template)
        B, S = audio.shape
        if template.shape[0] != B:
            raise TalkmeshError(f"{B} audio clips but {template.shape[0]} templates")
        fps = self.cfg.motion_fps
        T = num_frames if num_frames is not None else frames_for_audio(S, fps)
        if T < 1:
            raise TalkmeshError("num_frames must be at least 1")
        if audio_lengths is None:
            frames = torch.full((B,), T, device=audio.device)
        else:
            per = torch.round(audio_lengths.double() * fps / SAMPLE_RATE).long()
            frames = per.clamp(1, T).to(audio.device)
        style = self.speaker_vectors(styles, style_weights, B)
        tokens = self.speech_tokens(audio, audio_lengths, frames)
        k = self.cfg.tokens_per_frame
        tokens = F.pad(tokens, (0, 0, 0, T * k - tokens.shape[1]))
        out = template[:, None].repeat(1, T, 1, 1)  # (B, T, V, 3)
        for start in range(0, T, GENERATE_CHUNK):
            stop = min(T, start + GENERATE_CHUNK)
            out[:, start:stop] += self.offsets(tokens, style, start, stop).view(
                B, stop - start, -1, 3
            )
        past = torch.arange(T, device=out.device)[None] >= frames[:, None]
        out[past] = template[:, None].expand(B, T, -1, -1)[past]
        return out


__all__ = [
    "VOCA",
    "VOCAConfig",
    "VOCALoss",
    "VOCAOutput",
    "paper_vocaset_config",
    "principal_directions",
    "small_config",
    "voca_loss",
]
