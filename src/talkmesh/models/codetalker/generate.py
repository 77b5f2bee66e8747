"""CodeTalker's generation engine (:meth:`talkmesh.models.codetalker.model.CodeTalker.generate`).

:class:`FrameGenerator` runs stage 2 and the VQ decoder over the next frames with key/value
caches, one frame (:meth:`FrameGenerator.step`) or a pass of guessed frames
(:meth:`FrameGenerator.block`, Jacobi decoding) at a time; streaming uses the same steps.
:func:`generate_fast` schedules the passes (:class:`PassSchedule`); :func:`generate_exact` is the
paper's loop with stage-2 caches.

Axis letters: B batch, T frames, K frames of one pass, H face components, V vertices.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.models.base import FrameRequest, FrameStream
from talkmesh.models.codetalker.batch import frame_batch
from talkmesh.models.codetalker.vq import DecoderStep, Quantized
from talkmesh.models.layers import KVCache, folded_linear, sinusoid, window_bias
from talkmesh.models.speech import MelFeatureStream
from talkmesh.models.whisper_stream import WhisperFeatureStream, streamed_features

# Fast mode's pass schedule. Each pass runs K frames from guesses of their codes and keeps those up
# to the first wrong guess; a pass costs little more than one step, so long passes pay while the
# guesses hold and are a waste while they fail early.
PASS_PER_KEPT = 4  # a pass runs this many times the frames passes kept lately (running mean) ...
MIN_PASS = 2  # ... and at least this many (one frame is a step)
ONE_FRAME_RUN = 1.5  # passes keep fewer frames than this on average: they keep one frame only, and
STEPS_BEFORE_RETRY = 8  # ... frames then run one at a time (this many at first, doubling each
MAX_STEPS_BEFORE_RETRY = 16 * STEPS_BEFORE_RETRY  # time up to this) before a short pass is tried
RETRY_RUN = 2.0  # the running mean a retry starts from


class PassSchedule:
    """How many frames the next pass of :func:`generate_fast` runs (the constants above)."""

    def __init__(self, most: int) -> None:
        self.most = most  # the longest pass
        self.run: float = float(most)  # frames passes keep when a guess fails (running mean)
        self.alone = 0  # frames to run one at a time before passes are tried again ...
        self.wait = STEPS_BEFORE_RETRY  # ... the next time passes keep one frame only

    def length(self, done: int, remaining: int) -> int:
        """The next pass's length once ``done`` frames are final and ``remaining`` are left."""
        K = min(self.most, max(MIN_PASS, round(PASS_PER_KEPT * self.run)), remaining)
        if done == 0 or self.alone:  # frame 0 needs no guess: its input has no motion
            K, self.alone = 1, max(0, self.alone - 1)
        return K

    def update(self, kept: int, guessed: int) -> None:
        """After a pass of more than one frame that kept ``kept`` frames from ``guessed`` guesses."""
        # guesses that fail early again and again make long passes a waste: shorten them
        self.run = self.most if kept > guessed else (self.run + kept) / 2
        if self.run < ONE_FRAME_RUN:  # passes keep one frame, and each costs more than a step:
            self.alone = self.wait  # steps for a while (longer each time), then a short pass
            self.wait = min(2 * self.wait, MAX_STEPS_BEFORE_RETRY)
            self.run = RETRY_RUN
        elif kept > 1:
            self.wait = STEPS_BEFORE_RETRY


def generate_fast(
    model: nn.Module,
    style: Tensor,
    cross: list[Tensor],
    num_frames: int,
    block: int | None = None,
    face: Tensor | None = None,
) -> tuple[Tensor, Tensor | None]:
    """A CodeTalker's codes (B, T, H), and with a causal VQ decoder the motion (B, T, V*3) too;
    ``style`` (B, d), ``cross`` per decoder layer the (B, T, d) audio terms, ``face`` (B, hidden)
    the VQ decoder's head term (``CodeTalker.decoder_face``; None: none).

    Frames go through :meth:`FrameGenerator.block` up to ``block`` at a time (default
    ``model.generate_block``), each pass guessing its codes from the previous one; ``block=1`` is
    the plain frame-by-frame loop. Either way the codes are those of the frame-by-frame loop.
    """
    vq = model.cfg.vq
    B = style.shape[0]
    codes = torch.empty(B, num_frames, vq.components, dtype=torch.long, device=style.device)
    motion = style.new_empty(B, num_frames, vq.num_vertices * 3) if vq.causal else None
    done = moved = 0  # frames whose codes are final; frames whose motion is written
    passes = fast_passes(
        model, style, lambda a, b: [c[:, a:b] for c in cross], num_frames, block, face
    )
    for kept, frames in passes:
        codes[:, done : done + kept.shape[1]] = kept
        done += kept.shape[1]
        if frames is not None and motion is not None:
            motion[:, moved : moved + frames.shape[1]] = frames
            moved += frames.shape[1]
    return codes, motion


