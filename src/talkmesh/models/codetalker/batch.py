"""Streaming CodeTalker frames for many streams at once: one model step computes the next frame
of every stream that has one ready, whatever frame each stream is at.

Every stream of a model owns a slot of :class:`FrameBatch`: its style vector (and, for a model
with ``stage2.head_decoder``, its VQ decoder's head term), its next input,
the last inputs of the VQ decoder's convolution and, per attention layer, a ring of the keys and
values of its last ``window`` frames (frame ``t`` in row ``t % window``). A step gathers the
slots of the streams in it, so streams at frame 3 and at frame 3000 share one matrix product per
layer: a ring always holds ``window`` rows, the rows a stream has not filled yet are masked, and
each row's ALiBi bias comes from its distance to the stream's current frame
(:func:`ring_bias`). Attention does not depend on the order of its keys, so a stream computes
the frames it would compute alone (:class:`talkmesh.models.codetalker.generate.FrameGenerator`'s
``step``, and offline ``generate``) up to float rounding.

Axis letters: B streams in a step, N slots, H face components, W window, V vertices.
"""

from __future__ import annotations

import threading
import weakref

import numpy as np
import torch
from torch import Tensor, nn

from talkmesh.models.base import FrameRequest
from talkmesh.models.layers import folded_linear, window_bias


def ring_bias(by_distance: Tensor, t: Tensor) -> Tensor:
    """by_distance (heads, W): the bias of a key ``d`` frames before the query; t (B,) each
    stream's current frame -> (B, heads, 1, W) the bias of ring rows ``j`` (frame
    ``t - (t - j) mod W``), -inf where that frame is before the stream's start."""
    W = by_distance.shape[1]
    dist = (t[:, None] - torch.arange(W, device=t.device)[None]) % W  # (B, W)
    bias = by_distance[:, dist].permute(1, 0, 2)  # (B, heads, W)
    bias = bias.masked_fill((dist > t[:, None])[:, None], float("-inf"))
    return bias[:, :, None]


