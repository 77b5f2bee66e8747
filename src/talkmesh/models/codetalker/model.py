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

Releases imported from the official files (``talkmesh import-checkpoint``, codetalker/official.py)
switch the official behaviour back on through config options (``vq.instance_norm``,
``vq.gelu_tanh``, ``vq.final_norm``, ``vq.frame_positions``, ``stage2.postnorm``,
``stage2.interleaved_ppe``, the speech encoder's ``resample``/``normalize``); their generation
equals the official ``predict`` (docs/guide/official.md).

Here: the configs, stage 2 and :class:`CodeTalker` (training graph and ``generate``). Stage 1 is in
:mod:`talkmesh.models.codetalker.vq`, the cached generation engine in
:mod:`talkmesh.models.codetalker.generate`, the shared transformer layers in
:mod:`talkmesh.models.layers`, int8 generation in :mod:`talkmesh.models.int8`.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from talkmesh.constants import INT8_LAYERS, MOTION_FPS
from talkmesh.errors import TalkmeshError
from talkmesh.models.base import CHUNK_FRAMES, FrameStream, MotionModel, frames_for_audio
from talkmesh.models.codetalker.generate import (
    AheadWindow,
    CodeTalkerStream,
    fast_passes,
    generate_exact,
    generate_fast,
)
from talkmesh.models.codetalker.vq import MotionVQVAE, Quantized, VQConfig
from talkmesh.models.int8 import quantize_int8
from talkmesh.models.layers import Block, KVCache, padding_bias, periodic_encoding, temporal_bias
from talkmesh.models.postnorm import PostNormDecoderLayer, interleaved_encoding
from talkmesh.models.speech import (
    MelEncoder,
    MelFeatureStream,
    SpeechEncoderConfig,
    WhisperEncoder,
    build_speech_encoder,
    release_config,
)
from talkmesh.models.speech_chunks import FrameFeatures
from talkmesh.models.threads import step_threads
from talkmesh.models.whisper_stream import WhisperFeatureStream

GENERATION_MODES = ("fast", "naive", "exact")  # CodeTalker.generate(mode=...)
# the head term's input, in tenths of the training faces' spread: Adam moves each weight of its
# zero-initialised map about lr a step, and at 1 unit per spread 1300 fine-tuning steps left the
# term at a tenth of what the widest resting lips need (docs/results/multilingual.md)
HEAD_SCALE = 10.0

# ---------------------------------------------------------------------------------------------
# Configuration


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
    # 0 is the paper's plain teacher forcing (docs/results/codetalker.md measures the exposure bias)
    self_feedback: float = 0.0  # training: probability that a frame's fed-back motion is the
    # model's own prediction from a first, teacher-forced pass (no gradient) instead of the truth
    # (parallel scheduled sampling, Duckworth et al. 2019), so it learns from its own feedback
    # official-exact options (on in imported releases, docs/guide/official.md)
    postnorm: bool = False  # the official nn.TransformerDecoder layers (post-norm, ReLU,
    # dropout 0.1, attention over the frame's k aligned audio tokens, no final norm)
    interleaved_ppe: bool = False  # the official PPE channel order (sin/cos interleaved)
    # the head's own lips (not the paper's): vertex pairs across the lip gap, flat (a0, b0, a1,
    # b1, ...), whose distances on the template, standardised by the training templates'
    # head_mean/head_std, add a learned term to the style, so that the model knows how far a
    # head's lips stand apart at rest (a closure moves them that far); () off
    head_pairs: tuple[int, ...] = ()
    head_mean: tuple[float, ...] = ()
    head_std: tuple[float, ...] = ()
    # the same standardised distances, mapped by ``CodeTalker.decoder_head`` (zero at first), added
    # to the VQ decoder's input: the codes alone draw every head's lips with the training heads'
    # near-closure, so a head whose lips rest apart never closed them
    head_decoder: bool = False

    def __post_init__(self) -> None:
        pairs = len(self.head_pairs) // 2
        if len(self.head_pairs) % 2 or len(self.head_mean) != pairs or len(self.head_std) != pairs:
            raise ValueError("stage2.head_pairs needs vertex pairs and one mean and std each")
        if self.head_decoder and not self.head_pairs:
            raise ValueError("stage2.head_decoder reads the lips of stage2.head_pairs: give those")
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
    motion_fps: float = MOTION_FPS


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
        ),
        stage2=Stage2Config(
            d_model=256,
            heads=4,
            ff=512,
            layers=2,
            styles=styles,
            speech=SpeechEncoderConfig(kind="mel", dim=128),
        ),
    )