def fast_passes(
    model: nn.Module,
    style: Tensor,
    cross: Callable[[int, int], list[Tensor]],
    num_frames: int,
    block: int | None = None,
    face: Tensor | None = None,
) -> Iterator[tuple[Tensor, Tensor | None]]:
    """:func:`generate_fast`'s passes one at a time, for generation in chunks: ``cross(t0, t1)``
    gives per decoder layer the (B, t1 - t0, d) audio terms of frames t0..t1-1 (asked for in
    increasing order: ``t0`` never goes back). Yields each pass's kept codes (B, A, H) and, with a
    causal VQ decoder, the motion (B, M, V*3) of the frames that became final (None otherwise);
    the last frame's motion comes last, with no codes. ``face`` as in :func:`generate_fast`."""
    gen = FrameGenerator(model, style, face)
    B, H = style.shape[0], model.cfg.vq.components
    schedule = PassSchedule(max(1, block or model.generate_block))
    done = 0  # frames whose codes are final
    # the latest codes passes gave for the frames after ``done``
    guesses = torch.empty(B, 0, H, dtype=torch.long, device=style.device)
    while done < num_frames:
        K = schedule.length(done, num_frames - done)
        drafts = guesses[:, : K - 1]
        kept, after, frames = gen.block(cross(done, done + K), drafts)
        guesses = torch.cat([after, guesses[:, K:]], dim=1)  # older ones past this pass stay
        done += kept.shape[1]
        if K > 1:
            schedule.update(kept.shape[1], drafts.shape[1])
        yield kept, frames
    if gen.causal:  # the last frame's motion; a bidirectional decoder's feedback is not needed
        yield guesses[:, :0], gen.flush()


