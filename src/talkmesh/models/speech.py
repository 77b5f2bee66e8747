"""Speech encoders behind one interface: ``forward(audio (B, S), audio_lengths (B,) | None,
num_frames) -> (B, T, D)`` at the motion frame rate, resampled generally (no dataset branches).

* ``mel``: MeshTalk's log-mel convolutional encoder (:mod:`talkmesh.models.mel`), trained from scratch (fast, no weights needed).
* ``wav2vec2``: transformers' ``Wav2Vec2Model`` (CodeTalker's choice) from a local path or hub id
  (``source``), or a random model from ``hf_config`` (tests); its CNN feature extractor is frozen;
  features (50 Hz) are linearly interpolated to the motion frames.
* ``whisper``: Whisper's audio encoder (:mod:`talkmesh.models.whisper_encoder`; tiny.en, 8.2 M
  parameters, 384-d at 50 Hz), converted offline with ``talkmesh convert-whisper`` (``source``: the converted directory), or
  random from ``hf_config``; ``frozen: true`` keeps its pretrained weights fixed.

A model built from ``source`` records the encoder's full config in ``hf_config`` and drops
``source`` (see :meth:`release_config`), so a release rebuilds it from its own file alone.
"""

from __future__ import annotations

import math
import pickle
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import MissingDependencyError, TalkmeshError
from talkmesh.models.frames import fit_sample_frames, interpolate_frames
from talkmesh.models.mel import LOG_FLOOR, MelAudioEncoder, MelConfig
from talkmesh.models.whisper import WhisperFeatures, load_whisper_encoder
from talkmesh.models.whisper_encoder import WhisperAudioEncoder

KINDS = ("mel", "wav2vec2", "whisper")


@dataclass(frozen=True)
class SpeechEncoderConfig:
    kind: str = "mel"  # "mel" | "wav2vec2" | "whisper"
    dim: int = 128  # mel: output width (wav2vec2: taken from the model)
    frame_rate: float = (
        30.0  # tokens per second the caller asks for (motion fps x tokens per frame)
    )
    source: str | None = None  # wav2vec2: local path or hub id for from_pretrained
    hf_config: dict[str, Any] = field(default_factory=dict)  # wav2vec2: a config for random weights
    lookahead_ms: float = 100.0  # mel: audio after the frame it may see
    lookahead_max_ms: float | None = None  # mel, streaming models: the look-ahead becomes a
    # runtime choice in [lookahead_ms, lookahead_max_ms] (sampled per batch in training and told to
    # the model through a learned embedding); inference uses lookahead_max_ms unless set
    freeze_cnn: bool = True
    window_seconds: float = 20.0  # wav2vec2: longer audio is encoded in windows of this length,
    context_seconds: float = 2.0  # each with this much audio either side, so memory is bounded

    frozen: bool = False  # wav2vec2/whisper: keep the whole pretrained encoder fixed
    resample: str = "output"  # wav2vec2: where features meet the motion rate: "output" (after the
    # transformer) or "cnn" (the official FaceFormer/CodeTalker: the CNN features are resampled,
    # linearly or, at the CNN's own rate, by cutting, before the transformer; that also sets the
    # frame count, see Wav2Vec2Encoder.frames_for)
    normalize: bool = False  # zero-mean unit-variance audio per utterance (the wav2vec2
    # processor that the official demos run before the model)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"speech.kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.resample not in ("output", "cnn") or (
            self.resample == "cnn" and self.kind != "wav2vec2"
        ):
            raise ValueError("speech.resample must be 'output', or 'cnn' with kind wav2vec2")
        if self.lookahead_max_ms is not None and (
            self.kind != "mel" or self.lookahead_max_ms < self.lookahead_ms
        ):
            raise ValueError("speech.lookahead_max_ms needs kind mel and >= speech.lookahead_ms")


def _weights_file(source: str) -> str:
    """The pickled weights file of a local model folder (else the source as given)."""
    folder = Path(source).expanduser()
    return str(folder / "pytorch_model.bin") if folder.is_dir() else source


