"""Streams of one model computed together: each gets the frames it computes alone."""

from __future__ import annotations

import gc

import numpy as np
import torch
from test_stream import SR

from talkmesh.models.base import FrameRequest, next_frames
from talkmesh.models.codetalker.batch import frame_batch, ring_bias
from talkmesh.models.layers import window_bias
from talkmesh.models.release import load_model

FRAMES = 40


def streams_alone(path, setups, audio):
    """Each stream on a model of its own, frame by frame."""
    out = []
    for weights, lookahead, _ in setups:
        stream = load_model(path).eval().open_frame_stream(weights, lookahead)
        out.append(np.stack([stream.frame(audio, 0, t) for t in range(FRAMES)]))
    return out


def test_streams_computed_together_equal_each_stream_alone(tmp_path, tiny_stream_model):
    path = tiny_stream_model()
    audio = np.random.default_rng(2).normal(0, 0.1, 2 * SR).astype(np.float32)
    # style weights, look-ahead, the step at which the stream joins
    setups = [
        (np.array([1.0, 0.0], np.float32), 0.0, 0),
        (np.array([0.2, 0.8], np.float32), 100.0, 9),
        (None, 200.0, 23),
    ]
    alone = streams_alone(path, setups, audio)
    net = load_model(path).eval()
    # a stream that ends early: the slot it frees is reused by the last one
    early = net.open_frame_stream(None, 50.0)
    streams: list = [None] * len(setups)
    together = [[] for _ in setups]
    sizes = []
    for step in range(2 * FRAMES):
        if step == 20:
            early = None
            gc.collect()
        for k, (weights, lookahead, start) in enumerate(setups):
            if step == start:
                streams[k] = net.open_frame_stream(weights, lookahead)
        requests = [
            FrameRequest(s, audio, 0, len(together[k]))
            for k, s in enumerate(streams)
            if s is not None and len(together[k]) < FRAMES and (step + k) % 5  # some skip a step
        ]
        if step < 20:
            requests.append(FrameRequest(early, audio, 0, step))
        sizes.append(len(requests))
        for r, motion in zip(requests, next_frames(requests)):
            if r.stream in streams:
                together[streams.index(r.stream)].append(motion)
    assert max(sizes) == 3 and len(frame_batch(net)) == 3
    for k in range(len(setups)):
        assert len(together[k]) == FRAMES
        np.testing.assert_allclose(np.stack(together[k]), alone[k], atol=1e-5)
    # the streams differ from each other: equal frames are not an accident of the test
    assert np.abs(alone[0] - alone[1]).max() > 1e-3


def test_ring_bias_is_the_step_bias_of_the_rows_in_their_frames():
    heads, W, period = 2, 5, 2
    full = window_bias(heads, 1, W, W, period)[:, 0]  # (heads, W): the last column is distance 0
    t = torch.tensor([0, 3, 4, 12])
    bias = ring_bias(full.flip(-1), t)[:, :, 0]
    for b, now in enumerate(t.tolist()):
        for j in range(W):
            frame = now - (now - j) % W
            want = float("-inf") if frame < 0 else full[:, W - 1 - (now - frame)]
            torch.testing.assert_close(bias[b, :, j], torch.as_tensor(want).expand(heads))
