"""experiments/sure_summary.py: the reliability table and the ECE a calibrated confidence would show."""

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "experiments"))
import run_all  # noqa: E402

ss = run_all.load("sure_summary")


def test_the_reliability_table_and_ece_by_hand():
    """Four answers in two bins: 0.95 and 0.93 (one right) and 0.15 twice (one right)."""
    table, ece = ss.binned(np.array([0.95, 0.93, 0.15, 0.15]), np.array([1.0, 0.0, 1.0, 0.0]))
    assert [(lo, n) for lo, n, _, _ in table] == [(pytest.approx(0.1), 2), (pytest.approx(0.9), 2)]
    assert ece == pytest.approx(0.5 * abs(0.15 - 0.5) + 0.5 * abs(0.94 - 0.5))


@pytest.mark.parametrize("n", [10, 40])
def test_the_calibrated_ece_of_one_bin_is_the_binomial_mean_deviation(n):
    """n answers at confidence 0.55, each right with that probability: one bin, whose ECE is
    |K/n - 0.55|, K ~ Binomial(n, 0.55): its mean by the exact sum over K."""
    k = np.arange(n + 1)
    exact = float(np.sum(stats.binom.pmf(k, n, 0.55) * np.abs(k / n - 0.55)))
    mean, q95 = ss.calibrated_ece(np.full(n, 0.55), np.random.default_rng(1), draws=4000)
    assert mean == pytest.approx(exact, abs=0.006)
    assert q95 > mean


def test_a_confidence_that_is_wrong_lies_outside_the_calibrated_band():
    """Answers that say 0.9 and are right half the time: ECE 0.4, far above the calibrated 95 %."""
    conf = np.full(200, 0.9)
    right = (np.arange(200) % 2).astype(float)
    assert ss.binned(conf, right)[1] == pytest.approx(0.4)
    assert ss.calibrated_ece(conf, np.random.default_rng(2))[1] < 0.1


def test_every_placement_is_paired_with_its_own_outcome():
    """Two rows' space-separated columns give each placement's probability and strictness, in order;
    a row without them adds nothing."""
    rows = [{"placement_probability": "0.7 0.3", "placement_right": "1 0"},
            {"placement_probability": "1", "placement_right": "0"}, {"confidence": "0.5"}]
    p, y = ss.placement_outcomes(rows)
    assert p.tolist() == [0.7, 0.3, 1.0] and y.tolist() == [1.0, 0.0, 0.0]
    assert [len(a) for a in ss.placement_outcomes(rows[2:])] == [0, 0]
