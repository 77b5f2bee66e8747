"""Whisper's audio encoder (Radford et al. 2022, "Robust Speech Recognition via Large-Scale Weak
Supervision", Sec. 2.2), written out so that running a model needs no ``transformers`` import.

Importing ``transformers``' Whisper classes costs seconds on every ``talkmesh animate`` of the
bundled model, more than the model itself. The architecture is small: two convolutions (the
second with stride 2: one feature per 20 ms), GELU, learned or sinusoidal positions, pre-norm
transformer layers (self-attention whose key projection has no bias, a GELU feed-forward), a final
LayerNorm. Parameter names are those of ``transformers.WhisperEncoder``, so its state dicts, the
converted encoders of :mod:`talkmesh.models.whisper` and the releases that hold one load as they
are; ``tests/test_whisper.py`` checks the output against ``transformers``' own class.

:class:`EncoderConfig` keeps the HuggingFace config dict it was made from (``to_dict``), so a
release written with this encoder stores the same ``hf_config`` as before.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.errors import TalkmeshError

NEEDED = ("d_model", "num_mel_bins", "encoder_layers", "encoder_attention_heads", "encoder_ffn_dim")


class EncoderConfig:
    """The encoder's sizes from a HuggingFace ``WhisperConfig`` dict (the rest is kept as is)."""

    def __init__(self, hf: dict[str, Any]) -> None:
        missing = [k for k in NEEDED if not isinstance(hf.get(k), int) or hf[k] < 1]
        if missing:
            raise TalkmeshError(f"not a Whisper encoder config: {missing[0]} missing or invalid")
        activation = hf.get("activation_function", "gelu")
        if activation != "gelu":
            raise TalkmeshError(f"Whisper encoder with {activation!r} activations: only gelu")
        self._hf = dict(hf)
        self.d_model: int = hf["d_model"]
        self.num_mel_bins: int = hf["num_mel_bins"]
        self.encoder_layers: int = hf["encoder_layers"]
        self.encoder_attention_heads: int = hf["encoder_attention_heads"]
        self.encoder_ffn_dim: int = hf["encoder_ffn_dim"]
        self.max_source_positions: int = int(hf.get("max_source_positions", 1500))
        self.dropout = float(hf.get("dropout") or 0.0)
        self.attention_dropout = float(hf.get("attention_dropout") or 0.0)
        self.activation_dropout = float(hf.get("activation_dropout") or 0.0)
        if self.d_model % self.encoder_attention_heads:
            raise TalkmeshError(
                f"Whisper encoder: d_model {self.d_model} does not split into "
                f"{self.encoder_attention_heads} heads"
            )

    def to_dict(self) -> dict[str, Any]:
        return dict(self._hf)


class EncoderOutput(NamedTuple):
    last_hidden_state: Tensor  # (N, n, d_model)


class Attention(nn.Module):
    def __init__(self, dim: int, heads: int, dropout: float) -> None:
        super().__init__()
        self.heads = heads
        self.dropout = dropout
        self.q_proj = nn.Linear(dim, dim)
        self.k_proj = nn.Linear(dim, dim, bias=False)
        self.v_proj = nn.Linear(dim, dim)
        self.out_proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor) -> Tensor:
        N, n, dim = x.shape

        def split(t: Tensor) -> Tensor:
            return t.view(N, n, self.heads, dim // self.heads).transpose(1, 2)

        q, k, v = split(self.q_proj(x)), split(self.k_proj(x)), split(self.v_proj(x))
        drop = self.dropout if self.training else 0.0
        out = F.scaled_dot_product_attention(q, k, v, dropout_p=drop)
        return self.out_proj(out.transpose(1, 2).reshape(N, n, dim))


class EncoderLayer(nn.Module):
    def __init__(self, cfg: EncoderConfig) -> None:
        super().__init__()
        d = cfg.d_model
        self.cfg = cfg
        self.self_attn = Attention(d, cfg.encoder_attention_heads, cfg.attention_dropout)
        self.self_attn_layer_norm = nn.LayerNorm(d)
        self.fc1 = nn.Linear(d, cfg.encoder_ffn_dim)
        self.fc2 = nn.Linear(cfg.encoder_ffn_dim, d)
        self.final_layer_norm = nn.LayerNorm(d)

    def forward(self, x: Tensor) -> Tensor:
        c, train = self.cfg, self.training
        x = x + F.dropout(self.self_attn(self.self_attn_layer_norm(x)), c.dropout, train)
        h = F.dropout(F.gelu(self.fc1(self.final_layer_norm(x))), c.activation_dropout, train)
        return x + F.dropout(self.fc2(h), c.dropout, train)


class WhisperAudioEncoder(nn.Module):
    """``forward(mel (N, num_mel_bins, 2n)) -> EncoderOutput((N, n, d_model))`` for any ``n`` up to
    ``max_source_positions``: the first ``n`` positions are used (Whisper itself always pads to
    30 s; shorter windows are how :class:`~talkmesh.models.whisper.WhisperFeatures` runs fast)."""

    def __init__(self, config: EncoderConfig | dict[str, Any]) -> None:
        super().__init__()
        cfg = config if isinstance(config, EncoderConfig) else EncoderConfig(config)
        self.config = cfg
        d = cfg.d_model
        self.conv1 = nn.Conv1d(cfg.num_mel_bins, d, kernel_size=3, padding=1)
        self.conv2 = nn.Conv1d(d, d, kernel_size=3, stride=2, padding=1)
        self.embed_positions = nn.Embedding(cfg.max_source_positions, d)
        self.embed_positions.requires_grad_(False)
        self.layers = nn.ModuleList(EncoderLayer(cfg) for _ in range(cfg.encoder_layers))
        self.layer_norm = nn.LayerNorm(d)

    def forward(self, mel: Tensor) -> EncoderOutput:
        n = mel.shape[-1] // 2
        if (
            mel.dim() != 3
            or mel.shape[-1] != 2 * n
            or not 0 < n <= self.config.max_source_positions
        ):
            raise TalkmeshError(
                f"the Whisper encoder takes (N, {self.config.num_mel_bins}, 2n) mel frames with "
                f"n <= {self.config.max_source_positions}, got {tuple(mel.shape)}"
            )
        x = F.gelu(self.conv2(F.gelu(self.conv1(mel)))).transpose(1, 2)
        x = F.dropout(x + self.embed_positions.weight[:n], self.config.dropout, self.training)
        for layer in self.layers:
            x = layer(x)
        return EncoderOutput(self.layer_norm(x))


__all__ = ["EncoderConfig", "EncoderOutput", "WhisperAudioEncoder"]
