"""The paper apart from the built-ins: its five scenarios, its published numbers
(:mod:`~neural_estimator.paper.results`), the marks of departures from its protocol
(:mod:`~neural_estimator.paper.departures`), its expected failures
(:mod:`~neural_estimator.paper.expected_failures`) and, a layer higher, its experiments on Ray
(:mod:`~neural_estimator.paper.reproduce`).

A module of this package imports from :mod:`neural_estimator.paper.results`, never from this
``__init__`` (test/test_structure.py)."""

from neural_estimator.paper.results import PAPER_SCENARIOS, RESULTS_FILE, paper_results, paper_value

__all__ = ["PAPER_SCENARIOS", "RESULTS_FILE", "paper_results", "paper_value"]
