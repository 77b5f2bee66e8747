"""MeshTalk (Richard et al., ICCV 2021): a categorical expression space and an audio-conditioned prior.

Read top to bottom:

1. Configs: :class:`MeshTalkConfig` and the presets ``paper`` (H=64, C=128), ``released`` (the
   official code, H=16, C=128) and ``small`` (a synthetic corpus on 2 CPU cores).
2. Audio: the log-mel encoder (:class:`talkmesh.models.mel.MelAudioEncoder`, the paper's) or
   :class:`talkmesh.models.speech.SpeechFeatures` (any talkmesh speech encoder, same call).
3-5. The layers (:mod:`talkmesh.models.meshtalk.layers`): :class:`ExpressionEncoder` (per-frame
   MLP + LSTM), :class:`FusionQuantizer` (MLP to H heads of C logits, hard straight-through
   Gumbel-softmax, Eq. 1-2), :class:`TemplateDecoder` (U-Net over the template, Eq. 3: any neutral
   mesh of the topology can be animated).
6. Losses as functions returning NamedTuples: :func:`meshtalk_loss` (reconstruction, cross-modality
   Eq. 6 with the soft mouth and upper-face maps, eyelid Eq. 7).
7. :class:`MeshTalk`: ``forward`` (teacher-forced graph with the two cross-modal decodes), ``encode``,
   ``decode``, ``retarget`` (Sec. 4.3), ``dub`` (Sec. 4.4), ``loss``, ``set_statistics``.
8. The autoregressive prior lives in :mod:`talkmesh.models.meshtalk.prior` (Eq. 8-9).
9. :class:`MeshTalkModel` (+ :class:`MeshTalkModelConfig`, :class:`SamplingConfig`): the release,
   expression space + prior behind the model interface of :mod:`talkmesh.models.base`
   (``generate(audio, template, seed=)``: prior codes decoded on the template).

Axis letters: B batch, S audio samples, T motion frames, M mel frames, V vertices, H heads, C classes
(the codebook size K of the issue), D width.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.constants import MOTION_FPS
from talkmesh.errors import TalkmeshError
from talkmesh.models.base import MotionModel
from talkmesh.models.mel import MelAudioEncoder, MelConfig
from talkmesh.models.meshtalk.context import build_prior
from talkmesh.models.meshtalk.layers import (
    ExpressionEncoder,
    FusionQuantizer,
    Quantized,
    TemplateDecoder,
    gumbel_one_hot,
)
from talkmesh.models.meshtalk.prior import PRESETS, PriorConfig
from talkmesh.models.speech import SpeechEncoderConfig, SpeechFeatures, release_config
from talkmesh.models.threads import step_threads


def _fail(message: str) -> None:
    raise TalkmeshError(message)


# ---------------------------------------------------------------------------------------------
# 1. Configs


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
    fps: float = MOTION_FPS
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
    # official-exact options (facebookresearch/meshtalk; on in imported models):
    expression_output: int = 0  # width of a Linear after the expression LSTM (official ``code``)
    # "scalar": templates and offsets scaled by one spread each, the expression encoder reads
    # offsets from the template; "per_vertex" (official): per-coordinate mean and stddev, the
    # expression encoder reads normalised vertex positions
    vertex_norm: str = "scalar"
    official_decoder: bool = False  # TemplateDecoder(official=True): the released VertexUnet

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
        if self.vertex_norm not in ("scalar", "per_vertex"):
            _fail(
                f"meshtalk config: vertex_norm must be scalar or per_vertex, got {self.vertex_norm!r}"
            )


def meshtalk_config(preset: str, num_vertices: int, fps: float = MOTION_FPS) -> MeshTalkConfig:
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
            self.audio_encoder = SpeechFeatures(cfg.speech, cfg.audio.out_dim)
            # a pretrained encoder loaded from a path: the release keeps its config, not the path
            speech = release_config(cfg.speech, self.audio_encoder.encoder)
            if speech is not cfg.speech:
                self.config = cfg = replace(cfg, speech=speech)
        self.expression_encoder = ExpressionEncoder(
            V * 3, cfg.expression_widths, cfg.expression_output
        )
        expression_dim = cfg.expression_output or cfg.expression_widths[-1]
        self.fusion = FusionQuantizer(cfg.audio.out_dim + expression_dim, cfg.fusion_width, H, C)
        self.decoder = TemplateDecoder(
            V, H * C, cfg.decoder_widths, cfg.decoder_lstm_layers, cfg.official_decoder
        )
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
        scale = (V, 3) if cfg.vertex_norm == "per_vertex" else ()
        self.register_buffer("template_scale", torch.ones(scale))
        self.register_buffer("offset_scale", torch.ones(scale))

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
        if self.config.vertex_norm == "per_vertex":
            # the official face_mean / face_std: each coordinate's mean and spread over the
            # training frames' vertex positions (template + offset; speakers and motion alike)
            offsets = offsets.reshape(-1, *mean.shape)
            var = templates.var(0, correction=0) + offsets.var(0, correction=0)
            spread = var.sqrt().clamp(min=1e-8)
            self.template_mean.copy_(mean + offsets.mean(0))
            self.template_scale.copy_(spread)
            self.offset_scale.copy_(spread)
            return
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
        if self.config.vertex_norm == "per_vertex":  # official: normalised positions
            x = (vertices - self.template_mean) / self.template_scale
        else:
            x = (vertices - templates[:, None]) / self.offset_scale
        expr = self.expression_encoder(x.reshape(B, T, -1))
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
# 9. The released model: expression space + prior behind talkmesh's common model surface


@dataclass(frozen=True)
class SamplingConfig:
    """How :meth:`MeshTalkModel.generate` draws codes from the prior (defaults of a release)."""

    temperature: float = 1.0
    top_k: int | None = None
    argmax: bool = False
    # draw by Gumbel-max with one uniform per class, as the official ContextModel.sample: a seed
    # then gives the official code's draws under torch.manual_seed(seed); off: torch.multinomial
    gumbel: bool = False

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
    # the official demo's post-processing (animate_face.py): a temporal Gaussian (9 frames,
    # sigma 2) blended in by per-vertex masks, one after the other (forehead, then neck); the
    # masks are the buffer ``smooth_masks`` (smoothing, V), filled on import from the assets
    smoothing: int = 0

    def __post_init__(self) -> None:
        p, m = self.prior, self.model
        if p is not None and (p.num_heads, p.num_classes) != (m.num_heads, m.num_classes):
            _fail("meshtalk: the prior's num_heads/num_classes must match the expression space")
        if p is not None and p.audio_source == "expression" and p.audio.out_dim != m.audio.out_dim:
            _fail("meshtalk: a prior on the expression space's audio needs its audio.out_dim")


class MeshTalkModel(MotionModel):
    """MeshTalk as ``talkmesh animate`` uses it: audio -> prior codes -> decoded template.

    Same surface as the other families (``talkmesh.models.release``); no speaker styles
    (``styles == ()``): what is not in the audio is sampled, so ``seed`` changes blinks and brows.
    """

    family = "meshtalk"
    config_class = MeshTalkModelConfig

    def __init__(self, cfg: MeshTalkModelConfig, maps=(None, None, None)) -> None:
        super().__init__()
        self.model = MeshTalk(cfg.model, *maps)
        self.prior = build_prior(cfg.prior) if cfg.prior is not None else None
        if cfg.smoothing:
            self.register_buffer("smooth_masks", torch.zeros(cfg.smoothing, cfg.model.num_vertices))
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

    @property
    def resampler(self) -> str:
        """Imported releases: torchaudio's ``Resample`` (Hann-windowed sinc), as the official
        ``utils/helpers.load_audio``."""
        return "sinc_hann" if self.cfg.model.official_decoder else super().resampler

    def default_frames(self, samples: int) -> int:
        """Frames for ``samples`` of audio; the official 1 s windows count them as its
        ``audio_chunking`` does (``MelConfig.windows``)."""
        encoder = self.model.audio_encoder
        if isinstance(encoder, MelAudioEncoder) and encoder.cfg.windows:
            return max(1, encoder.window_frames(samples))
        return super().default_frames(samples)

    @classmethod
    def tiny_config(
        cls, num_vertices: int = 30, styles: tuple[str, ...] = ("a", "b")
    ) -> MeshTalkModelConfig:
        audio = MelConfig(width=16, out_dim=16)
        return MeshTalkModelConfig(
            MeshTalkConfig(
                num_vertices,
                num_heads=4,
                num_classes=8,
                audio=audio,
                expression_widths=(32, 16, 16),
                fusion_width=32,
                decoder_widths=(32, 16, 16),
            ),
            PriorConfig(num_heads=4, num_classes=8, width=16, audio=audio),
        )

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
        gumbel: bool | None = None,
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
            num_frames = self.default_frames(audio.shape[1])
        features = self.audio_features(audio, audio_lengths, num_frames)
        generator = torch.Generator(device=audio.device).manual_seed(int(seed))
        kwargs = dict(
            temperature=s.temperature if temperature is None else temperature,
            top_k=s.top_k if top_k is None else top_k,
            argmax=s.argmax if argmax is None else argmax,
            gumbel=s.gumbel if gumbel is None else gumbel,
            generator=generator,
        )
        with step_threads():  # small tensors, one step after another (models/threads.py)
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
        mode: str = "fast",
        **sampling,
    ) -> Tensor:
        """audio (B, S) at 16 kHz, template (B, V, 3) -> vertices (B, T, V, 3). ``style_weights``
        must be None (MeshTalk has no speaker styles); ``sampling``: see :meth:`sample_codes`."""
        self.check_mode(mode)
        if style_weights is not None:
            _fail("MeshTalk has no speaker styles: drop --style")
        _check_mesh("template", template, self.num_vertices, 3)
        codes = self.sample_codes(
            audio, audio_lengths=audio_lengths, num_frames=num_frames, seed=seed, **sampling
        )
        vertices = self.model.decode(template.to(audio.dtype), codes)
        for mask in getattr(self, "smooth_masks", ()):
            vertices = smooth_region(vertices, mask)
        return vertices


SMOOTH_TAPS = 9  # the official demo's smooth_geom: filter_size 9, sigma 2
SMOOTH_SIGMA = 2.0


def smooth_region(vertices: Tensor, mask: Tensor) -> Tensor:
    """(B, T, V, 3) -> the official ``smooth_geom``: a Gaussian over time (edge frames
    repeated), blended with the input by ``mask`` (V,) in [0, 1]."""
    B, T, V, _ = vertices.shape
    taps = torch.arange(SMOOTH_TAPS, dtype=torch.float64) - SMOOTH_TAPS // 2
    kernel = torch.exp(-0.5 * taps**2 / SMOOTH_SIGMA**2)
    kernel = (kernel / kernel.sum()).to(vertices)
    x = vertices.permute(0, 2, 3, 1).reshape(B * V * 3, 1, T)
    x = F.pad(x, (SMOOTH_TAPS // 2, SMOOTH_TAPS // 2), mode="replicate")
    smoothed = F.conv1d(x, kernel.view(1, 1, -1)).view(B, V, 3, T).permute(0, 3, 1, 2)
    m = mask.to(vertices)[None, None, :, None]
    return smoothed * m + vertices * (1 - m)
