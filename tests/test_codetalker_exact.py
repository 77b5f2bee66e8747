"""Exact generation's fed-back frame (codetalker.generate.PrefixFeedback): what the
bidirectional VQ decoder's full pass over each prefix gives, computed incrementally."""

from __future__ import annotations

import pytest
import torch

from talkmesh.models.codetalker.generate import PrefixFeedback
from talkmesh.models.codetalker.vq import MotionDecoder, VQConfig


def _decoder(**options) -> MotionDecoder:
    torch.manual_seed(0)
    cfg = VQConfig(
        num_vertices=10,
        hidden=32,
        layers=2,
        heads=2,
        ff=48,
        components=4,
        code_dim=8,
        codebook_size=16,
        **options,
    )
    return MotionDecoder(cfg).eval()


@pytest.mark.parametrize(
    "options",
    [
        dict(instance_norm=True, gelu_tanh=True, final_norm=False, frame_positions=False),
        dict(instance_norm=False, frame_positions=True),
    ],
)
def test_prefix_feedback_equals_the_full_pass(options):
    dec = _decoder(**options)
    z_q = torch.randn(2, 14, 4, 8)
    feedback = PrefixFeedback(dec)
    assert feedback.usable
    with torch.inference_mode():
        for t in range(1, 15):
            want = dec.hidden(z_q[:, :t])[:, -1:]
            got = feedback(z_q[:, :t], 0)
            torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
        assert feedback.fixed is not None  # the incremental path ran
        # a prefix that does not grow by one frame (a new sequence) starts over
        torch.testing.assert_close(feedback(z_q[:, :9], 0), dec.hidden(z_q[:, :9])[:, -1:])
        # the window sliding: the full pass
        torch.testing.assert_close(
            feedback(z_q[:, 3:12], 3), dec.hidden(z_q[:, 3:12], offset=3)[:, -1:]
        )


def test_exact_generation_is_unchanged(tiny_codetalker):
    """generate(mode="exact") against the naive loop on an InstanceNorm decoder."""
    from dataclasses import replace

    from talkmesh.models.codetalker.model import CodeTalker

    net = tiny_codetalker()
    cfg = replace(net.cfg, vq=replace(net.cfg.vq, instance_norm=True))
    torch.manual_seed(1)
    model = CodeTalker(cfg).eval()
    for p in model.feat_map.parameters():
        torch.nn.init.normal_(p, std=0.5)
    audio, template = torch.randn(1, 16000) * 0.1, torch.zeros(1, model.num_vertices, 3)
    style = torch.tensor([0])
    exact = model.generate(audio, template, styles=style, mode="exact")
    naive = model.generate(audio, template, styles=style, mode="naive")
    assert exact.shape[1] >= 10
    torch.testing.assert_close(exact, naive, atol=1e-5, rtol=1e-5)
