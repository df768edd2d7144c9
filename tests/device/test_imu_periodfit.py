"""Lower-envelope period fit: rejects latency, learns a period 1 % off nominal, survives restarts."""

from __future__ import annotations

import numpy as np
import pytest

from stereopath.device.capture.imu.period_fit import PeriodFit


def observe(fit, true_period, t0, n_reads, rng, read_ms=20.0, latency_max_ns=300_000, start_index=0):
    """Reads at jittered times; each sees the newest sample produced before it, plus latency."""
    t = t0
    for _ in range(n_reads):
        t += int(read_ms * 1e6 + rng.uniform(0, 4e6))
        newest = int((t - t0) // true_period) - 1 + start_index
        if newest < start_index:
            continue
        fit.add(newest - start_index, t + int(rng.exponential(latency_max_ns / 3)))
    return t


def test_learns_the_true_period_and_offset():
    rng = np.random.default_rng(0)
    true_p = 1.01e6
    fit = PeriodFit(1.0e6)
    t0 = 10_000_000_000
    observe(fit, true_p, t0, 600, rng)
    assert fit.period_ns == pytest.approx(true_p, rel=1e-4)
    idx = np.arange(1000, 11000, 1000)
    truth = t0 + true_p * (idx + 1)      # sample i is produced at t0 + (i + 1) * period
    err = fit.times_ns(idx) - truth
    assert np.max(np.abs(err)) < 100_000           # 0.1 ms despite up to ms of read latency
    assert np.all(err >= -1)                       # the envelope stays at/above the truth (upper bounds)


def test_nominal_prior_until_the_span_is_long_enough():
    fit = PeriodFit(5e6, min_span=200)
    fit.add(0, 1_000_000_000)
    fit.add(3, 1_020_000_000)
    assert fit.period_ns == 5e6 and not fit.state().from_hull


def test_absurd_slopes_are_clamped_to_the_last_good_period():
    fit = PeriodFit(1e6, min_span=10)
    for i in range(0, 400, 20):
        fit.add(i, 1_000_000_000 + i * 2_000_000)   # a clock 100 % off: not believable
    assert fit.period_ns == 1e6


def test_restart_keeps_the_period_and_refits_the_offset():
    rng = np.random.default_rng(1)
    true_p = 0.99e6
    fit = PeriodFit(1.0e6)
    t_end = observe(fit, true_p, 5_000_000_000, 300, rng)
    learned = fit.period_ns
    fit.restart()
    t1 = t_end + 2_000_000_000
    observe(fit, true_p, t1, 5, rng)
    assert fit.period_ns == learned
    assert abs(int(fit.times_ns([50])[0]) - (t1 + true_p * 51)) < 1_500_000


def test_old_observations_leave_the_window():
    fit = PeriodFit(1e6, window_ns=2_000_000_000, min_span=50)
    for k in range(400):          # first 4 s at 1.00 ms, then 1.02 ms
        fit.add(k * 20, 1_000_000_000 + k * 20_000_000)
    t = 1_000_000_000 + 399 * 20_000_000
    for k in range(1, 400):
        fit.add(399 * 20 + k * 20, t + int(k * 20 * 1.02e6))
    assert fit.period_ns == pytest.approx(1.02e6, rel=1e-3)
