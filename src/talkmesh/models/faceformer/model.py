"""FaceFormer (Fan et al., CVPR 2022): speech-driven 3D facial animation with transformers.

    model = FaceFormer(vocaset_config(styles))
    out = model(audio, audio_lengths, vertices, templates, styles, motion_mask)  # training
    vertices = model.generate(audio, template, styles=torch.tensor([0]))  # (B, T, V, 3)

The model (paper Sec. 3, Fig. 2), one decoder step per motion frame t:

* Audio encoder: a speech encoder (wav2vec 2.0 in the paper; any of talkmesh's pluggable encoders
  here) gives k features per motion frame, mapped linearly to ``d_model``.
* Decoder input: the motion of frame t-1 (offsets from the template) through a linear motion
  encoder, plus the speaker's style embedding (a learned vector per training speaker: the paper's
  one-hot times a matrix), plus the periodic positional encoding (PPE), a sinusoid of
  ``t mod period``. Frame 0 reads zero offsets (the neutral face) as its previous frame.
* Decoder layers: biased causal self-attention, whose ALiBi-like temporal bias is
  ``-slope_h * floor((i - j) / period)`` for keys j <= i; biased cross-modal attention whose
  alignment bias lets frame t see only its own audio token(s); a feed-forward network.
* Motion decoder: a zero-initialised linear map to V*3 offsets; the template is added.
* Loss: mean squared error of the offsets (that is, of the vertices).

Differences from the paper and the official code, and why:

* Training. The paper trains autoregressively on its own predictions: T decoder passes per
  sequence. ``teacher_forcing=False`` does that (the official training loop, run by the training
  task, training/faceformer.py; the paper recipes switch it on). By default ``forward`` is
  teacher forced in one pass, and ``self_feedback`` (a fraction) of the fed-back frames are
  replaced by the model's own predictions from a first teacher-forced pass, detached (parallel
  scheduled sampling, Duckworth et al. 2019), so that it learns to continue from its own,
  imperfect motion (exposure bias) at the cost of two passes instead of T.
* Layers are talkmesh's pre-LN ``Block`` (GELU, a final LayerNorm, no dropout inside) where the
  official code uses PyTorch's post-LN ``TransformerDecoderLayer`` (ReLU, dropout 0.1);
  ``dropout`` acts on the decoder input, like the official PPE's dropout.
* Cross-attention onto one aligned audio token (VOCASET) has a single key: its softmax is 1, so
  it is exactly a linear map of that token, computed for all frames at once (no attention
  matrix). With k tokens per frame (BIWI: k = 2) the frame attends uniformly to its k tokens
  (their mean), where the official softmax weighs them by the query.
* Speech features are resampled to the motion rate after the encoder; the official code
  interpolates wav2vec 2.0's CNN features before its transformer.
* Offsets are divided by one scale (the RMS of the training offsets, a buffer fitted by the
  training task, 1 until then) so the motion encoder's inputs and the loss are about 1 in any
  units; the loss changes by a constant factor only.
* No 600-frame length cap: attention sees the last ``attention_window`` frames, in training and
  generation alike. ``generate(mode="fast")`` caches keys and values (cost linear in length);
  ``mode="naive"`` is the official loop (the whole decoder over the whole prefix at every step);
  both give the same frames.
* Padding masks hold for any batch size, and an unseen speaker takes style weights over the
  training speakers (e.g. their mean) instead of one training speaker's one-hot.

Models imported from the released weights (``talkmesh import-checkpoint``, faceformer/official.py)
switch on ``postnorm``, ``interleaved_ppe``, ``frame0_motion_bias=False`` and the speech
encoder's ``resample="cnn"`` and ``normalize``: then generation equals the official ``predict``
(docs/guide/official.md has the table of official vs default and why).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.constants import MOTION_FPS
from talkmesh.errors import TalkmeshError
from talkmesh.models.base import MotionModel, frames_for_audio
from talkmesh.models.layers import (
    Block,
    KVCache,
    folded_linear,
    periodic_encoding,
    temporal_bias,
)
from talkmesh.models.postnorm import PostNormDecoderLayer, interleaved_encoding
from talkmesh.models.speech import SpeechEncoderConfig, build_speech_encoder, release_config
from talkmesh.models.threads import step_threads

MODES = ("fast", "naive")
OUTPUT_CHUNK = 512  # frames decoded to vertices at once at the end of fast generation

# ---------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True)
class FaceFormerConfig:
    """The official sizes: VOCASET d_model 64, period 30; BIWI d_model 128, period 25, two audio
    tokens per frame; both 4 heads, FF 2 x d_model, one decoder layer."""

    num_vertices: int
    styles: tuple[str, ...]  # training speakers, in one-hot order
    motion_fps: float = MOTION_FPS
    d_model: int = 64
    heads: int = 4
    ff: int = 128
    layers: int = 1
    period: int = 30  # frames of the PPE and of the temporal bias
    audio_tokens_per_frame: int = 1  # k: speech features aligned with each motion frame
    speech: SpeechEncoderConfig = SpeechEncoderConfig()  # frame_rate = motion_fps x k
    dropout: float = 0.1  # on the decoder input (the official PPE dropout)
    attention_window: int = 600  # frames of self-attention (the official length cap)
    self_feedback: float = 0.0  # training: fraction of fed-back frames that are the model's own
    # one-pass predictions instead of the truth (0: plain teacher forcing; see the module doc)
    teacher_forcing: bool = True  # training: False feeds back every frame's own prediction, as
    # the paper and the official loop do (T decoder passes per sequence; training/faceformer.py)
    # official-exact options (on in models imported from the released weights; docs/guide/official.md):
    postnorm: bool = False  # the official decoder layers: post-norm, ReLU, dropout inside, real
    # attention over the frame's k aligned audio tokens, no final norm (models/postnorm.py)
    interleaved_ppe: bool = False  # the official PPE channel order (sin/cos interleaved)
    frame0_motion_bias: bool = True  # generation's frame 0 reads motion_map(0) (= its bias), as
    # in training; the official generation feeds the style vector alone

    def __post_init__(self) -> None:
        for name in (
            "num_vertices",
            "d_model",
            "heads",
            "ff",
            "period",
            "audio_tokens_per_frame",
            "attention_window",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1")
        if self.layers < 0:
            raise ValueError("layers must be >= 0")
        if self.d_model % self.heads:
            raise ValueError("d_model must be divisible by heads")
        if not self.styles:
            raise ValueError("styles must name at least one training speaker")
        if self.motion_fps <= 0:
            raise ValueError("motion_fps must be positive")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError("dropout must be in [0, 1)")
        if not 0.0 <= self.self_feedback <= 1.0:
            raise ValueError("self_feedback must be in [0, 1]")
        if not self.teacher_forcing and self.self_feedback:
            raise ValueError(
                "self_feedback mixes teacher forcing with own predictions: with "
                "teacher_forcing False every fed-back frame is already the model's own"
            )
        rate = self.motion_fps * self.audio_tokens_per_frame
        if abs(self.speech.frame_rate - rate) > 1e-6:
            raise ValueError(
                f"speech.frame_rate must be motion_fps x audio_tokens_per_frame = {rate:g}, "
                f"got {self.speech.frame_rate:g}"
            )


def vocaset_config(
    styles: tuple[str, ...] = tuple(f"speaker{k}" for k in range(8)), num_vertices: int = 5023
) -> FaceFormerConfig:
    """The official VOCASET setup: d_model 64, period 30, wav2vec 2.0 base (960 h) at 30 fps."""
    return FaceFormerConfig(
        num_vertices=num_vertices,
        styles=styles,
        speech=SpeechEncoderConfig(kind="wav2vec2", source="facebook/wav2vec2-base-960h"),
    )


def biwi_config(
    styles: tuple[str, ...] = tuple(f"speaker{k}" for k in range(6)), num_vertices: int = 23370
) -> FaceFormerConfig:
    """The official BIWI setup: d_model 128, period 25, two wav2vec 2.0 tokens per 25 fps frame."""
    return FaceFormerConfig(
        num_vertices=num_vertices,
        styles=styles,
        motion_fps=25.0,
        d_model=128,
        ff=256,
        period=25,
        audio_tokens_per_frame=2,
        speech=SpeechEncoderConfig(
            kind="wav2vec2", source="facebook/wav2vec2-base-960h", frame_rate=50.0
        ),
    )


def small_synth_config(styles: tuple[str, ...], num_vertices: int = 4766) -> FaceFormerConfig:
    """A CPU-trainable configuration for the synthetic corpus (mel speech encoder)."""
    return FaceFormerConfig(
        num_vertices=num_vertices,
        styles=styles,
        d_model=128,
        ff=256,
        layers=2,
        speech=SpeechEncoderConfig(kind="mel", dim=128),
    )


# ---------------------------------------------------------------------------------------------
# The model


def decoder_bias(
    heads: int,
    q_len: int,
    k_len: int,
    period: int,
    window: int,
    device: torch.device | str | None = None,
    q_offset: int = 0,
) -> Tensor:
    """(heads, q_len, k_len) causal periodic temporal bias that also hides keys ``window`` or more
    frames before the query (what a key/value cache of ``window`` frames keeps)."""
    bias = temporal_bias(heads, q_len, k_len, period, device, q_offset)
    i = torch.arange(q_len, device=device)[:, None] + q_offset
    j = torch.arange(k_len, device=device)[None]
    return bias.masked_fill((j <= i - window)[None], float("-inf"))


def masked_mse(pred: Tensor, target: Tensor, mask: Tensor | None) -> Tensor:
    """pred, target (B, T, D), mask (B, T) bool or None -> () mean squared error over the
    valid frames."""
    err = (pred - target).pow(2)
    if mask is None:
        return err.mean()
    w = mask[:, :, None].to(err.dtype)
    return (err * w).sum() / (w.sum() * err.shape[-1]).clamp(min=1)


class FaceFormerOutput(NamedTuple):
    motion: Tensor  # (B, T, V*3) predicted offsets from the template (teacher forced)
    loss: Tensor  # () masked MSE of the offsets, in units of the motion scale


class FaceFormer(MotionModel):
    """Speech encoder -> biased causal transformer decoder -> motion decoder (the module doc);
    ``forward`` is the teacher-forced training graph, ``generate`` the autoregressive loop."""

    family = "faceformer"
    config_class = FaceFormerConfig
    generation_modes = MODES

    def __init__(self, cfg: FaceFormerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d, vertex_dims = cfg.d_model, cfg.num_vertices * 3
        self.speech = build_speech_encoder(cfg.speech)
        # a pretrained encoder loaded from a path: the release keeps its config, not the path
        speech_cfg = release_config(cfg.speech, self.speech)
        if speech_cfg is not cfg.speech:
            self.cfg = replace(cfg, speech=speech_cfg)
        self.audio_map = nn.Linear(self.speech.dim, d)  # audio_feature_map
        self.style = nn.Embedding(len(cfg.styles), d)  # obj_vector (one-hot x matrix)
        self.motion_map = nn.Linear(vertex_dims, d)  # vertice_map: the motion encoder
        self.dropout = nn.Dropout(cfg.dropout)
        if cfg.postnorm:
            self.blocks = nn.ModuleList(
                PostNormDecoderLayer(d, cfg.heads, cfg.ff, cfg.dropout) for _ in range(cfg.layers)
            )
            self.cross = nn.ModuleList()  # the layers attend to the aligned tokens themselves
            self.norm = nn.Identity()
        else:
            self.blocks = nn.ModuleList(Block(d, cfg.heads, cfg.ff) for _ in range(cfg.layers))
            # cross-modal attention onto the frame's aligned audio token: one key, a linear map
            self.cross = nn.ModuleList(nn.Linear(d, d) for _ in range(cfg.layers))
            self.norm = nn.LayerNorm(d)
        self.out = nn.Linear(d, vertex_dims)  # vertice_map_r: the motion decoder
        nn.init.zeros_(self.out.weight)  # zero-initialised, as in the official code
        nn.init.zeros_(self.out.bias)
        # offsets are read and predicted in units of this scale (set from training data)
        self.register_buffer("scale", torch.ones(()))

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
    ) -> FaceFormerConfig:
        return FaceFormerConfig(
            num_vertices=num_vertices,
            styles=styles,
            d_model=32,
            heads=2,
            ff=64,
            layers=2,
            period=5,
            speech=SpeechEncoderConfig(kind="mel", dim=16),
        )

    @torch.no_grad()
    def set_motion_scale(self, motion: Tensor) -> None:
        """The RMS of training offsets (N, V*3) (vertices - template) becomes the motion unit."""
        rms = motion.double().pow(2).mean().sqrt()
        self.scale.fill_(float(rms) if rms > 0 else 1.0)

    # -- pieces ---------------------------------------------------------------------------------

    def _check(self, audio: Tensor, template: Tensor, name: str = "template") -> None:
        V = self.cfg.num_vertices
        if audio.ndim != 2:
            raise TalkmeshError(
                f"audio must be (batch, samples) at 16 kHz, got shape {tuple(audio.shape)}"
            )
        if template.ndim != 3 or tuple(template.shape[1:]) != (V, 3):
            raise TalkmeshError(
                f"{name} must be (batch, {V}, 3): this model animates {V}-vertex meshes, "
                f"got shape {tuple(template.shape)}"
            )
        if len(template) != len(audio):
            raise TalkmeshError(
                f"audio and {name} batch sizes differ ({len(audio)} and {len(template)})"
            )

    def style_vector(self, styles: Tensor | None, weights: Tensor | None = None) -> Tensor:
        """(B,) training-speaker ids, or (B, K) weights over the K training speakers -> (B, d)."""
        K = len(self.cfg.styles)
        if weights is not None:
            if weights.ndim != 2 or weights.shape[1] != K:
                raise TalkmeshError(
                    f"style_weights must be (batch, {K}), one weight per training speaker "
                    f"({', '.join(self.cfg.styles)}), got shape {tuple(weights.shape)}"
                )
            return weights.to(self.style.weight.dtype) @ self.style.weight
        if styles is None or (styles < 0).any():
            raise TalkmeshError(
                "an unseen speaker needs style weights over the training speakers "
                "(e.g. their mean, or --style A:0.5,B:0.5)"
            )
        if (styles >= K).any():
            raise TalkmeshError(f"style ids must be below {K}, the number of training speakers")
        return self.style(styles)

    def audio_tokens(self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int) -> Tensor:
        """(B, S) -> (B, T, d): the audio token(s) each frame's alignment bias lets it see (with
        k tokens per frame, their mean: uniform attention over them); ``postnorm``: all k tokens,
        (B, T, k, d), for the layers' attention."""
        k = self.cfg.audio_tokens_per_frame
        feats = self.audio_map(self.speech(audio, audio_lengths, num_frames * k))
        if self.cfg.postnorm:
            return feats.view(feats.shape[0], num_frames, k, -1)
        if k > 1:
            feats = feats.view(feats.shape[0], num_frames, k, -1).mean(2)
        return feats

    def cross_terms(self, audio_tokens: Tensor) -> list[Tensor]:
        """Per decoder layer, the (B, T, d) cross-attention output of every frame at once
        (``postnorm``: the (B, T, k, d) tokens, which the layers attend to)."""
        if self.cfg.postnorm:
            return [audio_tokens] * len(self.blocks)
        return [layer(audio_tokens) for layer in self.cross]

    def ppe(self, num_frames: int, device: torch.device, offset: int = 0) -> Tensor:
        """(T, d) periodic positional encoding of frames offset..offset+T-1."""
        cfg = self.cfg
        encode = interleaved_encoding if cfg.interleaved_ppe else periodic_encoding
        return encode(num_frames, cfg.d_model, cfg.period, device, offset)

    def first_input(self, style: Tensor) -> Tensor:
        """(B, d) generation's input for frame 0 (no previous frame)."""
        return self.motion_map.bias + style if self.cfg.frame0_motion_bias else style

    @property
    def resampler(self) -> str:
        """Imported releases (CNN-feature resampling, as the official code): resampy's
        ``kaiser_best``, which the official ``librosa.load(sr=16000)`` used (librosa 0.8.1)."""
        return "kaiser_best" if self.cfg.speech.resample == "cnn" else super().resampler

    def default_frames(self, samples: int) -> int:
        """Motion frames for ``samples`` of 16 kHz audio: the encoder's own count where it
        resamples its CNN features (the official frame count), else duration x fps."""
        count = getattr(self.speech, "frames_for", None)
        if count is not None and self.cfg.speech.resample == "cnn":
            return count(samples, self.cfg.motion_fps, self.cfg.audio_tokens_per_frame)
        return frames_for_audio(samples, self.cfg.motion_fps)

    def _bias(self, length: int, device: torch.device) -> Tensor:
        cfg = self.cfg
        return decoder_bias(cfg.heads, length, length, cfg.period, cfg.attention_window, device)

    def _inputs(self, previous: Tensor, style: Tensor) -> Tensor:
        """previous (B, T, V*3) the normalised offsets each frame reads (zero for frame 0),
        style (B, d) -> (B, T, d) decoder inputs."""
        x = self.motion_map(previous) + style[:, None]
        return x + self.ppe(x.shape[1], x.device)

    def hidden_states(
        self, x: Tensor, cross: list[Tensor], bias: Tensor, caches: list[KVCache] | None = None
    ) -> Tensor:
        """x (B, T, d) inputs -> (B, T, d) decoder states, before the motion decoder."""
        for n, block in enumerate(self.blocks):
            x = block(x, bias, caches[n] if caches else None, cross[n])
        return self.norm(x)

    # -- training (teacher forcing with self-feedback) -----------------------------------------

    def forward(
        self,
        audio: Tensor,
        audio_lengths: Tensor | None,
        vertices: Tensor,
        templates: Tensor,
        styles: Tensor,
        motion_mask: Tensor | None = None,
    ) -> FaceFormerOutput:
        """audio (B, S), audio_lengths (B,) or None, vertices (B, T, V, 3), templates (B, V, 3),
        styles (B,) (-1: a speaker outside the training set, who gets the mean style),
        motion_mask (B, T) bool or None -> :class:`FaceFormerOutput`."""
        self._check(audio, templates, "templates")
        B, T = vertices.shape[:2]
        if tuple(vertices.shape[2:]) != tuple(templates.shape[1:]) or len(vertices) != B:
            raise TalkmeshError(
                f"vertices must be (batch, frames, {self.num_vertices}, 3), "
                f"got shape {tuple(vertices.shape)}"
            )
        motion = (vertices - templates[:, None]).flatten(2) / self.scale
        seen = self.style(styles.clamp(min=0))
        style = torch.where((styles >= 0)[:, None], seen, self.style.weight.mean(0)[None])
        cross = self.cross_terms(self.audio_tokens(audio, audio_lengths, T))
        # causal: a valid frame never sees the padded frames after it, so no padding bias
        bias = self._bias(T, motion.device)[None]

        def run(fed_back: Tensor) -> Tensor:
            previous = F.pad(fed_back[:, :-1], (0, 0, 1, 0))  # frame 0 reads the neutral face
            x = self.dropout(self._inputs(previous, style))
            return self.out(self.hidden_states(x, cross, bias))

        fed_back = motion
        if self.training and self.cfg.self_feedback > 0:
            with torch.no_grad():
                own = run(motion)
            pick = torch.rand(B, T, 1, device=motion.device) < self.cfg.self_feedback
            fed_back = torch.where(pick, own, motion)
        pred = run(fed_back)
        return FaceFormerOutput(pred * self.scale, masked_mse(pred, motion, motion_mask))

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

        ``styles`` (B,) training-speaker ids or ``style_weights`` (B, K) over the K training
        speakers (an unseen speaker: e.g. their mean). Deterministic: ``seed`` is accepted for the
        common model surface and unused. ``mode="fast"`` runs one decoder step per frame with
        key/value caches of ``attention_window`` frames; ``mode="naive"`` is the official loop.
        """
        if mode not in MODES:
            raise TalkmeshError(f"unknown generation mode '{mode}': use {' or '.join(MODES)}")
        self._check(audio, template)
        B, V = audio.shape[0], self.cfg.num_vertices
        if num_frames is None:
            samples = int(audio_lengths.max()) if audio_lengths is not None else audio.shape[1]
            num_frames = self.default_frames(samples)
        if num_frames < 1:
            raise TalkmeshError(f"num_frames must be at least 1, got {num_frames}")
        style = self.style_vector(styles, style_weights)
        if len(style) != B:
            raise TalkmeshError(f"styles are given for {len(style)} samples but audio has {B}")
        tokens = self.audio_tokens(audio, audio_lengths, num_frames)
        if mode == "naive":
            with step_threads():  # small tensors, one step after another (models/threads.py)
                offsets = self._generate_naive(style, tokens, num_frames)
            return offsets.view(B, num_frames, V, 3) + template[:, None]
        cross = self.cross_terms(tokens)
        gen = FrameGenerator(self, style)
        states = style.new_empty(B, num_frames, self.cfg.d_model)
        with step_threads():
            for t in range(num_frames):
                states[:, t] = gen.step([c[:, t : t + 1] for c in cross])
        result = template.new_empty(B, num_frames, V, 3)
        for a in range(0, num_frames, OUTPUT_CHUNK):  # bounded memory for the V*3 map
            offsets = self.out(states[:, a : a + OUTPUT_CHUNK]) * self.scale
            result[:, a : a + OUTPUT_CHUNK] = offsets.view(B, -1, V, 3) + template[:, None]
        return result

    def _generate_naive(self, style: Tensor, tokens: Tensor, num_frames: int) -> Tensor:
        """The official loop: every step runs the whole decoder (its cross-attention onto the
        prefix's audio ``tokens`` (B, T, d) included) and motion decoder over the whole prefix and
        feeds its last frame back -> offsets (B, T, V*3)."""
        previous = [self.first_input(style)[:, None]]
        for t in range(num_frames):
            x = torch.cat(previous, dim=1)
            x = x + self.ppe(t + 1, x.device)
            h = self.hidden_states(
                x, self.cross_terms(tokens[:, : t + 1]), self._bias(t + 1, x.device)[None]
            )
            motion = self.out(h)
            previous.append((self.motion_map(motion[:, -1]) + style)[:, None])
        return motion * self.scale


class FrameGenerator:
    """The decoder one frame at a time with key/value caches of ``attention_window`` frames
    (``generate``'s fast mode, and streaming): every frame costs the same, whatever the length.

    A step returns the frame's decoder state; ``model.out(state) * model.scale`` are its offsets,
    decoded for many frames at once by the caller. The motion decoder followed by the motion
    encoder is one linear map (d -> d): folded, a step never reads the two V*3 x d matrices.
    """

    def __init__(self, model: FaceFormer, style: Tensor) -> None:
        cfg = model.cfg
        self.model, self.style = model, style
        self.window, self.period = cfg.attention_window, cfg.period
        self.caches = [KVCache(self.window) for _ in model.blocks]
        self.fold = folded_linear(model, model.out, model.motion_map)  # (d -> d)
        device = style.device
        self.ppe = model.ppe(cfg.period, device)
        self.bias = decoder_bias(
            cfg.heads, 1, self.window, cfg.period, self.window, device, q_offset=self.window - 1
        )[None]
        self.x_in = model.first_input(style)
        self.t = 0

    def step(self, cross: list[Tensor]) -> Tensor:
        """cross: per decoder layer the (B, 1, d) audio term of this frame -> (B, d) state."""
        x = (self.x_in + self.ppe[self.t % self.period])[:, None]
        bias = self.bias[..., self.window - min(self.t + 1, self.window) :]
        h = self.model.hidden_states(x, cross, bias, self.caches)[:, 0]
        self.x_in = self.fold(h) + self.style
        self.t += 1
        return h
