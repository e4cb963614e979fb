"""Input signal generators."""

import numpy as np
import pytest

from greyid.simulate import multisine, prbs, steps


@pytest.mark.parametrize("order", range(2, 17))
def test_prbs_is_maximal_length(order):
    period = 2**order - 1
    x = prbs(order, levels=(-1.0, 1.0), length=2 * period)
    assert np.array_equal(x[:period], x[period:])
    seq = x[:period]
    # Two-valued circular autocorrelation: N at lag 0, −1 elsewhere.
    lags = range(1, period) if period < 2000 else np.random.default_rng(order).integers(1, period, 200)
    for k in lags:
        assert np.dot(seq, np.roll(seq, k)) == -1
    assert seq.sum() == 1  # one more "high" than "low" in a maximal sequence


def test_prbs_clock_and_levels():
    x = prbs(6, clock=24, levels=(0.0, 300.0))
    assert len(x) == 63 * 24 and set(np.unique(x)) == {0.0, 300.0}
    assert np.all(x.reshape(63, 24) == x.reshape(63, 24)[:, :1])
    with pytest.raises(ValueError, match="order"):
        prbs(1)


def test_steps_and_multisine():
    t = np.arange(10.0)
    np.testing.assert_array_equal(steps(t, [(3, 1.0), (7, -1.0)]), [0, 0, 0, 1, 1, 1, 1, -1, -1, -1])
    t = np.arange(1000) / 1000
    x = multisine(t, [5, 20, 50], power=[2, 1, 1], total_power=4.0)
    assert x.var() == pytest.approx(4.0, rel=1e-6)
    spec = np.abs(np.fft.rfft(x)) ** 2
    assert spec[5] / spec[20] == pytest.approx(2.0, rel=1e-6)