class Stage2Output(NamedTuple):
    motion: Tensor  # (B, T, V*3) predicted motion (teacher forced)
    loss: Tensor  # () Eq. 6
    feature_loss: Tensor
    motion_loss: Tensor
    features: Tensor | None = None  # (B, T, H, C) the predicted features, before quantisation
    target_codes: Tensor | None = None  # (B, T, H) the codes the VQ-VAE gives the true motion


class CodeTalker(MotionModel):
    """Both stages; stage 1 is frozen while stage 2 trains."""

    family = "codetalker"
    config_class = CodeTalkerConfig
    generation_modes = GENERATION_MODES
    generate_block = 128  # most frames per pass of fast generation (see FrameGenerator.block)
    head_scale = HEAD_SCALE  # the head term's input unit (export: talkmesh.models.onnx)

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
        self.head_map = nn.Linear(len(s2.head_mean), s2.d_model) if s2.head_pairs else None
        if self.head_map is not None:  # a model given it starts where it was
            nn.init.zeros_(self.head_map.weight)
            nn.init.zeros_(self.head_map.bias)
        self.decoder_head = nn.Linear(len(s2.head_mean), vq.hidden) if s2.head_decoder else None
        if self.decoder_head is not None:  # likewise: the decoder draws what it drew before
            nn.init.zeros_(self.decoder_head.weight)
            nn.init.zeros_(self.decoder_head.bias)
        self.motion_map = nn.Linear(vq.num_vertices * 3, s2.d_model)  # vertice_map
        if s2.postnorm:  # the official nn.TransformerDecoder layers (models/postnorm.py)
            self.blocks = nn.ModuleList(
                PostNormDecoderLayer(s2.d_model, s2.heads, s2.ff) for _ in range(s2.layers)
            )
            self.cross = nn.ModuleList()
            self.norm = nn.Identity()
        else:
            self.blocks = nn.ModuleList(
                Block(s2.d_model, s2.heads, s2.ff) for _ in range(s2.layers)
            )
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

    @classmethod
    def tiny_config(
        cls, num_vertices: int = 30, styles: tuple[str, ...] = ("a", "b")
    ) -> CodeTalkerConfig:
        return CodeTalkerConfig(
            vq=VQConfig(
                num_vertices=num_vertices,
                hidden=32,
                layers=1,
                heads=2,
                ff=64,
                components=4,
                code_dim=8,
                codebook_size=16,
            ),
            stage2=Stage2Config(
                d_model=32,
                heads=2,
                ff=64,
                layers=2,
                period=5,
                styles=styles,
                speech=SpeechEncoderConfig(kind="mel", dim=16),
            ),
        )

    # -- the model interface's optional verbs (talkmesh.models.base) ------------------------------

    def mode_note(self, mode: str) -> str | None:
        if mode == "fast" and not self.cfg.vq.causal:
            return (
                "this model's VQ decoder is bidirectional (the paper's), so fast mode "
                "approximates the paper's loop (docs/results/codetalker.md); --mode exact gives its output"
            )
        return None

    def int8_copy(self, layers: str) -> CodeTalker:
        """A copy with ``layers`` in int8: ``speech`` (the speech encoder), ``decoders`` (both
        decoders) or ``all`` (:func:`talkmesh.models.int8.quantize_int8`)."""
        if layers not in INT8_LAYERS:
            raise TalkmeshError(f"unknown int8 layers '{layers}': use {', '.join(INT8_LAYERS)}")
        return quantize_int8(self, speech=layers != "decoders", decoders=layers != "speech")

    def reconstruct(self, vertices: Tensor, template: Tensor) -> Tensor:
        """Stage 1 alone: vertices (B, T, V, 3), template (B, V, 3) -> (B, T, V, 3)."""
        motion = (vertices - template[:, None]).flatten(2)
        out = self.vqvae(motion, face=self.decoder_face(template)).motion
        return out.reshape(vertices.shape) + template[:, None]

    @property
    def codebook_size(self) -> int:
        return self.cfg.vq.codebook_size

    def motion_codes(self, vertices: Tensor, template: Tensor) -> Tensor:
        return self.vqvae((vertices - template[:, None]).flatten(2)).codes

    def open_frame_stream(
        self,
        style_weights: np.ndarray | None,
        lookahead_ms: float | None,
        template: np.ndarray | None = None,
    ) -> FrameStream:
        """One frame per step (:class:`CodeTalkerStream`) for a model with a causal VQ decoder:
        a streaming release (``configs/codetalker_stream.yaml``: mel speech encoder with a
        runtime look-ahead, None its largest) or one with the Whisper encoder (the bundled
        model: features a few frames at a time, :mod:`talkmesh.models.whisper_stream`, None its
        default look-ahead); ``template`` (V, 3): the head it drives (``stage2.head_pairs``)."""
        s2 = self.cfg.stage2
        if isinstance(self.speech, MelEncoder):
            features = MelFeatureStream(self.speech, self.motion_fps, lookahead_ms)
        elif isinstance(self.speech, WhisperEncoder) and s2.audio_tokens_per_frame == 1:
            features = WhisperFeatureStream(self.speech, self.motion_fps, lookahead_ms)
        else:
            features = None
        if not self.cfg.vq.causal or features is None:
            raise TalkmeshError(
                "this codetalker model cannot stream: it needs a causal VQ decoder and the mel "
                "speech encoder or the Whisper one (train one with configs/codetalker_stream.yaml)"
            )
        style, face = self.stream_terms(style_weights, template)
        return CodeTalkerStream(self, style, features, face)

    def stream_terms(
        self, style_weights: np.ndarray | None, template: np.ndarray | None
    ) -> tuple[Tensor, Tensor | None]:
        """One stream's style vector (1, d) (``style_weights`` over the training styles, None:
        all alike, a speaker the model has not heard) and its VQ decoder's head term (1, hidden)
        (:meth:`decoder_face`) for the head ``template`` (V, 3) it drives."""
        K = len(self.styles)
        weights = np.full(K, 1.0 / K, np.float32) if style_weights is None else style_weights
        with torch.inference_mode():
            head = (
                None if template is None else torch.as_tensor(template, dtype=torch.float32)[None]
            )
            weights = torch.from_numpy(np.asarray(weights, np.float32))[None]
            return self.style_vector(None, weights, head), self.decoder_face(head)

    def onnx_graphs(self) -> tuple[nn.Module, nn.Module]:
        """The Whisper speech encoder and one step of generation with its state as inputs and
        outputs (:mod:`talkmesh.models.codetalker.export`): a causal VQ decoder's steps are final."""
        from talkmesh.models.codetalker.export import EncoderGraph, StepGraph

        if not self.cfg.vq.causal or not isinstance(self.speech, WhisperEncoder):
            raise TalkmeshError(
                "export-onnx needs a CodeTalker with a causal VQ decoder and the Whisper speech "
                "encoder (as the bundled codetalker-synth)"
            )
        return EncoderGraph(self.speech.features.encoder).eval(), StepGraph(self).eval()

    # -- pieces ---------------------------------------------------------------------------------

    def style_vector(
        self, styles: Tensor | None, weights: Tensor | None = None, template: Tensor | None = None
    ) -> Tensor:
        """(B,) style ids, or (B, S) weights over the training styles (Eq. 4) -> (B, d); plus
        the head term of ``template`` (B, V, 3) where the model has one."""
        if weights is not None:
            style = weights.to(self.style.weight.dtype) @ self.style.weight
        elif styles is None or (styles < 0).any():
            raise TalkmeshError("an unseen speaker needs style weights (e.g. --style A:0.5,B:0.5)")
        else:
            style = self.style(styles)
        return style + self.head_term(template, style.dtype)

    def head_term(self, template: Tensor | None, dtype: torch.dtype = torch.float32) -> Tensor:
        """(B, d) the style's term for the head ``template`` (B, V, 3) (``stage2.head_pairs``);
        0 for a model without one. No template: the training templates' average head."""
        if self.head_map is None:
            return torch.zeros((), dtype=dtype)
        if template is None:
            return self.head_map.bias[None].to(dtype)
        z = self.head_input(template)
        return self.head_map(z.to(self.head_map.weight.dtype)).to(dtype)

    def decoder_face(self, template: Tensor | None) -> Tensor | None:
        """(B, hidden) the VQ decoder's input term for the head ``template`` (B, V, 3)
        (``stage2.head_decoder``), (1, hidden) for no template (the training templates' average
        head); None for a model without one."""
        if self.decoder_head is None:
            return None
        if template is None:
            return self.decoder_head.bias[None]
        return self.decoder_head(self.head_input(template).to(self.decoder_head.weight.dtype))

    def head_input(self, template: Tensor) -> Tensor:
        """template (B, V, 3) -> (B, P) float32: the distances of its P lip pairs
        (``stage2.head_pairs``), standardised by the training templates', in HEAD_SCALE units."""
        s2 = self.cfg.stage2
        pairs = torch.tensor(s2.head_pairs, device=template.device).view(-1, 2)
        dist = (template[:, pairs[:, 0]] - template[:, pairs[:, 1]]).float().norm(dim=-1)
        mean = torch.tensor(s2.head_mean, device=template.device)
        return (dist - mean) / torch.tensor(s2.head_std, device=template.device) * HEAD_SCALE

    def audio_tokens(self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int) -> Tensor:
        """(B, S) -> (B, T, d) one token per motion frame (the alignment mask: frame t sees token t;
        with k tokens per frame their mean, which equals attending uniformly to them)."""
        k = self.cfg.stage2.audio_tokens_per_frame
        return self._tokens(self.speech(audio, audio_lengths, num_frames * k), num_frames)

    def _tokens(self, feats: Tensor, num_frames: int) -> Tensor:
        """Speech features (B, T * k, D) of T frames -> their tokens, as :meth:`audio_tokens`."""
        k = self.cfg.stage2.audio_tokens_per_frame
        feats = self.audio_map(feats)
        if self.cfg.stage2.postnorm:  # all k tokens, for the layers' attention
            return feats.view(feats.shape[0], num_frames, k, -1)
        if k > 1:
            feats = feats.view(feats.shape[0], num_frames, k, -1).mean(2)
        return feats

    def cross_terms(self, audio_tokens: Tensor) -> list[Tensor]:
        """Cross-attention of frame t onto its own audio token(s) only: with one key the softmax is
        1, so the output is a linear map of the token - exact and computed for all frames at once.
        ``postnorm``: the (B, T, k, d) tokens themselves, which the layers attend to."""
        if self.cfg.stage2.postnorm:
            return [audio_tokens] * len(self.blocks)
        return [layer(audio_tokens) for layer in self.cross]

    def ppe(self, num_frames: int, device: torch.device, offset: int = 0) -> Tensor:
        """(T, d) periodic positional encoding of frames offset..offset+T-1."""
        s2 = self.cfg.stage2
        encode = interleaved_encoding if s2.interleaved_ppe else periodic_encoding
        return encode(num_frames, s2.d_model, s2.period, device, offset)

    @property
    def resampler(self) -> str:
        """Imported releases (CNN-feature resampling, as the official code): resampy's
        ``kaiser_best``, which the official ``librosa.load(sr=16000)`` used (librosa 0.8.1)."""
        return "kaiser_best" if self.cfg.stage2.speech.resample == "cnn" else super().resampler

    def default_frames(self, samples: int) -> int:
        """Motion frames for ``samples`` of 16 kHz audio: the official count where the speech
        encoder resamples its CNN features, else duration x fps."""
        count = getattr(self.speech, "frames_for", None)
        if count is not None and self.cfg.stage2.speech.resample == "cnn":
            return count(samples, self.motion_fps, self.cfg.stage2.audio_tokens_per_frame)
        return frames_for_audio(samples, self.motion_fps)

    def decode_features(
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
            encoded = self.vqvae.encode(motion, motion_mask)
            target = encoded.z_q  # (B, T, H, C)
        # validation speakers outside the training set get the mean style (as in generation)
        seen = styles.clamp(min=0)
        style = torch.where(
            (styles >= 0)[:, None], self.style(seen), self.style.weight.mean(0)[None]
        )
        style = style + self.head_term(templates, style.dtype)
        face = self.decoder_face(templates)
        s2 = self.cfg.stage2
        cross = self.cross_terms(self.audio_tokens(audio, audio_lengths, T))
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
            x = prev + self.ppe(T, prev.device)
            feats = self.decode_features(x, cross, bias)
            feats = feats.view(B, T, self.cfg.vq.components, self.cfg.vq.code_dim)
            q = self.vqvae.quantizer(feats)
            return feats, q, self.vqvae.decoder(q.z_q, motion_mask, face=face)

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
        return Stage2Output(pred, f_loss + m_loss, f_loss, m_loss, feats, encoded.codes)

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
        if mode == "fast" and self.cfg.vq.instance_norm:
            # instance statistics span the whole prefix: the cached causal pass cannot compute
            # them, so such a model (every imported release) generates in exact mode
            mode = "exact"
        B = audio.shape[0]
        if num_frames is None:
            num_frames = self.default_frames(audio.shape[1])
        s2, vq = self.cfg.stage2, self.cfg.vq
        style = self.style_vector(styles, style_weights, template)
        face = self.decoder_face(template)
        tokens = self.audio_tokens(audio, audio_lengths, num_frames)
        with step_threads():  # small tensors, one step after another (models/threads.py)
            all_codes, motion = self._step_loop(mode, style, tokens, num_frames, block, face)
        if mode == "naive" or motion is None:  # a causal decoder's steps are already final
            window = None if mode == "naive" else max(1, s2.attention_window // vq.temporal_unit)
            motion = self.vqvae.decode(all_codes, window, face=face)[:, :num_frames]
        motion = motion.reshape(B, num_frames, vq.num_vertices, 3)  # a view: no copy
        return motion.add_(template[:, None])  # in place: 10 minutes are about 1 GB

    def _step_loop(
        self,
        mode: str,
        style: Tensor,
        tokens: Tensor,
        num_frames: int,
        block: int | None,
        face: Tensor | None = None,
    ) -> tuple[Tensor, Tensor | None]:
        """The autoregressive loop of ``generate``'s ``mode`` -> codes (B, T, H) and the motion
        of fast mode's causal decoder (None where the codes are decoded after); ``face``
        (B, hidden): the VQ decoder's head term (:meth:`decoder_face`)."""
        B, s2 = style.shape[0], self.cfg.stage2
        H, C = self.cfg.vq.components, self.cfg.vq.code_dim
        if mode == "naive":
            inputs = style[:, None]
            codes = []
            for t in range(num_frames):
                x = inputs + self.ppe(t + 1, inputs.device)
                bias = temporal_bias(s2.heads, t + 1, t + 1, s2.period, x.device)[None]
                # as the paper's decoder: its cross-attention runs over the prefix at every step
                feats = self.decode_features(x, self.cross_terms(tokens[:, : t + 1]), bias)
                q = self.vqvae.quantizer(feats.view(B, t + 1, H, C))
                motion = self.vqvae.decoder(q.z_q, face=face)
                codes.append(q.codes[:, -1])
                nxt = self.motion_map(motion[:, -1] / self.vqvae.decoder.scale) + style
                inputs = torch.cat([inputs, nxt[:, None]], dim=1)
            all_codes = torch.stack(codes, dim=1)
        elif mode == "exact":
            all_codes, motion = (
                generate_exact(self, style, self.cross_terms(tokens), num_frames, face),
                None,
            )
        else:
            all_codes, motion = generate_fast(
                self, style, self.cross_terms(tokens), num_frames, block, face
            )
        return all_codes, motion

    def generate_chunks(
        self,
        audio: Tensor,
        template: Tensor,
        *,
        style_weights: Tensor | None = None,
        num_frames: int | None = None,
        seed: int = 0,
        mode: str = "fast",
        chunk: int = CHUNK_FRAMES,
    ) -> Iterator[Tensor]:
        """Fast generation a chunk at a time (arguments as :meth:`generate`, one sample): speech
        features computed window by window (:class:`~talkmesh.models.speech_chunks.FrameFeatures`)
        and the frames of :func:`~talkmesh.models.codetalker.generate.fast_passes` handed out as
        they become final, so memory does not grow with the audio. The passes are those of
        :meth:`generate` (the audio terms are loaded ahead of them): the same vertices up to
        float rounding. Models without a causal VQ decoder (their vertices come from a
        bidirectional decode of all codes) and other modes generate the whole sequence."""
        self.check_mode(mode)
        vq, k = self.cfg.vq, self.cfg.stage2.audio_tokens_per_frame
        streamed = not isinstance(audio, Tensor)  # a Waveform, read a window at a time
        one = streamed or audio.shape[0] == 1
        if mode != "fast" or not vq.causal or vq.instance_norm or not one:
            yield from super().generate_chunks(
                audio,
                template,
                style_weights=style_weights,
                num_frames=num_frames,
                seed=seed,
                mode=mode,
                chunk=chunk,
            )
            return
        if num_frames is None:
            num_frames = self.default_frames(len(audio) if streamed else audio.shape[1])
        # the speech windows and the steps alike on the step threads (bench/threads.py: the
        # fastest for the whole loop on a shared machine)
        with torch.inference_mode(), step_threads():
            style = self.style_vector(None, style_weights, template)
            face = self.decoder_face(template)
            features = FrameFeatures(self.speech, audio, num_frames * k)
            terms = AheadWindow(
                lambda a, b: self.cross_terms(self._tokens(features(a * k, b * k), b - a)),
                chunk,
                num_frames,
            )
            ready: list[Tensor] = []
            count = 0
            for _, frames in fast_passes(self, style, terms, num_frames, face=face):
                if frames is not None and frames.shape[1]:
                    ready.append(frames)
                    count += frames.shape[1]
                if count >= chunk:
                    motion = torch.cat(ready, dim=1)
                    ready, count = [], 0
                    yield motion.view(1, -1, vq.num_vertices, 3) + template[:, None]
            if count:
                yield torch.cat(ready, dim=1).view(1, -1, vq.num_vertices, 3) + template[:, None]
