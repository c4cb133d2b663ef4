"""The ``neural-estimator`` command line: a thin front end over the library.

Verbs (``neural-estimator VERB --help`` for each):
    simulate   write a dataset (.npz) of a scenario
    metrics    the paper's table from a truth file and an estimate file (or one file, or an MCAP bag)
    evaluate   run methods on the three evaluation sets and print the paper's per-scenario table
    train      train a neural estimator with the paper's protocol
    live       a live ROS 2 run (simulator, estimators, evaluator) ending with the table and an MCAP bag
    replay     run an MCAP bag's observations through estimators offline
    recover    rewrite a damaged or unfinished bag into a valid .mcap
    scenarios  list the registered scenarios and their constants
    reproduce  the paper's experiments on Ray, with a report beside the paper's numbers
    dataset    recorded bags of a robot -> a dataset (.npz), through a spec of message fields
    ros2       the minimal ``ros2 run`` / ``ros2 pkg executables`` of pip environments

``train`` and ``evaluate`` take ``--data FILE.npz`` (a recorded dataset) instead of ``--scenario``.

Every command accepts ``--plugin FILE`` (repeatable) to import a Python file that registers user
scenarios. Errors in the input print one line naming the problem and exit with status 2.

One module per verb group: :mod:`~neural_estimator.cli.data` (simulate, scenarios, dataset),
:mod:`~neural_estimator.cli.evaluate` (metrics, evaluate), :mod:`~neural_estimator.cli.train`,
:mod:`~neural_estimator.cli.streams` (live, replay, recover), :mod:`~neural_estimator.cli.reproduce`;
the flags they share in :mod:`~neural_estimator.cli.common`, the parser and :func:`main` in
:mod:`~neural_estimator.cli.app`.
"""

from neural_estimator.cli.app import build_parser, main

__all__ = ["build_parser", "main"]
