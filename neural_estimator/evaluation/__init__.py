"""The paper's evaluation protocol, in four modules:

- :mod:`~neural_estimator.evaluation.protocol`: methods x evaluation sets -> metrics per run
  (:func:`evaluate`), the recorded-data rules;
- :mod:`~neural_estimator.evaluation.starts`: how the classical filters start (``init``);
- :mod:`~neural_estimator.evaluation.cache`: the result cache and its keys;
- :mod:`~neural_estimator.evaluation.output`: the table, its marks, results.json and an output folder.

Their public names are importable from here. Imported on demand (not from here): a recorded run
scored from its bag (:mod:`~neural_estimator.evaluation.bag_report`, in bounded memory through
:mod:`~neural_estimator.evaluation.bag_scoring`) and a bag run through estimators
(:mod:`~neural_estimator.evaluation.replay`).
"""

from neural_estimator.evaluation.cache import (
    RESULTS_REVISION,
    checkpoint_digest,
    load_run,
    result_path,
    run_key,
    save_run,
)
from neural_estimator.evaluation.output import (
    RESULTS_SCHEMA,
    consistency_table,
    departure_legend,
    departure_marks,
    results_json,
    results_table,
    write_evaluation,
)
from neural_estimator.evaluation.protocol import (
    DEFAULT_MEMORY_BUDGET,
    MethodResult,
    chunk_size,
    evaluate,
    recorded_data_methods,
    recorded_result,
    run_method,
    run_stepwise,
    served_context,
)
from neural_estimator.evaluation.starts import INIT_MODES, check_init, effective_init

__all__ = [
    "DEFAULT_MEMORY_BUDGET",
    "INIT_MODES",
    "RESULTS_REVISION",
    "RESULTS_SCHEMA",
    "MethodResult",
    "check_init",
    "checkpoint_digest",
    "consistency_table",
    "chunk_size",
    "departure_legend",
    "departure_marks",
    "effective_init",
    "evaluate",
    "load_run",
    "recorded_data_methods",
    "recorded_result",
    "result_path",
    "results_json",
    "results_table",
    "run_key",
    "run_method",
    "run_stepwise",
    "save_run",
    "served_context",
    "write_evaluation",
]
