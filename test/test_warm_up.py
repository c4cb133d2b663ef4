"""The estimator node's warm-up: every compiled path is built before the first observation."""

from __future__ import annotations

import numpy as np

from neural_estimator.stream.online import WARM_UP_STEPS, warm_up
from neural_estimator.scenarios import make_scenario


class CountingEstimator:
    """Records the calls warm_up makes, in order."""

    def __init__(self, fail_at_step: int | None = None) -> None:
        self.calls: list[tuple[str, object]] = []
        self.fail_at_step = fail_at_step

    def reset(self, batch: int) -> None:
        self.calls.append(("reset", batch))

    def step(self, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        steps = sum(1 for c in self.calls if c[0] == "step")
        if self.fail_at_step is not None and steps == self.fail_at_step:
            raise ValueError("zeros are not a valid observation here")
        self.calls.append(("step", (y.shape, u.shape)))
        return np.zeros((1, 1))


def test_warm_up_takes_more_than_one_step_and_leaves_the_estimator_reset():
    # the first step from the prior and the later ones take different paths: one step leaves the
    # second path to be built on the second observation (the EKF's 19 ms, measured)
    sc = make_scenario("lorenz96")
    est = CountingEstimator()
    warm_up(est, sc)
    steps = [c for c in est.calls if c[0] == "step"]
    assert WARM_UP_STEPS >= 2 and len(steps) == WARM_UP_STEPS
    assert steps[0][1] == ((1, sc.dy), (1, sc.du))
    assert est.calls[0] == ("reset", 1) and est.calls[-1] == ("reset", 1)


def test_a_warm_up_that_fails_still_leaves_the_estimator_reset():
    est = CountingEstimator(fail_at_step=1)
    warm_up(est, make_scenario("lorenz96"))
    assert est.calls[-1] == ("reset", 1)


def test_a_real_filter_after_warm_up_estimates_as_a_fresh_one():
    sc = make_scenario("lorenz96")
    from neural_estimator.methods.registry import make_estimator

    warmed, fresh = make_estimator("ekf", sc, seed=0), make_estimator("ekf", sc, seed=0)
    warm_up(warmed, sc)
    fresh.reset(1)
    y = np.random.default_rng(0).normal(size=(5, 1, sc.dy))
    u = np.zeros((1, sc.du))
    for t in range(5):
        np.testing.assert_array_equal(warmed.step(y[t], u), fresh.step(y[t], u))
