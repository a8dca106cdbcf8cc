"""Continual-learning metrics, checked on small matrices worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drago.eval.metrics import (
    continual_metrics,
    cw_average_performance,
    cw_forgetting,
    cw_forward_transfer,
    gem_acc,
    gem_bwt,
    gem_fwt,
)

R3 = [[0.9, 0.1, 0.0], [0.5, 0.8, 0.2], [0.3, 0.6, 0.7]]


def test_three_task_matrix_by_hand():
    assert gem_acc(R3) == pytest.approx((0.3 + 0.6 + 0.7) / 3)
    assert cw_average_performance(R3) == pytest.approx((0.3 + 0.6 + 0.7) / 3)
    assert gem_bwt(R3) == pytest.approx(((0.3 - 0.9) + (0.6 - 0.8)) / 2)  # -0.4
    assert cw_forgetting(R3) == pytest.approx(0.4)
    assert gem_fwt(R3, [0.0, 0.1, 0.1]) == pytest.approx(((0.1 - 0.1) + (0.2 - 0.1)) / 2)  # 0.05


def test_two_task_matrix_by_hand():
    R = [[0.6, 0.3], [0.2, 1.0]]
    assert gem_acc(R) == pytest.approx(0.6)
    assert gem_bwt(R) == pytest.approx(-0.4)
    assert cw_forgetting(R) == pytest.approx(0.4)
    assert gem_fwt(R, [0.5, 0.1]) == pytest.approx(0.2)


def test_no_forgetting_and_positive_backward_transfer():
    kept = [[1.0, 0.0], [1.0, 1.0]]
    assert gem_bwt(kept) == 0.0
    assert cw_forgetting(kept) == 0.0
    improved = [[0.5, 0.0], [0.75, 1.0]]
    assert gem_bwt(improved) == pytest.approx(0.25)
    assert cw_forgetting(improved) == pytest.approx(-0.25)


def test_extra_task_columns_are_ignored():
    # Two stages of a four-task sequence: only the two learned tasks are measured.
    R = [[0.9, 0.1, 0.0, 0.0], [0.5, 0.8, 0.3, 0.3]]
    assert gem_acc(R) == pytest.approx((0.5 + 0.8) / 2)
    assert gem_bwt(R) == pytest.approx(-0.4)
    assert gem_fwt(R, [0.0, 0.0, 0.0, 0.0]) == pytest.approx(0.1)


def test_continual_metrics_gathers_everything():
    m = continual_metrics(R3, random_baseline=[0.0, 0.1, 0.1])
    assert m == pytest.approx(
        {"acc": 1.6 / 3, "bwt": -0.4, "fwt": 0.05, "average_performance": 1.6 / 3, "forgetting": 0.4}
    )
    assert "fwt" not in continual_metrics(R3)


def test_continual_metrics_of_a_single_stage():
    m = continual_metrics([[0.8, 0.1]], random_baseline=[0.0, 0.0])
    assert m["acc"] == pytest.approx(0.8)
    assert m["average_performance"] == pytest.approx(0.8)
    assert math.isnan(m["bwt"]) and math.isnan(m["forgetting"]) and math.isnan(m["fwt"])
    with pytest.raises(ValueError):
        gem_bwt([[0.8, 0.1]])


def test_forward_transfer_of_curves():
    ref = [0.0, 0.25, 0.5, 0.75, 1.0]
    assert cw_forward_transfer(ref, ref) == 0.0
    assert cw_forward_transfer([1.0] * 5, ref) == pytest.approx(1.0)
    # Trapezoid on [0, 1]: curve [0, 1, 1] has area 0.75; the reference [0, 0, 1] has 0.25;
    # FT = (0.75 - 0.25) / (1 - 0.25) = 2/3.
    assert cw_forward_transfer([0.0, 1.0, 1.0], [0.0, 0.0, 1.0]) == pytest.approx(2.0 / 3.0)
    # Slower than the reference: negative transfer, (0.25 - 0.75) / (1 - 0.75) = -2.
    assert cw_forward_transfer([0.0, 0.0, 1.0], [0.0, 1.0, 1.0]) == pytest.approx(-2.0)


def test_forward_transfer_on_another_scale():
    # Returns out of 10: areas 7.5 and 2.5, FT = (7.5 - 2.5) / (10 - 2.5) = 2/3.
    assert cw_forward_transfer([0, 10, 10], [0, 0, 10], max_performance=10.0) == pytest.approx(2.0 / 3.0)


def test_forward_transfer_errors():
    with pytest.raises(ValueError, match="undefined"):
        cw_forward_transfer([1.0, 1.0], [1.0, 1.0])
    with pytest.raises(ValueError, match="same grid"):
        cw_forward_transfer([0.0, 1.0, 1.0], [0.0, 1.0])
    with pytest.raises(ValueError):
        cw_forward_transfer([0.5], [0.2])
    with pytest.raises(ValueError):
        cw_forward_transfer([0.0, np.nan], [0.0, 0.5])


@pytest.mark.parametrize(
    "bad",
    [
        [0.1, 0.2, 0.3],  # 1-D
        [[0.9, 0.1], [0.5, 0.8], [0.3, 0.6]],  # more stages than tasks
        [[0.9, np.nan], [0.5, 0.8]],  # missing evaluation
        np.zeros((0, 3)),  # no stages
    ],
)
def test_bad_matrices_raise(bad):
    with pytest.raises(ValueError):
        continual_metrics(bad)


def test_bad_baseline_raises():
    with pytest.raises(ValueError, match="random_baseline"):
        gem_fwt(R3, [0.0, 0.1])
    with pytest.raises(ValueError, match="random_baseline"):
        continual_metrics([[0.8, 0.1]], random_baseline=[0.0])
    with pytest.raises(ValueError, match="random_baseline"):
        gem_fwt(R3, [0.0, np.nan, 0.1])
