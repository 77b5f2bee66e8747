"""The log-mel speech encoder (MeshTalk, Richard et al., ICCV 2021, Sec. 3.1), shared by MeshTalk's
expression space and prior and by the ``mel`` kind of :mod:`talkmesh.models.speech`.

:class:`MelAudioEncoder`: log-mel spectrogram (torch.stft + a mel filterbank buffer, 80 bins, 16 kHz)
and dilated convolutions whose receptive field is exactly a window of mel frames around each motion
frame (``context`` before, ``lookahead`` after). The speech-encoder call:
``forward(audio (B, S), audio_lengths (B,) | None, num_frames) -> (B, T, D)``.

Axis letters: B batch, S audio samples, T motion frames, M mel frames, D width.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import TalkmeshError

LEAKY_SLOPE = 0.2  # LeakyReLU slope used throughout MeshTalk, as in the official code
LOG_FLOOR = 1e-5  # power floor before the log: silence maps to log(LOG_FLOOR)
DEFAULT_MEL_MEAN = -4.0  # rough log-mel statistics of speech; replace with data via set_statistics
DEFAULT_MEL_STD = 4.0
MS_PER_S = 1000.0
WINDOW_BLOCK = 64  # windows transformed at once in ``windows`` mode (bounds the STFT's memory)


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
    # the softmax and the Gumbel gradients to the expression path vanished (docs/results/meshtalk.md)
    layer_norm: bool = False
    # official-exact options (facebookresearch/meshtalk models/encoders.py; on in imported models):
    input_kernel: int = 1  # kernel of the first conv (mels -> width); official 5
    log_floor: float = LOG_FLOOR  # power floor before the log; official 1e-10
    # official: every motion frame reads its own 1 s of audio (hop sample_rate // fps, centred on
    # the frame), each window's spectrogram reflect-padded alone, the stack's output averaged over
    # time; talkmesh: one spectrogram of the whole utterance, streamable
    windows: bool = False
    gain: float = (
        0.0  # scale each utterance to this mean absolute amplitude (official 0.01); 0: off
    )
    # per-bin log-mel mean and std fitted on the training audio (set_statistics); official: none
    # (the log-mels enter the convs as they are: mean 0, std 1)
    mel_statistics: bool = True

    def __post_init__(self) -> None:
        if self.sample_rate <= 0 or self.hop_length <= 0 or self.n_mels <= 0:
            raise TalkmeshError(
                "meshtalk audio config: sample_rate, hop_length and n_mels must be positive"
            )
        if not 0 < self.win_length <= self.n_fft:
            raise TalkmeshError("meshtalk audio config: win_length must be in (0, n_fft]")
        if self.kernel_size < 1 or not self.dilations or min(self.dilations) < 1:
            raise TalkmeshError("meshtalk audio config: kernel_size and dilations must be >= 1")
        if self.input_kernel < 1 or self.log_floor <= 0 or self.gain < 0:
            raise TalkmeshError(
                "meshtalk audio config: input_kernel >= 1, log_floor > 0 and gain >= 0 needed"
            )
        if self.lookahead_frames > self.receptive_field - 1 or self.lookahead_ms < 0:
            raise TalkmeshError(
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
        return self.input_kernel + (self.kernel_size - 1) * sum(self.dilations)

    @property
    def lookahead_frames(self) -> int:
        return int(round(self.lookahead_ms / MS_PER_S * self.mel_rate))

    @property
    def context_frames(self) -> int:
        return self.receptive_field - 1 - self.lookahead_frames


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
        mean, std = (DEFAULT_MEL_MEAN, DEFAULT_MEL_STD) if cfg.mel_statistics else (0.0, 1.0)
        self.register_buffer("mel_mean", torch.full((cfg.n_mels,), mean))
        self.register_buffer("mel_std", torch.full((cfg.n_mels,), std))
        self.input = nn.Conv1d(cfg.n_mels, cfg.width, kernel_size=cfg.input_kernel)
        self.convs = nn.ModuleList(
            nn.Conv1d(cfg.width, cfg.width, cfg.kernel_size, dilation=d) for d in cfg.dilations
        )
        self.output = nn.Linear(cfg.width, cfg.out_dim)
        self.norm = nn.LayerNorm(cfg.out_dim) if cfg.layer_norm else nn.Identity()

    def log_mel(self, audio: Tensor, center: bool = True, pad_mode: str = "constant") -> Tensor:
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
            pad_mode=pad_mode,
            return_complex=True,
        )
        power = spec.real.square() + spec.imag.square()
        mel = torch.einsum("bfm,fn->bnm", power, self.filterbank)
        return torch.log(mel.clamp(min=cfg.log_floor))

    @torch.no_grad()
    def set_statistics(self, audio: Tensor) -> None:
        """Per-bin log-mel mean and std from training audio (B, S) (buffers: saved with the weights);
        nothing with ``mel_statistics`` off (the official encoder: mean 0, std 1)."""
        if not self.cfg.mel_statistics:
            return
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
            raise TalkmeshError(
                f"meshtalk audio encoder: audio must be (B, S), got {tuple(audio.shape)}"
            )
        if num_frames < 1:
            raise TalkmeshError("meshtalk audio encoder: num_frames must be at least 1")
        if audio_lengths is not None:  # padded batches: silence past each sample's end
            valid = torch.arange(audio.shape[1], device=audio.device)[None] < audio_lengths[:, None]
            audio = audio * valid
        if cfg.gain:
            audio = self.scale_gain(audio, audio_lengths)
        if cfg.windows:
            return self.windowed(audio, num_frames, shift)
        centres = self.frame_indices(num_frames).to(audio.device) + shift
        last_mel = (
            int(centres[-1]) + cfg.lookahead_frames
        )  # the last mel frame any motion frame sees
        # exactly the samples those mel frames read, zero-padded when the audio ends early, so a
        # sample gives the same features alone or padded in a batch
        needed = last_mel * cfg.hop_length + cfg.n_fft // 2 + 1
        audio = F.pad(audio[:, :needed], (0, max(0, needed - audio.shape[1])))
        mel = self.log_mel(audio)[:, :, : last_mel + 1]
        mel = F.pad(mel, (cfg.context_frames, 0), value=math.log(cfg.log_floor))  # before t=0
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

    def scale_gain(self, audio: Tensor, audio_lengths: Tensor | None) -> Tensor:
        """(B, S) -> each utterance scaled to mean absolute amplitude ``cfg.gain`` (official
        ``load_audio``: "energy matches average energy of audio used in training")."""
        n = audio.new_full((audio.shape[0],), audio.shape[1])
        if audio_lengths is not None:
            n = audio_lengths.to(audio.dtype)
        level = audio.abs().sum(1) / n.clamp(min=1)
        return audio * (self.cfg.gain / level.clamp(min=1e-12))[:, None]

    def window_hop(self) -> int:
        """Samples between motion frames in ``windows`` mode (official: sample_rate // fps)."""
        return int(self.cfg.sample_rate // self.fps)

    def window_frames(self, samples: int) -> int:
        """The motion frames the official ``audio_chunking`` makes from ``samples``: one per
        hop whose 1 s window (centred on the frame) fits the zero-padded audio."""
        hop, size = self.window_hop(), self.cfg.sample_rate
        padded = samples + 2 * ((size - hop) // 2)
        return max(0, -(-(padded - size) // hop))

    def windowed(self, audio: Tensor, num_frames: int, shift: int = 0) -> Tensor:
        """Official ``windows`` mode: (B, S) -> (B, T, out_dim). Frame t reads samples
        [t*hop - pad, t*hop - pad + sample_rate) (zeros outside the audio), pad = (sample_rate -
        hop) // 2; ``shift`` moves every window that many mel hops later."""
        cfg = self.cfg
        hop, size = self.window_hop(), cfg.sample_rate
        pad = (size - hop) // 2
        start = pad - shift * cfg.hop_length
        x = F.pad(audio, (max(0, start), 0))[:, max(0, -start) :]
        need = (num_frames - 1) * hop + size
        x = F.pad(x[:, :need], (0, max(0, need - x.shape[1])))
        windows = x.unfold(1, size, hop)  # (B, T, size): a view, no copy
        B, T = windows.shape[:2]
        out = []
        for block in windows.reshape(B * T, size).split(WINDOW_BLOCK):
            mel = self.log_mel(block, pad_mode="reflect")  # each window alone, as officially
            out.append(self.convolve(mel).mean(-1))  # (N, width): the stack's output, averaged
        x = torch.cat(out).view(B, T, -1)
        return self.norm(self.output(x))
