"""A CodeTalker with a causal VQ decoder as two graphs that export to ONNX
(:mod:`talkmesh.models.onnx`): the speech encoder, and one generation step with its state as
inputs and outputs.

The autoregressive loop itself does not export (its length, caches and Jacobi passes are Python
control flow), so the step is :class:`talkmesh.models.codetalker.batch.FrameBatch`'s step written
as a pure function: the caller keeps the state and calls it once per frame. Each attention
layer's keys and values are a ring of its last W frames (frame ``t`` in row ``t % W``), rows a
stream has not filled yet masked by the bias, as in the batched server step.

Axis letters: B streams, N encoder frames (50 Hz), T motion frames, W window, V vertices.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from talkmesh.models.codetalker.batch import ring_bias
from talkmesh.models.layers import window_bias


class EncoderGraph(nn.Module):
    """Whisper's encoder on one window of log-mel: mel (1, n_mels, 2N) -> features (1, N, D)."""

    def __init__(self, encoder: nn.Module) -> None:
        super().__init__()
        self.encoder = encoder

    def forward(self, mel: Tensor) -> Tensor:
        return self.encoder(mel).last_hidden_state


class _Ring:
    """One attention layer's key/value rings, written functionally: :meth:`append` returns the
    rings with the current frame's row replaced and keeps them as the layer's new state."""

    def __init__(self, k: Tensor, v: Tensor, row: Tensor) -> None:
        self.k, self.v, self.row = k, v, row  # row (B, 1, W, 1) bool: the current frame's row

    def append(self, k: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        self.k = torch.where(self.row, k, self.k)  # k (B, heads, 1, dh) onto (B, heads, W, dh)
        self.v = torch.where(self.row, v, self.v)
        return self.k, self.v


class StepGraph(nn.Module):
    """One frame of generation: the frame's speech feature and the state -> its motion and the
    next state. Inputs (:meth:`input_names`): ``feature`` (B, D), ``t`` (B,) int64 the frame's
    index, ``style`` (B, d), for a model with ``stage2.head_decoder`` only ``face`` (B, hidden) the
    VQ decoder's head term (``CodeTalker.decoder_face``), ``x_in`` (B, 1, d) the frame's input (the
    style at frame 0), ``conv`` (B, 4, hidden) the VQ decoder's last conv inputs, then the rings
    (B, heads, W, d / heads) of :meth:`ring_names`.
    Outputs: ``motion`` (B, V * 3) offsets from the template, then ``x_in``, ``conv`` and the
    rings for the next frame."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        s2, vq = model.cfg.stage2, model.cfg.vq
        self.model = model
        self.components, self.code_dim = vq.components, vq.code_dim
        dec = model.vqvae.decoder
        fold = nn.Linear(dec.out.in_features, model.motion_map.out_features)
        with torch.no_grad():  # the VQ decoder's output map then the motion map, as one map
            fold.weight.copy_(model.motion_map.weight @ dec.out.weight)
            fold.bias.copy_(model.motion_map.weight @ dec.out.bias + model.motion_map.bias)
        self.fold = fold
        self.register_buffer("ppe", model.ppe(s2.period, torch.device("cpu")))
        s2_bias = window_bias(s2.heads, 1, s2.attention_window, s2.attention_window, s2.period)
        self.register_buffer("s2_bias", s2_bias[:, 0].flip(-1))
        vq_bias = window_bias(vq.heads, 1, vq.causal_window, vq.causal_window, 1)
        self.register_buffer("vq_bias", vq_bias[:, 0].flip(-1))
        self.s2_layers, self.vq_layers = len(model.blocks), len(dec.blocks)
        # models without the decoder's head term keep the inputs they always had
        self.face = getattr(model, "decoder_head", None) is not None

    def input_names(self) -> list[str]:
        """The inputs before the state: ``feature``, ``t``, ``style`` (and ``face``)."""
        return ["feature", "t", "style", *(["face"] if self.face else [])]

    def ring_names(self) -> list[str]:
        s2 = [f"s2_{kv}{n}" for n in range(self.s2_layers) for kv in "kv"]
        return s2 + [f"vq_{kv}{n}" for n in range(self.vq_layers) for kv in "kv"]

    def state_shapes(self) -> dict[str, tuple[int, ...]]:
        """Each state input's shape without its batch axis."""
        s2, vq = self.model.cfg.stage2, self.model.cfg.vq
        shapes = {"x_in": (1, s2.d_model), "conv": (4, vq.hidden)}
        for name in self.ring_names():
            if name.startswith("s2"):
                shapes[name] = (s2.heads, s2.attention_window, s2.d_model // s2.heads)
            else:
                shapes[name] = (vq.heads, vq.causal_window, vq.hidden // vq.heads)
        return shapes

    def forward(
        self, feature: Tensor, t: Tensor, style: Tensor, *rest: Tensor
    ) -> tuple[Tensor, ...]:
        """The inputs in the order of :meth:`input_names` then the state -> the outputs."""
        face, (x_in, conv, *rings) = (rest[0], rest[1:]) if self.face else (None, rest)
        model, dec = self.model, self.model.vqvae.decoder
        B = feature.shape[0]
        cross = model.cross_terms(model.audio_map(feature)[:, None])
        x = x_in + self.ppe[t % self.ppe.shape[0]][:, None]
        W = self.s2_bias.shape[1]
        row = (torch.arange(W)[None] == (t % W)[:, None])[:, None, :, None]
        s2 = [_Ring(rings[2 * n], rings[2 * n + 1], row) for n in range(self.s2_layers)]
        out = model.decode_features(x, cross, ring_bias(self.s2_bias, t), s2)
        quantizer = model.vqvae.quantizer
        codes = quantizer(out.view(B, 1, self.components, self.code_dim)).codes
        x = dec.inputs(quantizer.lookup(codes), face)  # (B, 1, hidden)
        past = torch.where((t == 0)[:, None, None], x, conv)  # the conv pads with frame 0
        seq = torch.cat([past, x], dim=1)  # (B, 5, hidden)
        h = dec.mid(dec.conv.step(seq.transpose(1, 2)[:, None]))
        W = self.vq_bias.shape[1]
        row = (torch.arange(W)[None] == (t % W)[:, None])[:, None, :, None]
        base = 2 * self.s2_layers
        vq = [
            _Ring(rings[base + 2 * n], rings[base + 2 * n + 1], row) for n in range(self.vq_layers)
        ]
        bias = ring_bias(self.vq_bias, t)
        for block, ring in zip(dec.blocks, vq):
            h = block(h, bias, ring)
        h = dec.norm(h)
        motion = dec.out(h[:, 0]) * dec.scale
        x_next = self.fold(h) + style[:, None]
        new_rings = [r for ring in s2 + vq for r in (ring.k, ring.v)]
        return (motion, x_next, seq[:, 1:], *new_rings)
