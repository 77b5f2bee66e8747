"""The lip-gap loss (talkmesh.training.lip_gap): which pairs it finds, what it measures."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from talkmesh.errors import TalkmeshError
from talkmesh.training.lip_gap import (
    CodeChoice,
    LipGap,
    code_cross_entropy,
    lip_gap_loss,
    lip_gap_pairs,
    optional_terms,
    rest_frames,
    shut_frames,
)
from talkmesh.training.trainer import StepOutput, TrainConfig

XS = np.arange(5) * 2.0  # five columns 2 apart: the region is 8 wide, candidates 0.64 apart


def _mouth(opening: float) -> np.ndarray:
    """Three rows of five vertices: the outer upper lip, the inner upper lip 0.5 below it, the
    lower lip 0.5 below that; the lower lip drops by ``opening``."""
    rows = [(0.75, 0.0), (0.25, 0.0), (-0.25, -opening)]
    return np.array([[x, y + drop, 0.0] for y, drop in rows for x in XS], np.float32)


def _dataset(openings: list[list[float]]):
    template = _mouth(0.0)
    clips = [
        SimpleNamespace(template=template, vertices=np.stack([_mouth(o) for o in clip]))
        for clip in openings
    ]
    return clips


def test_pairs_are_the_lips_facing_each_other_across_the_mouth():
    data = _dataset([[0.0, 0.3, 0.1], [0.5, 0.0, 0.2]])
    pairs = lip_gap_pairs(data, np.arange(15))
    # the inner upper lip (5..9) over the lower lip (10..14), column by column; the outer and
    # inner upper lip move together, so their pairs do not count
    assert sorted(map(tuple, np.sort(pairs, axis=1))) == [(5 + k, 10 + k) for k in range(5)]


def test_pairs_need_the_lip_region():
    with pytest.raises(TalkmeshError, match="lip region"):
        lip_gap_pairs(_dataset([[0.0, 0.2]]), None)


def test_the_loss_is_the_gap_error_in_per_cent_of_the_lip_width():
    template = torch.from_numpy(_mouth(0.0))[None]
    truth = torch.from_numpy(np.stack([_mouth(0.0), _mouth(0.5)]))[None]  # (1, 2, V, 3)
    pairs = torch.tensor([[7, 12]])
    exact = (truth - template[:, None]).flatten(2)
    assert float(lip_gap_loss(exact, truth, template, pairs, 8.0)) == 0.0
    moved = exact.view(1, 2, 15, 3) + torch.tensor([0.3, -0.2, 0.1])  # the whole face shifted
    assert float(lip_gap_loss(moved.flatten(2), truth, template, pairs, 8.0)) == pytest.approx(0)
    # the lips left shut in the second frame: 0.5 of an 8-wide region = 6.25 %, in one frame of 2
    shut = torch.zeros_like(exact)
    got = float(lip_gap_loss(shut, truth, template, pairs, 8.0))
    assert got == pytest.approx(6.25**2 / 2)
    only_first = torch.tensor([[True, False]])
    assert float(lip_gap_loss(shut, truth, template, pairs, 8.0, only_first)) == 0.0


def test_the_term_adds_to_the_task_loss_and_needs_predicted_motion():
    template = torch.from_numpy(_mouth(0.0))[None]
    truth = torch.from_numpy(np.stack([_mouth(0.0), _mouth(0.5)]))[None]
    batch = SimpleNamespace(vertices=truth, templates=template, motion_mask=None)
    term = LipGap(np.array([[7, 12]]), 8.0, weight=0.1)
    out = StepOutput(torch.tensor(1.0), {"motion": 1.0}, torch.zeros(1, 2, 45))
    loss, logs = term.add(out.loss, out.logs, out, batch, "codetalker-stage2")
    assert float(loss) == pytest.approx(1.0 + 0.1 * 6.25**2 / 2)
    assert logs["lip_gap"] == pytest.approx(6.25**2 / 2) and logs["motion"] == 1.0
    with pytest.raises(TalkmeshError, match="no lip-gap loss"):
        term.add(torch.tensor(1.0), {}, StepOutput(torch.tensor(1.0), {}), batch, "meshtalk-prior")


def test_the_truths_shut_frames_weigh_more():
    template = torch.from_numpy(_mouth(0.0))[None]  # the lips rest 0.5 apart
    # the lower lip up to the upper (shut), then dropped 0.5
    truth = torch.from_numpy(np.stack([_mouth(-0.5), _mouth(0.5)]))[None]
    pairs = torch.tensor([[7, 12], [5, 10]])
    assert shut_frames(truth, pairs, 8.0).tolist() == [[True, False]]
    assert shut_frames(template[:, None], pairs, 8.0).tolist() == [[False]]  # at rest: open
    rest = torch.zeros(1, 2, 45)  # the lips left at rest: 0.5 off in both frames (6.25 %)
    plain = float(lip_gap_loss(rest, truth, template, pairs, 8.0))
    assert plain == pytest.approx(6.25**2)
    weighted = float(lip_gap_loss(rest, truth, template, pairs, 8.0, close_weight=3.0))
    assert weighted == pytest.approx((4 * 6.25**2 + 6.25**2) / 2)
    # only the pairs that part the most decide what is shut: here none of them closes
    far = torch.tensor([[2, 7]])  # outer over inner upper lip: 0.5 apart in every frame
    kept = lip_gap_loss(rest, truth, template, pairs, 8.0, close_weight=3.0, shut_pairs=far)
    assert float(kept) == pytest.approx(plain)


def test_a_recipe_term_finds_its_shut_pairs_in_the_data(capsys):
    data = _dataset([[0.0, -0.5, 0.3], [0.5, 0.0, 0.2]])
    regions = SimpleNamespace(lve=np.arange(15))
    term = LipGap.from_data(data, regions, 0.1, close_weight=2.0)
    assert term.close_weight == 2.0 and len(term.shut_pairs) == 5
    assert "shut frames (16.7% of them) weigh 3" in capsys.readouterr().out


def test_the_truths_frames_at_rest_weigh_more():
    template = torch.from_numpy(_mouth(0.0))[None]  # the lips rest 0.5 apart
    # at rest, a hair off rest (0.005: 0.06 % of the 8-wide region), shut, dropped 0.5
    openings = (0.0, 0.005, -0.5, 0.5)
    truth = torch.from_numpy(np.stack([_mouth(o) for o in openings]))[None]
    pairs = torch.tensor([[7, 12], [5, 10]])
    assert rest_frames(truth, template, pairs, 8.0).tolist() == [[True, True, False, False]]
    # 0.01 off rest (0.125 %) is speech, not rest
    assert not rest_frames(torch.from_numpy(_mouth(0.01))[None, None], template, pairs, 8.0)
    moved = torch.from_numpy(np.stack([_mouth(0.25)] * 4) - _mouth(0.0)).reshape(1, 4, 45)
    # the prediction's lower lip 0.25 down in every frame: off by 0.25 at rest, 0.75 shut, ...
    errors = [(abs(0.25 - o) * 100 / 8) ** 2 for o in openings]
    plain = float(lip_gap_loss(moved, truth, template, pairs, 8.0))
    assert plain == pytest.approx(np.mean(errors), rel=1e-4)
    weighted = float(lip_gap_loss(moved, truth, template, pairs, 8.0, rest_weight=2.0))
    assert weighted == pytest.approx(np.mean([3, 3, 1, 1] * np.array(errors)), rel=1e-4)
    both = float(
        lip_gap_loss(moved, truth, template, pairs, 8.0, close_weight=1.0, rest_weight=2.0)
    )
    assert both == pytest.approx(np.mean([3, 3, 2, 1] * np.array(errors)), rel=1e-4)


def test_a_recipe_term_finds_the_truths_frames_at_rest(capsys):
    data = _dataset([[0.0, -0.5, 0.3], [0.5, 0.0, 0.2]])
    term = LipGap.from_data(data, SimpleNamespace(lve=np.arange(15)), 0.1, rest_weight=4.0)
    assert term.rest_weight == 4.0 and term.shut_pairs is None
    assert "frames at rest (33.3%) weigh 5" in capsys.readouterr().out


@pytest.mark.parametrize("name", ["lip_close_weight", "lip_rest_weight"])
def test_the_close_and_rest_weights_need_the_lip_gap_loss(name):
    train = TrainConfig(**{name: 2.0})
    with pytest.raises(TalkmeshError, match=f"{name}.*lip_gap_weight"):
        optional_terms(train, [], SimpleNamespace(regions=None))
    with pytest.raises(ValueError, match=name):
        TrainConfig(lip_gap_weight=0.1, **{name: -1.0})


def test_a_negative_weight_is_refused():
    with pytest.raises(ValueError, match="lip_gap_weight"):
        TrainConfig(lip_gap_weight=-1.0)
    with pytest.raises(ValueError, match="code_ce_weight"):
        TrainConfig(code_ce_weight=-0.5)


def test_code_choice_rewards_the_nearest_true_code_and_needs_codes():
    codebook = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    codes = torch.tensor([[[1]]])  # (B, T, H)
    on_it = torch.tensor([[[[1.0, 0.0]]]])
    between = torch.tensor([[[[0.5, 0.0]]]])  # as near code 0 as code 1: the average's code
    assert float(code_cross_entropy(on_it, codes, codebook)) < float(
        code_cross_entropy(between, codes, codebook)
    )
    # the softmax cross-entropy of the negative squared distances, in units of the squared
    # distance between neighbouring codes (1 here)
    logits = -torch.tensor([1.0, 0.0, 2.0])
    assert float(code_cross_entropy(on_it * 3, codes, codebook * 3)) == pytest.approx(
        float(code_cross_entropy(on_it, codes, codebook))
    )
    want = float(-torch.log_softmax(logits, 0)[1])
    assert float(code_cross_entropy(on_it, codes, codebook)) == pytest.approx(want)
    term = CodeChoice(0.5)
    out = StepOutput(torch.tensor(2.0), {}, None, (on_it, codes, codebook))
    batch = SimpleNamespace(motion_mask=None)
    loss, logs = term.add(out.loss, out.logs, out, batch, "codetalker-finetune")
    assert float(loss) == pytest.approx(2.0 + 0.5 * want) and logs["code_ce"] == pytest.approx(want)
    with pytest.raises(TalkmeshError, match="queries no codebook"):
        term.add(out.loss, {}, StepOutput(torch.tensor(1.0), {}), batch, "voca")