class RingView:
    """One attention layer's key/value rings seen by the streams of a step: the
    :class:`talkmesh.models.layers.KVCache` interface that :class:`talkmesh.models.layers.Attention`
    calls."""

    def __init__(self, k: Tensor, v: Tensor, slots: Tensor, rows: Tensor) -> None:
        self.k, self.v, self.slots, self.rows = k, v, slots, rows
        # the slots of a step are sorted: consecutive ones are read as a view, without a copy
        first, last = int(slots[0]), int(slots[-1])
        self.span = slice(first, last + 1) if last - first + 1 == len(slots) else slots

    def append(self, k: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """k, v (B, heads, 1, dh) of the current frames -> the rings (B, heads, W, dh)."""
        self.k[self.slots, :, self.rows] = k[:, :, 0]
        self.v[self.slots, :, self.rows] = v[:, :, 0]
        return self.k[self.span], self.v[self.span]


class FrameBatch:
    """All streams of one CodeTalker with a causal VQ decoder (mel or Whisper speech encoder),
    one slot each; :meth:`step` runs the next frame of any of them together (module docstring).
    Thread-safe: streams open and close while another thread steps."""

    def __init__(self, model: nn.Module) -> None:
        s2, vq = model.cfg.stage2, model.cfg.vq
        self.model = model
        # reentrant: a stream garbage-collected during a step frees its slot from that thread
        self.lock = threading.RLock()
        self.dec = model.vqvae.decoder
        self.fold = folded_linear(
            model, self.dec.out, model.motion_map, int8=getattr(model, "int8", False)
        )
        self.ppe = model.ppe(s2.period, torch.device("cpu"))
        # bias by distance: the last column of the step bias is the query's own frame
        self.s2_bias = window_bias(s2.heads, 1, s2.attention_window, s2.attention_window, s2.period)
        self.s2_bias = self.s2_bias[:, 0].flip(-1)
        self.vq_bias = window_bias(vq.heads, 1, vq.causal_window, vq.causal_window, 1)[:, 0].flip(
            -1
        )
        self.shapes = {
            "style": (s2.d_model,),
            "x_in": (1, s2.d_model),
            "conv": (4, vq.hidden),  # the VQ decoder's conv: the 4 inputs before the frame
        }
        if getattr(model, "decoder_head", None) is not None:
            self.shapes["face"] = (vq.hidden,)  # the VQ decoder's head term, per stream
        for n in range(len(model.blocks)):
            ring = (s2.heads, s2.attention_window, s2.d_model // s2.heads)
            self.shapes[f"s2_k{n}"] = self.shapes[f"s2_v{n}"] = ring
        for n in range(len(self.dec.blocks)):
            ring = (vq.heads, vq.causal_window, vq.hidden // vq.heads)
            self.shapes[f"vq_k{n}"] = self.shapes[f"vq_v{n}"] = ring
        self.state = {name: torch.zeros(0, *shape) for name, shape in self.shapes.items()}
        self._projection = None
        self.t: list[int] = []  # per slot: frames computed
        self.free: list[int] = []

    # -- slots
    def open(self, stream: object, style: Tensor, face: Tensor | None = None) -> int:
        """A slot for ``stream`` (style (d,), face (hidden,) its VQ decoder's head term where the
        model has one; None: the average head's); freed when the stream is garbage-collected."""
        with self.lock, torch.inference_mode():
            if not self.free:
                N = len(self.t)
                grow = max(4, N)
                for name, shape in self.shapes.items():
                    self.state[name] = torch.cat([self.state[name], torch.zeros(grow, *shape)])
                self.t += [0] * grow
                self.free = list(range(N + grow - 1, N - 1, -1))
            slot = self.free.pop()
            self.t[slot] = 0
            self.state["style"][slot] = style
            self.state["x_in"][slot] = style  # frame 0's input: the style alone
            if "face" in self.state:
                self.state["face"][slot] = (
                    self.model.decoder_face(None)[0] if face is None else face
                )
        weakref.finalize(stream, self._close, slot)
        return slot

    def _close(self, slot: int) -> None:
        with self.lock:
            self.free.append(slot)

    def __len__(self) -> int:
        """Streams open."""
        return len(self.t) - len(self.free)

    # -- one step
    def step(self, requests: list[FrameRequest], basis: np.ndarray | None = None) -> np.ndarray:
        """The next frame of each request's stream (each stream at most once) -> motion
        (B, V * 3) float32 offsets from the template, in the order of ``requests``; with
        ``basis`` (K, V * 3) their projections onto it (B, K) float64 instead, through the
        output map folded with the basis (:meth:`projection`), without the V * 3 coordinates.

        Long because it is the model's step in one piece: speech features, stage 2, the VQ
        decoder, the fed-back input."""
        model, dec, S = self.model, self.dec, self.state
        order = sorted(range(len(requests)), key=lambda i: requests[i].stream.slot)
        requests = [requests[i] for i in order]
        with self.lock, torch.inference_mode():
            slots = torch.tensor([r.stream.slot for r in requests])
            if len(set(slots.tolist())) != len(requests):
                raise ValueError("a step computes one frame per stream")
            for r in requests:
                if r.frame != self.t[r.stream.slot]:
                    raise ValueError(f"frame {r.frame} asked for out of order")
            t = torch.tensor([r.frame for r in requests])
            B = len(requests)
            # the speech features (each stream's mel stack, or its Whisper block's feature;
            # the Whisper windows that streams start this step are encoded together)
            prepare = getattr(requests[0].stream.features, "prepare", None)
            if prepare is not None:
                prepare([(r.stream.features, *r[1:]) for r in requests])
            windows = torch.stack([r.stream.features.window(*r[1:]) for r in requests])
            shifts = [r.stream.features.shift for r in requests]
            feats = requests[0].stream.features.encode(windows, shifts)
            cross = model.cross_terms(model.audio_map(feats)[:, None])
            # stage 2: the codes of the frame
            x = S["x_in"][slots] + self.ppe[t % len(self.ppe)][:, None]
            W = self.s2_bias.shape[1]
            rings = [
                RingView(S[f"s2_k{n}"], S[f"s2_v{n}"], slots, t % W)
                for n in range(len(model.blocks))
            ]
            out = model.decode_features(x, cross, ring_bias(self.s2_bias, t), rings)
            vq = model.cfg.vq
            codes = model.vqvae.quantizer(out.view(B, 1, vq.components, vq.code_dim)).codes
            # the causal VQ decoder's step (vq.DecoderStep), its conv padded on the
            # left with the stream's first frame
            face = S["face"][slots] if "face" in S else None
            x = dec.inputs(model.vqvae.quantizer.lookup(codes), face)  # (B, 1, hidden)
            past = torch.where((t == 0)[:, None, None], x, S["conv"][slots])
            seq = torch.cat([past, x], dim=1)  # (B, 5, hidden)
            S["conv"][slots] = seq[:, 1:]
            h = dec.mid(dec.conv.step(seq.unfold(1, 5, 1)))
            W = self.vq_bias.shape[1]
            bias = ring_bias(self.vq_bias, t)
            for n, block in enumerate(dec.blocks):
                h = block(h, bias, RingView(S[f"vq_k{n}"], S[f"vq_v{n}"], slots, t % W))
            h = dec.norm(h)
            # the next frame's input, and this frame's motion
            S["x_in"][slots] = self.fold(h) + S["style"][slots][:, None]
            for r in requests:
                self.t[r.stream.slot] += 1
            if basis is None:
                result = (dec.out(h[:, 0]) * dec.scale).numpy()
            else:
                weight, bias = self.projection(basis)
                result = h[:, 0].double().numpy() @ weight + bias
        out = np.empty_like(result)
        out[order] = result
        return out

    def projection(self, basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The VQ decoder's output map followed by the projection onto ``basis`` (K, V * 3) as
        one affine map of its hidden states: weight (hidden, K), bias (K,), float64. Kept for
        the last basis asked for (a server has one face)."""
        key = (id(basis), basis.shape)
        if self._projection is None or self._projection[0] != key:
            out, scale = self.dec.out, self.dec.scale.double()
            scaled = basis.astype(np.float64) * scale.numpy()  # (K, V * 3)
            weight = out.weight.double().numpy().T @ scaled.T
            bias = scaled @ out.bias.double().numpy()
            self._projection = (key, (weight, bias), basis)
        return self._projection[1]


_CREATE = threading.Lock()


def frame_batch(model: nn.Module) -> FrameBatch:
    """The model's one :class:`FrameBatch` (kept on the model, outside its state dict)."""
    with _CREATE:
        batch = model.__dict__.get("_frame_batch")
        if batch is None:
            with torch.inference_mode():
                batch = model.__dict__["_frame_batch"] = FrameBatch(model)
    return batch
