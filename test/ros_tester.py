"""The tester node the ROS tests drive a node under test with: a node of its own in a fresh context
on the test's domain, discovery kept to this machine, its executor, and ``spin_until``."""

from __future__ import annotations

import time
from collections.abc import Callable


class Tester:
    """``node`` and ``executor`` in their own context; :meth:`shutdown` in the test's ``finally``."""

    def __init__(self, monkeypatch, domain: int, log: Callable[[], str] = lambda: "", timeout: float = 60.0) -> None:
        import rclpy  # imported here: a test module importing this still collects where rclpy is missing
        from rclpy.executors import SingleThreadedExecutor

        monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        try:
            self.node = rclpy.create_node("tester", context=self.context)
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
        except BaseException:
            self.shutdown()
            raise
        self.log, self.timeout = log, timeout

    def spin_until(self, pred: Callable[[], bool], timeout: float | None = None) -> None:
        """Spin until ``pred()``; after ``timeout`` seconds (the tester's by default) an AssertionError
        with the nodes' log."""
        timeout = self.timeout if timeout is None else timeout
        t0 = time.monotonic()
        while not pred():
            if time.monotonic() - t0 > timeout:
                raise AssertionError(f"timed out; {self.log()}")
            self.executor.spin_once(timeout_sec=0.05)

    def shutdown(self) -> None:
        import rclpy

        rclpy.try_shutdown(context=self.context)


TEST_DOMAINS = (200, 232)  # the launcher's own default is 100..199: a test never meets a demo
_used_domains: set[int] = set()


def fresh_domain() -> int:
    """A ROS domain for one test: at random from ``NEURAL_ESTIMATOR_DOMAINS`` (``LO-HI``: confine a
    run of the suite to a share of a host's domains) or else 200..232, not one this process used
    before while the range has others left."""
    import random

    from neural_estimator.nodes.launch import domain_range

    lo, hi = domain_range(TEST_DOMAINS)
    free = [d for d in range(lo, hi + 1) if d not in _used_domains] or list(range(lo, hi + 1))
    d = random.SystemRandom().choice(free)
    _used_domains.add(d)
    return d
