"""Metrics against values worked out by hand on tiny arrays."""

from __future__ import annotations

import numpy as np
import pytest

from talkmesh.evaluation.metrics import (
    correlation,
    dynamics,
    lip_max_error,
    meshtalk_lip_error,
    motion_statistics,
    pool,
    score_sequence,
)

LIPS = np.array([0, 1])
UPPER = np.array([2, 3])


def seq(frames: list[list[float]]) -> np.ndarray:
    """(T, 4) x-offsets of four vertices -> (T, 4, 3) positions on the x axis."""
    out = np.zeros((len(frames), 4, 3))
    out[:, :, 0] = frames
    return out


def test_lve_anchor_is_pooled_max_squared_error():
    gt = seq([[0, 0, 0, 0], [0, 0, 0, 0]])
    pred = seq([[1, 2, 0, 0], [3, 0, 0, 0]])  # frame maxima of squared errors: 4, 9
    assert lip_max_error(pred, gt, LIPS, squared=True).tolist() == [4, 9]
    assert lip_max_error(pred, gt, LIPS, squared=False).tolist() == [2, 3]
    # Pooling: frames of all sequences, not the mean of sequence means.
    a = score_sequence(pred, gt, gt[0], LIPS, UPPER, "codetalker")  # frames 4, 9
    b = score_sequence(
        seq([[1, 0, 0, 0]]), seq([[0, 0, 0, 0]]), gt[0], LIPS, UPPER, "codetalker"
    )  # 1
    pooled = pool([a, b], "codetalker")
    assert pooled.lve == pytest.approx(
        (4 + 9 + 1) / 3
    )  # 4.667, where mean of means is (6.5+1)/2=3.75
    assert pooled.n_frames == 3 and pooled.n_sequences == 2
    physical = pool(
        [
            score_sequence(pred, gt, gt[0], LIPS, UPPER, "physical"),
            score_sequence(
                seq([[1, 0, 0, 0]]), seq([[0, 0, 0, 0]]), gt[0], LIPS, UPPER, "physical"
            ),
        ],
        "physical",
    )
    assert physical.lve == pytest.approx((2 + 3 + 1) / 3)


def test_fdd_anchor_is_signed_mean_of_std_of_squared_motion():
    template = np.zeros((4, 3))
    gt = seq([[0, 0, 0, 0], [0, 0, 2, 2]])  # upper e_v(t) = [0, 4] for both vertices: std 2
    pred = seq([[0, 0, 0, 0], [0, 0, 1, 1]])  # e_v(t) = [0, 1]: std 0.5
    assert dynamics(gt, template, UPPER, squared=True) == pytest.approx(2.0)
    assert dynamics(pred, template, UPPER, squared=True) == pytest.approx(0.5)
    s = score_sequence(pred, gt, template, LIPS, UPPER, "codetalker")
    assert s.row.fdd == pytest.approx(1.5)
    swapped = score_sequence(gt, pred, template, LIPS, UPPER, "codetalker")
    assert swapped.row.fdd == pytest.approx(-1.5)  # signed
    # physical: distances (std of [0, 2] is 1, of [0, 1] is 0.5), absolute difference
    assert score_sequence(gt, pred, template, LIPS, UPPER, "physical").row.fdd == pytest.approx(0.5)
    both = pool([s, swapped], "codetalker")
    assert both.fdd == pytest.approx(0.0)  # signed values cancel, as in the anchors


def test_mve_and_identical_inputs():
    gt = seq([[0, 0, 0, 0], [1, 1, 1, 1]])
    pred = seq([[3, 0, 0, 1], [1, 1, 1, 1]])  # frame errors: mean(3,0,0,1)=1 and 0
    s = score_sequence(pred, gt, np.zeros((4, 3)), LIPS, UPPER, "codetalker")
    assert s.row.mve == pytest.approx(0.5)
    same = pool(
        [score_sequence(gt, gt, np.zeros((4, 3)), LIPS, UPPER, p) for p in ("codetalker",)],
        "codetalker",
    )
    assert same.lve == 0 and same.fdd == 0 and same.mve == 0


def test_length_mismatch_truncates_and_is_counted():
    gt = seq([[0, 0, 0, 0]] * 5)
    pred = seq([[1, 0, 0, 0]] * 3)
    s = score_sequence(pred, gt, np.zeros((4, 3)), LIPS, UPPER, "physical")
    assert s.row.frames == 3 and s.row.truncated == 2


def test_meshtalk_lip_error_ignores_translation():
    gt = seq([[0, 1, 0, 0]])
    pred = gt + 5.0  # everything shifted: centred lips agree
    assert meshtalk_lip_error(pred, gt, LIPS) == pytest.approx(0.0)
    pred2 = seq([[0, 3, 0, 0]])  # lips centred: gt (-0.5, 0.5), pred (-1.5, 1.5): errors 1, 1
    assert meshtalk_lip_error(pred2, gt, LIPS) == pytest.approx(1.0)


def test_lip_sync_correlation():
    t = np.linspace(0, 1, 20)
    assert correlation(np.sin(6 * t), 3 * np.sin(6 * t) + 1) == pytest.approx(1.0)
    assert correlation(np.sin(6 * t), -np.sin(6 * t)) == pytest.approx(-1.0)
    assert np.isnan(correlation(np.ones(20), np.sin(6 * t)))
    gt = np.zeros((20, 4, 3))
    gt[:, 1, 1] = 1 + np.sin(6 * t)  # vertex 1 above vertex 0 by a moving gap
    pred = gt.copy()
    pred[:, 1, 1] = 1 + 0.5 * np.sin(6 * t)
    s = score_sequence(
        pred, gt, np.zeros((4, 3)), LIPS, UPPER, "codetalker", lip_pairs=np.array([1, 0])
    )
    assert s.row.lip_sync == pytest.approx(1.0)


def test_motion_statistics_by_hand():
    a = seq([[0, 0, 0, 0], [1, 0, 0, 0], [1, 0, 0, 0]])  # vertex 0 steps 1, 0
    b = seq([[0, 0, 0, 0], [0, 0, 0, 0], [3, 0, 0, 0]])  # vertex 0 steps 0, 3
    mean, std = motion_statistics([a, b])
    assert mean[0] == pytest.approx(1.0) and std[0] == pytest.approx(np.std([1, 0, 0, 3]))
    assert mean[1] == 0 and std[1] == 0