def generate_exact(
    model: nn.Module,
    style: Tensor,
    cross: list[Tensor],
    num_frames: int,
    face: Tensor | None = None,
) -> Tensor:
    """A CodeTalker's codes (B, T, H) of the naive loop, one frame at a time: the stage-2 decoder
    with its caches (the same computation: it is causal), the fed-back frame from the
    bidirectional VQ decoder over the prefix, re-run at every step as in the paper's loop (only
    its hidden states: the output and motion maps are folded into one). ``face`` as in
    :func:`generate_fast`."""
    gen = FrameGenerator(model, style, face)
    vq = model.cfg.vq
    B, window = style.shape[0], max(1, model.cfg.stage2.attention_window // vq.temporal_unit)
    codes = torch.empty(B, num_frames, vq.components, dtype=torch.long, device=style.device)
    feedback = PrefixFeedback(model.vqvae.decoder, face)
    for t in range(num_frames):
        codes[:, t] = gen.codes_step([c[:, t : t + 1] for c in cross])
        if t + 1 < num_frames:
            start = max(0, t + 1 - window)
            z_q = model.vqvae.quantizer.lookup(codes[:, start : t + 1])
            gen.feed(feedback(z_q, start * vq.temporal_unit))
    return codes


class PrefixFeedback:
    """The bidirectional VQ decoder's last frame over a prefix that grows by one frame a call,
    ``decoder.hidden(z_q, offset=offset, face=face)[:, -1:]``, computing only what the fed-back frame needs:
    the input map of the new frame alone, the convolution of the last three frames alone (with
    the replicate padding, frame i reads frames i-2..i+2, so frames up to T-3 keep their
    pre-normalisation outputs as the prefix grows; the instance statistics and everything after
    them still span the prefix), and in the last block only the last row (the others' keys and
    values). Other calls (the window sliding, temporal units, int8 layers, causal decoders) take
    the full pass. ``face`` (B, hidden): the head term added to every frame's input."""

    def __init__(self, decoder: nn.Module, face: Tensor | None = None) -> None:
        cfg = decoder.cfg
        self.decoder, self.face = decoder, face
        self.usable = (
            cfg.temporal_unit == 1
            and not cfg.causal
            and decoder.conv.linear is None
            and isinstance(decoder.blocks[-1].attn.qkv, nn.Linear)
            and isinstance(decoder.inp, nn.Linear)
        )
        self.x: Tensor | None = None  # (B, T, D) input-map rows of the prefix
        self.fixed: Tensor | None = None  # (B, D, T - 3) conv outputs no new frame changes

    def __call__(self, z_q: Tensor, offset: int) -> Tensor:
        """z_q (B, T, H, C) of frames offset..offset+T-1 -> (B, 1, hidden)."""
        dec, T = self.decoder, z_q.shape[1]
        known = 0 if self.x is None else self.x.shape[1]
        if not self.usable or offset or T < 6 or T != known + 1:
            self.x = self.fixed = None
            if self.usable and not offset and T >= 5:
                self._start(z_q)
            return dec.hidden(z_q, offset=offset, face=self.face)[:, -1:]
        x = self.x = torch.cat([self.x, dec.inputs(z_q[:, -1:], self.face)], dim=1)
        tail = F.pad(x[:, -5:].transpose(1, 2), (0, 2), mode="replicate")
        new = F.leaky_relu(dec.conv.conv(tail), 0.2)  # (B, D, 3): frames T-3..T-1
        pre = torch.cat([self.fixed, new], dim=2)
        self.fixed = pre[:, :, : T - 2]
        h = dec.mid((dec.conv.norm(pre) if dec.conv.norm is not None else pre).transpose(1, 2))
        if dec.cfg.frame_positions:
            h = h + sinusoid(torch.arange(T, device=h.device), h.shape[-1])
        for block in dec.blocks[:-1]:
            h = block(h)
        return dec.norm(_last_row(dec.blocks[-1], h))

    def _start(self, z_q: Tensor) -> None:
        """Keep the input rows and fixed conv outputs of a prefix of T >= 5 frames."""
        dec, T = self.decoder, z_q.shape[1]
        self.x = dec.inputs(z_q, self.face)
        pre = F.leaky_relu(dec.conv.conv(F.pad(self.x.transpose(1, 2), (2, 2), "replicate")), 0.2)
        self.fixed = pre[:, :, : T - 2]


def _last_row(block: nn.Module, h: Tensor) -> Tensor:
    """A transformer block (no bias) over h (B, T, D), its last row only -> (B, 1, D)."""
    B, T, D = h.shape
    attn, heads = block.attn, block.attn.heads
    n = block.norm1(h)
    w, b = attn.qkv.weight, attn.qkv.bias
    q = F.linear(n[:, -1:], w[:D], b[:D]).view(B, 1, heads, D // heads).transpose(1, 2)
    k, v = F.linear(n, w[D:], b[D:]).view(B, T, 2, heads, D // heads).permute(2, 0, 3, 1, 4)
    y = F.scaled_dot_product_attention(q, k, v)
    x = h[:, -1:] + attn.out(y.transpose(1, 2).reshape(B, 1, D))
    return x + block.mlp(block.norm2(x))


class AheadWindow:
    """The audio terms of :func:`fast_passes` for generation in chunks: ``load(t0, t1)`` computes
    them for frames t0..t1-1, called ``chunk`` frames ahead of the passes at a time; the frames
    before the current pass are dropped, so only about a chunk is held."""

    def __init__(self, load: Callable[[int, int], list[Tensor]], chunk: int, total: int) -> None:
        self.load, self.chunk, self.total = load, max(1, chunk), total
        self.start = self.end = 0  # frames held: start..end-1
        self.terms: list[Tensor] = []

    def __call__(self, t0: int, t1: int) -> list[Tensor]:
        assert self.start <= t0 <= self.end and t1 <= self.total, (t0, t1, self.start, self.end)
        if t1 > self.end:
            new = self.load(self.end, min(self.total, max(t1, self.end + self.chunk)))
            if self.terms:
                new = [
                    torch.cat([old[:, t0 - self.start :], n], 1) for old, n in zip(self.terms, new)
                ]
                self.start = t0
            self.terms, self.end = new, self.start + new[0].shape[1]
        return [t[:, t0 - self.start : t1 - self.start] for t in self.terms]


class FrameGenerator:
    """Stage 2 and the VQ decoder over the next frames with key/value caches (``generate``'s fast
    mode, and streaming): every frame costs the same, whatever the length.

    :meth:`step` runs one frame. :meth:`block` runs K frames in one pass from guesses of their
    codes and keeps those it got right (Jacobi decoding of the autoregressive loop): generating a
    frame reads all the weights for one small matrix-vector product per layer, so a pass over K
    frames costs little more than one, and a frame's codes depend mostly on its audio, so most
    guesses taken from the previous pass hold.

    With a causal VQ decoder (``vq.causal``) the motion of each frame is returned as well, exactly
    what a full pass would give. Otherwise the fed-back frame comes from a causal, cached pass
    through the bidirectional decoder (see :meth:`CodeTalker.generate`) and no motion is returned.
    """

    def __init__(self, model: nn.Module, style: Tensor, face: Tensor | None = None) -> None:
        """``model``: a CodeTalker; ``style`` (B, d) its style vector; ``face`` (B, hidden) its
        VQ decoder's head term (``CodeTalker.decoder_face``; None: none)."""
        s2, vq = model.cfg.stage2, model.cfg.vq
        self.model, self.style, self.face = model, style, face
        self.window = s2.attention_window
        self.caches = [KVCache(self.window) for _ in model.blocks]
        dec = model.vqvae.decoder
        self.causal = vq.causal
        self.vq_step = DecoderStep(dec, face) if vq.causal else None
        # the bidirectional decoder's cached causal pass (unused with a causal decoder)
        self.vq_caches = [] if vq.causal else [KVCache(self.window) for _ in dec.blocks]
        self.conv_inputs: Tensor | None = None  # (B, 2 + K, hidden) its conv's recent inputs
        # the VQ decoder's output map followed by the motion map is one linear map: fold them
        # (normalised motion in, so the decoder's scale cancels)
        self.fold = folded_linear(
            model, dec.out, model.motion_map, int8=getattr(model, "int8", False)
        )
        device = style.device
        self.ppe = model.ppe(s2.period, device)
        self.step_bias = window_bias(s2.heads, 1, self.window, self.window, s2.period, device)[None]
        self.x_in: Tensor | None = style[:, None]  # (B, 1, d) the next frame's input ...
        self.pending: Tensor | None = None  # ... or (B, H) codes of the last frame, not yet
        # through the VQ decoder (after ``block``)
        self.t = 0  # frames whose codes are final
        self.vq_t = 0  # frames through the VQ decoder

    def _stage2(self, x: Tensor, cross: list[Tensor]) -> Quantized:
        """x (B, K, d) fed-back inputs of frames t..t+K-1 -> their codes; the rows join the cache."""
        model, t = self.model, self.t
        s2, vq = model.cfg.stage2, model.cfg.vq
        B, K = x.shape[:2]
        x = x + self.ppe[torch.arange(t, t + K, device=x.device) % len(self.ppe)]
        if K == 1:
            bias = self.step_bias[..., self.window - min(t + 1, self.window) :]
        else:
            keys = min(t + K, self.window + K - 1)
            bias = window_bias(s2.heads, K, keys, self.window, s2.period, x.device)[None]
        feats = model.decode_features(x, cross, bias, self.caches)
        return model.vqvae.quantizer(feats.view(B, K, vq.components, vq.code_dim))

    def _vq_hidden(self, codes: Tensor) -> Tensor:
        """codes (B, K, H) of the next K frames -> (B, K, hidden), the VQ decoder's normalised
        hidden states before its output map; the rows join the caches."""
        dec, K = self.model.vqvae.decoder, codes.shape[1]
        z_q = self.model.vqvae.quantizer.lookup(codes)
        if self.vq_step is not None:
            h = self.vq_step.hidden(z_q)
        else:
            x = dec.inputs(z_q, self.face)
            past = x[:, :1].expand(-1, 2, -1) if self.conv_inputs is None else self.conv_inputs
            seq = self.conv_inputs = torch.cat([past[:, -2:], x], dim=1)
            # the kernel sees t-2..t+2; t+1 and t+2 are not decoded yet, so they repeat t
            now = seq[:, 2:]
            windows = torch.stack([seq[:, :K], seq[:, 1 : K + 1], now, now, now], dim=-1)
            pos = torch.arange(self.vq_t, self.vq_t + K, device=x.device)
            h = dec.mid(dec.conv.step(windows)) + sinusoid(pos, dec.cfg.hidden)
            bias = None
            if K > 1:
                keys = min(self.vq_t + K, self.window + K - 1)
                bias = window_bias(dec.cfg.heads, K, keys, self.window, None, x.device)[None]
            for block, cache in zip(dec.blocks, self.vq_caches):
                h = block(h, bias, cache)
            h = dec.norm(h)
        self.vq_t += K
        return h

    def _vq_drop(self, frames: int) -> None:
        if not frames:
            return
        if self.vq_step is not None:
            self.vq_step.drop(frames)
        else:
            for cache in self.vq_caches:
                cache.drop(frames)
            self.conv_inputs = self.conv_inputs[:, :-frames]
        self.vq_t -= frames
        if not self.vq_t:  # the conv's left padding repeats frame 0: gone with it
            self.conv_inputs = None

    def _motion(self, h: Tensor) -> Tensor | None:
        dec = self.model.vqvae.decoder
        return dec.out(h) * dec.scale if self.causal else None

    def step(self, cross: list[Tensor]) -> tuple[Tensor, Tensor | None]:
        """cross: per decoder layer the (B, 1, d) audio term of this frame -> codes (B, H) and,
        with a causal VQ decoder, motion (B, V*3)."""
        self.flush()
        codes = self.codes_step(cross)
        h = self._vq_hidden(codes[:, None])
        self.feed(h)
        motion = self._motion(h)
        return codes, None if motion is None else motion[:, 0]

    def codes_step(self, cross: list[Tensor]) -> Tensor:
        """Stage 2 alone over the next frame, from the input :meth:`feed` (or the start) left:
        cross as in :meth:`step` -> its codes (B, H). The VQ decoder is not run: the caller feeds
        the frame back with :meth:`feed`."""
        q = self._stage2(self.x_in, cross)
        self.t += 1
        return q.codes[:, 0]

    def feed(self, hidden: Tensor) -> None:
        """Make (B, 1, hidden) VQ decoder states (before its output map) the next frame's input."""
        self.x_in = self.fold(hidden) + self.style[:, None]

    def block(self, cross: list[Tensor], drafts: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
        """The next K frames in one pass; cross: per decoder layer their (B, K, d) audio terms;
        ``drafts`` (B, G, H), G < K, guess the codes of the first G of them.

        Each frame is computed from the guessed codes before it, so the frames up to the first
        wrong guess, and that one (its inputs were right), are exactly what K steps would give:
        they are kept, the rest are taken back out of the caches. A pass without any guesses
        guesses that the codes of the last kept frame hold still, so that every frame is fed
        motion that the VQ decoder made from real codes, as in the next pass (on random
        weights, codes computed from such motion hold there; from a repeated input they do
        not). Frames after the G + 1 that follow guesses are only drafts: they repeat the last
        input that a guess gave, so they cost no VQ decoder step, and their codes serve as
        guesses for the next pass. The last kept frame's codes wait for the next pass (or
        :meth:`flush`) to go through the VQ decoder.
        -> codes (B, A, H) of the A >= 1 frames kept; this pass's codes (B, K - A, H) for the
        frames after them (guesses for the next pass); with a causal VQ decoder the motion
        (B, M, V*3) of the frames that went through it for good, else None.
        """
        K = cross[0].shape[1]
        if drafts.shape[1] >= K:
            raise ValueError(f"{drafts.shape[1]} guesses for a pass of {K} frames: at most K - 1")
        if not drafts.shape[1] and self.pending is not None:
            drafts = self.pending[:, None].expand(-1, K - 1, -1)
        G = drafts.shape[1]
        rows = drafts if self.pending is None else torch.cat([self.pending[:, None], drafts], 1)
        x, h = self.x_in, None
        if rows.shape[1]:
            h = self._vq_hidden(rows)
            fed = self.fold(h) + self.style[:, None]
            x = fed if self.pending is not None else torch.cat([self.x_in, fed], dim=1)
        if K > G + 1:
            x = torch.cat([x, x[:, -1:].expand(-1, K - G - 1, -1)], dim=1)
        codes = self._stage2(x, cross).codes
        right = (codes[:, :G] == drafts).all(-1).all(0)
        A = 1 + int(right.long().cumprod(0).sum())
        for cache in self.caches:
            cache.drop(K - A)
        wrong = G + 1 - A  # VQ decoder rows from guesses that did not hold
        self._vq_drop(wrong)
        self.t += A
        self.pending, self.x_in = codes[:, A - 1], None
        exact = rows.shape[1] - wrong
        motion = self._motion(h[:, :exact]) if exact else None
        return codes[:, :A], codes[:, A:], motion

    def flush(self) -> Tensor | None:
        """Run the last frame's codes through the VQ decoder if :meth:`block` left them waiting
        -> with a causal VQ decoder their motion (B, 1, V*3), else None."""
        if self.pending is None:
            return None
        h = self._vq_hidden(self.pending[:, None])
        self.pending = None
        self.feed(h)
        return self._motion(h)


class CodeTalkerStream(FrameStream):
    """A CodeTalker with a causal VQ decoder one frame per step: the frame's speech feature from
    the stream's audio (:class:`MelFeatureStream`, or for the Whisper encoder
    :class:`~talkmesh.models.whisper_stream.WhisperFeatureStream`), then the model's
    step with key/value caches, exactly what ``generate`` computes. The streams of one model
    share its :class:`talkmesh.models.codetalker.batch.FrameBatch`, where each holds a slot, and
    compute their frames together (:meth:`frames_together`)."""

    def __init__(
        self,
        model: nn.Module,
        style: Tensor,
        features: MelFeatureStream | WhisperFeatureStream,
        face: Tensor | None = None,
    ) -> None:
        """``model``: a CodeTalker; ``style`` (1, d) its style vector; ``face`` (1, hidden) its VQ
        decoder's head term (``CodeTalker.decoder_face``; None: none)."""
        self.model, self.features = model, features
        self.fps, self.lookahead_ms = model.motion_fps, features.lookahead_ms
        self.engine = frame_batch(model)
        self.slot = self.engine.open(self, style[0], None if face is None else face[0])

    def audio_needed(self, frame: int) -> float:
        return self.features.audio_needed(frame)

    def first_sample(self, frame: int) -> int:
        return self.features.first_sample(frame)

    def frame(self, buffer: np.ndarray, buffer_start: int, frame: int) -> np.ndarray:
        return self.engine.step([FrameRequest(self, buffer, buffer_start, frame)])[0]

    def frames_together(
        self, requests: list[FrameRequest], basis: np.ndarray | None = None
    ) -> np.ndarray:
        return self.engine.step(requests, basis)


def generate_streamed(
    model: nn.Module,
    audio: np.ndarray,
    template: np.ndarray,
    lookahead_ms: float | None = None,
    style_weights: np.ndarray | None = None,
    **windows,
) -> np.ndarray:
    """(T, V, 3) vertices: what a stream of ``audio`` (S,) 16 kHz computes on ``template``
    (V, 3), offline, for a CodeTalker with the Whisper encoder and a causal VQ decoder
    (:mod:`talkmesh.models.whisper_stream`; ``windows``: its ``context_s`` and ``block``)."""
    T = model.default_frames(len(audio))
    style, face = model.stream_terms(style_weights, template)
    with torch.inference_mode():
        feats = streamed_features(model.speech, audio, T, model.motion_fps, lookahead_ms, **windows)
        cross = model.cross_terms(model._tokens(feats[None], T))
        _, motion = generate_fast(model, style, cross, T, None, face)
    return motion.view(T, -1, 3).numpy() + np.asarray(template, np.float32)