class Wav2Vec2Encoder(nn.Module):
    def __init__(self, cfg: SpeechEncoderConfig) -> None:
        super().__init__()
        try:
            from transformers import Wav2Vec2Config, Wav2Vec2Model
        except ImportError:
            raise MissingDependencyError(
                "transformers", "models", "the wav2vec2 speech encoder"
            ) from None
        if cfg.source:
            try:  # transformers reads pytorch_model.bin with torch.load(weights_only=True)
                self.model = Wav2Vec2Model.from_pretrained(cfg.source)
            except pickle.UnpicklingError:
                raise TalkmeshError(
                    f"{_weights_file(cfg.source)}: refusing to load these wav2vec2 weights: the "
                    "file holds objects other than tensors; use a model.safetensors you trust"
                ) from None
            except OSError as e:
                first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
                raise TalkmeshError(f"cannot load wav2vec2 from {cfg.source}: {first}") from None
        else:
            self.model = Wav2Vec2Model(Wav2Vec2Config(**cfg.hf_config))
        if cfg.freeze_cnn:
            self.model.feature_extractor._freeze_parameters()
        if cfg.frozen:
            self.model.requires_grad_(False)
        self.dim = self.model.config.hidden_size
        self.cfg = cfg

    def hf_config(self) -> dict[str, Any]:
        return self.model.config.to_dict()

    @property
    def cnn_rate(self) -> float:
        """CNN feature vectors per second of 16 kHz audio (50 for wav2vec 2.0)."""
        return SAMPLE_RATE / math.prod(self.model.config.conv_stride)

    def frames_for(self, samples: int, fps: float, tokens_per_frame: int = 1) -> int:
        """Motion frames for ``samples`` of audio as the official code counts them: N CNN
        features give int(N / rate * fps) frames, or N // k at the CNN's own rate (k tokens per
        frame: BIWI drops an odd last feature)."""
        n = int(self.model._get_feat_extract_output_lengths(torch.tensor(samples)))
        if abs(fps * tokens_per_frame - self.cnn_rate) < 1e-6:
            return max(1, n // tokens_per_frame)
        return max(1, int(n / self.cnn_rate * fps))

    def _normalize(self, audio: Tensor) -> Tensor:
        """(1, S) -> zero mean, unit variance (the processor's ``do_normalize``)."""
        if not self.cfg.normalize:
            return audio
        return (audio - audio.mean()) / torch.sqrt(audio.var(unbiased=False) + 1e-7)

    def _cnn_tokens(self, audio: Tensor, n: int) -> Tensor:
        """(1, S) unpadded audio -> (1, n, D): CNN features resampled to ``n`` (cut or padded
        at the CNN's own rate, else linearly interpolated), then the transformer (in windows with
        context when long, as :meth:`features`)."""
        feats = self.model.feature_extractor(self._normalize(audio)).transpose(1, 2)
        if abs(self.cfg.frame_rate - self.cnn_rate) < 1e-6:
            feats = feats[:, :n]
            if feats.shape[1] < n:
                feats = torch.cat([feats, feats[:, -1:].expand(-1, n - feats.shape[1], -1)], 1)
        else:
            feats = interpolate_frames(feats, n)
        hidden = self.model.feature_projection(feats)
        hidden = hidden[0] if isinstance(hidden, tuple) else hidden
        rate = self.cfg.frame_rate
        window, context = int(self.cfg.window_seconds * rate), int(self.cfg.context_seconds * rate)
        if n <= window + 2 * context:
            return self.model.encoder(hidden)[0]
        parts = []
        for start in range(0, n, window):
            a, b = max(0, start - context), min(n, start + window + context)
            out = self.model.encoder(hidden[:, a:b])[0]
            parts.append(out[:, start - a : start - a + min(window, n - start)])
        return torch.cat(parts, dim=1)

    def _forward_cnn(self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int) -> Tensor:
        """``resample="cnn"``: each sample on its own valid audio, over its share of the frames
        (the rest repeat its last token, padding masked by the caller)."""
        S = audio.shape[1]
        out = []
        for b in range(audio.shape[0]):
            valid = int(audio_lengths[b]) if audio_lengths is not None else S
            n = num_frames
            if valid < S:
                n = min(num_frames, max(1, int(round(num_frames * valid / S))))
            tokens = self._cnn_tokens(audio[b : b + 1, :valid], n)[0]
            if n < num_frames:
                tokens = torch.cat([tokens, tokens[-1:].expand(num_frames - n, -1)])
            out.append(tokens)
        return torch.stack(out)

    def features(self, audio: Tensor) -> Tensor:
        """(1, S) unpadded audio -> (1, N, D) features; audio longer than the window is encoded in
        windows with context on both sides that is dropped (the transformer's attention is
        quadratic in length: 10 minutes at once would need tens of GB)."""
        window = int(self.cfg.window_seconds * SAMPLE_RATE)
        context = int(self.cfg.context_seconds * SAMPLE_RATE)
        S = audio.shape[1]
        if S <= window + 2 * context:
            return self.model(audio).last_hidden_state
        parts = []
        for start in range(0, S, window):
            a, b = max(0, start - context), min(S, start + window + context)
            hidden = self.model(audio[:, a:b]).last_hidden_state
            rate = hidden.shape[1] / (b - a)  # features per sample
            i0 = round((start - a) * rate)
            i1 = round((min(start + window, S) - a) * rate)
            parts.append(hidden[:, i0:i1])
        return torch.cat(parts, dim=1)

    def forward(self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int) -> Tensor:
        if self.cfg.resample == "cnn":
            return self._forward_cnn(audio, audio_lengths, num_frames)
        if self.cfg.normalize:  # each sample over its own valid audio
            audio = audio.clone()
            for i in range(len(audio)):
                n = int(audio_lengths[i]) if audio_lengths is not None else audio.shape[1]
                audio[i, :n] = self._normalize(audio[i : i + 1, :n])[0]
        longest = int(audio_lengths.max()) if audio_lengths is not None else audio.shape[1]
        if longest > int((self.cfg.window_seconds + 2 * self.cfg.context_seconds) * SAMPLE_RATE):
            lengths = (
                audio_lengths.tolist()
                if audio_lengths is not None
                else [audio.shape[1]] * len(audio)
            )
            return torch.stack(
                [
                    fit_sample_frames(
                        self.features(audio[b : b + 1, : int(n)])[0],
                        int(n),
                        audio.shape[1],
                        num_frames,
                    )
                    for b, n in enumerate(lengths)
                ]
            )
        mask = None
        if audio_lengths is not None:
            mask = (
                torch.arange(audio.shape[1], device=audio.device)[None] < audio_lengths[:, None]
            ).long()
        hidden = self.model(audio, attention_mask=mask).last_hidden_state
        if audio_lengths is None:
            return interpolate_frames(hidden, num_frames)
        # each sample is interpolated over its own valid features, so padding changes nothing
        rates = hidden.shape[1] / audio.shape[1]
        out = []
        for b in range(audio.shape[0]):
            n = max(1, int(round(float(audio_lengths[b]) * rates)))
            out.append(
                fit_sample_frames(hidden[b, :n], int(audio_lengths[b]), audio.shape[1], num_frames)
            )
        return torch.stack(out)


class MelEncoder(nn.Module):
    def __init__(self, cfg: SpeechEncoderConfig) -> None:
        super().__init__()
        self.encoder = MelAudioEncoder(
            MelConfig(out_dim=cfg.dim, lookahead_ms=cfg.lookahead_ms), cfg.frame_rate
        )
        self.dim = cfg.dim
        self.cfg = cfg
        self.max_shift = 0
        if cfg.lookahead_max_ms is not None:
            self.max_shift = self.shift_for(cfg.lookahead_max_ms)
            self.shift_embedding = nn.Embedding(self.max_shift + 1, cfg.dim)
            nn.init.zeros_(self.shift_embedding.weight)
        self.shift: int | None = None  # inference look-ahead (None: the largest)

    def shift_for(self, lookahead_ms: float) -> int:
        """Mel frames of extra look-ahead for a total look-ahead of ``lookahead_ms``."""
        return round((lookahead_ms - self.cfg.lookahead_ms) / 1000 * self.encoder.cfg.mel_rate)

    def check_lookahead(self, lookahead_ms: float) -> int:
        """The shift for a look-ahead, after checking it is in the trained range."""
        low, high = self.cfg.lookahead_ms, self.cfg.lookahead_max_ms or self.cfg.lookahead_ms
        if not low - 1e-6 <= lookahead_ms <= high + 1e-6:
            raise TalkmeshError(
                f"look-ahead {lookahead_ms:g} ms is outside what this model was trained for "
                f"({low:g}-{high:g} ms): pick a value in that range"
            )
        return self.shift_for(lookahead_ms)

    def set_lookahead(self, lookahead_ms: float | None) -> None:
        """Inference look-ahead of a streaming model (None: the largest it was trained for)."""
        self.shift = None if lookahead_ms is None else self.check_lookahead(lookahead_ms)

    def lookahead_for(self, shift: int) -> float:
        """The look-ahead (ms) that ``shift`` extra mel frames give."""
        return self.cfg.lookahead_ms + shift * 1000 / self.encoder.cfg.mel_rate

    @property
    def lookahead_ms(self) -> float:
        """The look-ahead in use: audio after a frame that its feature reads."""
        return self.lookahead_for(self.max_shift if self.shift is None else self.shift)

    def set_statistics(self, audio: Tensor) -> None:
        self.encoder.set_statistics(audio)

    def forward(self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int) -> Tensor:
        if not self.max_shift:
            return self.encoder(audio, audio_lengths, num_frames)
        if self.training:  # one look-ahead per batch, uniformly over the trained range
            shift = int(torch.randint(0, self.max_shift + 1, ()))
        else:
            shift = self.max_shift if self.shift is None else self.shift
        feats = self.encoder(audio, audio_lengths, num_frames, shift=shift)
        return feats + self.shift_embedding.weight[shift]


class MelFeatureStream:
    """A :class:`MelEncoder`'s features one motion frame at a time from a stream's audio, each
    exactly what the offline encoder computes; the log-mel frames of the receptive field are
    kept, so each frame computes only the new ones. The caller holds the audio: ``buffer``
    (float32 samples) whose first sample is stream sample ``buffer_start``."""

    def __init__(self, speech: MelEncoder, fps: float, lookahead_ms: float | None) -> None:
        self.speech, self.encoder, self.fps = speech, speech.encoder, fps
        self.mel = speech.encoder.cfg
        # the shared model is not changed: the stream keeps its own shift
        self.shift = (
            speech.max_shift if lookahead_ms is None else speech.check_lookahead(lookahead_ms)
        )
        self.lookahead_ms = speech.lookahead_for(self.shift)
        self.silence = math.log(LOG_FLOOR)  # log-mel of frames before the stream (as offline)
        self.cache: Tensor | None = None  # log-mel frames first.. of the current receptive field
        self.first = 0

    def last_mel(self, frame: int) -> int:
        """The last mel frame that ``frame``'s feature reads."""
        centre = int(round(frame * self.mel.mel_rate / self.fps))  # as MelAudioEncoder
        return centre + self.shift + self.mel.lookahead_frames

    def first_sample(self, frame: int) -> int:
        """The first stream sample ``frame``'s feature reads."""
        first = self.last_mel(frame) - self.mel.receptive_field + 1
        return first * self.mel.hop_length - self.mel.n_fft // 2

    def audio_needed(self, frame: int) -> float:
        """Samples that must have arrived before ``frame``'s feature can be computed."""
        # the last mel frame's window ends win_length / 2 after its centre
        return self.last_mel(frame) * self.mel.hop_length + self.mel.win_length // 2

    def _columns(self, buffer: np.ndarray, buffer_start: int, first: int, last: int) -> Tensor:
        """Log-mel frames ``first..last`` (n_mels, n) from the buffered audio, computed as the
        offline encoder does (frames before the stream are silence)."""
        mel = self.mel
        start = first * mel.hop_length - mel.n_fft // 2
        length = (last - first) * mel.hop_length + mel.n_fft
        segment = np.zeros(length, np.float32)
        a = max(start, buffer_start)
        b = min(start + length, buffer_start + len(buffer))
        if b > a:
            segment[a - start : b - start] = buffer[a - buffer_start : b - buffer_start]
        logmel = self.encoder.log_mel(torch.from_numpy(segment)[None], center=False)[0]
        if first < 0:  # before the stream: silence, as the offline encoder pads
            logmel[:, :-first] = self.silence
        return logmel

    def feature(self, buffer: np.ndarray, buffer_start: int, frame: int) -> Tensor:
        """The speech feature (1, dim) of ``frame``; frames are asked for in order."""
        return self.encode(self.window(buffer, buffer_start, frame)[None], [self.shift])

    def window(self, buffer: np.ndarray, buffer_start: int, frame: int) -> Tensor:
        """The log-mel frames (n_mels, receptive_field) that ``frame``'s feature reads; frames are
        asked for in order."""
        mel = self.mel
        last = self.last_mel(frame)
        first = last - mel.receptive_field + 1
        if self.cache is None or self.first + self.cache.shape[1] <= first:
            self.cache, self.first = self._columns(buffer, buffer_start, first, last), first
        else:
            have = self.first + self.cache.shape[1] - 1  # the last frame cached
            if last > have:
                new = self._columns(buffer, buffer_start, have + 1, last)
                self.cache = torch.cat([self.cache, new], dim=1)
            self.cache = self.cache[:, first - self.first :]
            self.first = first
        return self.cache[:, : mel.receptive_field]

    def encode(self, windows: Tensor, shifts: list[int]) -> Tensor:
        """windows (B, n_mels, receptive_field) of :meth:`window`, the look-ahead shift of each
        (B streams of one model) -> their speech features (B, dim)."""
        x = self.encoder.convolve(windows)[:, :, -1]
        feats = self.encoder.norm(self.encoder.output(x))
        if self.speech.max_shift:
            feats = feats + self.speech.shift_embedding.weight[shifts]
        return feats


class WhisperEncoder(nn.Module):
    def __init__(self, cfg: SpeechEncoderConfig) -> None:
        super().__init__()
        if cfg.source:
            encoder = load_whisper_encoder(cfg.source)
        elif cfg.hf_config:
            encoder = WhisperAudioEncoder(cfg.hf_config).eval()
        else:
            raise TalkmeshError(
                "speech.kind whisper needs speech.source (a directory written by "
                "`talkmesh convert-whisper`) or speech.hf_config"
            )
        self.features = WhisperFeatures(encoder)
        self.dim = self.features.dim
        self.frozen = cfg.frozen
        if cfg.frozen:
            self.features.requires_grad_(False)

    def hf_config(self) -> dict[str, Any]:
        return self.features.encoder.config.to_dict()

    def train(self, mode: bool = True) -> WhisperEncoder:
        super().train(mode)
        if self.frozen:
            self.features.eval()  # a frozen encoder never runs dropout
        return self

    def forward(self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int) -> Tensor:
        if self.frozen:
            with torch.no_grad():
                return self.features(audio, audio_lengths, num_frames)
        return self.features(audio, audio_lengths, num_frames)


def build_speech_encoder(cfg: SpeechEncoderConfig) -> nn.Module:
    """The encoder for ``cfg.kind``; it has ``.dim`` and the forward described in the module doc."""
    if cfg.kind == "wav2vec2":
        return Wav2Vec2Encoder(cfg)
    if cfg.kind == "whisper":
        return WhisperEncoder(cfg)
    return MelEncoder(cfg)


class SpeechFeatures(nn.Module):
    """A speech encoder of ``cfg.kind`` mapped to ``out_dim`` with a LayerNorm (MeshTalk's audio
    encoder when its config names a talkmesh speech encoder instead of the paper's mel convs)."""

    def __init__(self, cfg: SpeechEncoderConfig, out_dim: int) -> None:
        super().__init__()
        self.encoder = build_speech_encoder(cfg)
        self.output = nn.Linear(self.encoder.dim, out_dim)
        self.norm = nn.LayerNorm(out_dim)

    def forward(self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int) -> Tensor:
        return self.norm(self.output(self.encoder(audio, audio_lengths, num_frames)))

    def set_statistics(self, audio: Tensor) -> None:
        if hasattr(self.encoder, "set_statistics"):
            self.encoder.set_statistics(audio)


def release_config(cfg: SpeechEncoderConfig, encoder: nn.Module) -> SpeechEncoderConfig:
    """The config a release stores: a pretrained encoder's full config instead of its source path
    (the weights travel in the release), so loading needs neither the path nor the network."""
    if cfg.source and hasattr(encoder, "hf_config"):
        return replace(cfg, source=None, hf_config=encoder.hf_config())
    return cfg
