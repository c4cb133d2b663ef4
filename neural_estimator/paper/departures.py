"""Marks of the departures from the paper's protocol, printed where the number is printed.

A table cell that does not rest on the paper's protocol carries a short mark, and every table
that shows a mark is followed by a legend that explains each mark it used, once:

====  ===============================================================================================
mark  meaning
====  ===============================================================================================
[c]   bounded context: a neural model validated, and served, with every estimate seeing at most N
      steps of input (its card's ``training.recipe.val_context``, or the ``context`` option); the
      paper runs every model continuously over the whole horizon.
[o]   the outlier rule decides the figure: trajectories were dropped (log-MSE robust z-score > 6)
      and the RMSE over the kept ones differs from the Full RMSE over all of them by more than
      :data:`OUTLIER_TOLERANCE`; the Full RMSE is printed beside it.
[t]   a classical filter started at each trajectory's true x_0 (``--init truth``): a start no live
      filter has; the paper's tables start from the prior.
[y]   a classical filter started from the first observation (``--init observation``): the live
      pipeline's practical start, not the paper's prior.
(!)   expected to fail here under the paper's start (:mod:`neural_estimator.paper.expected_failures`).
====  ===============================================================================================

The scored steps are a choice of this project, named in every heading: the protocol scores steps
10.. of each trajectory (:data:`~neural_estimator.metrics.EVALUATION_WARMUP`), where the paper
states its 10-step warm-up for the training loss only; ``--every-step`` scores every step.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

from neural_estimator.methods import table
from neural_estimator.paper.expected_failures import MARK as EXPECTED_MARK
from neural_estimator.metrics import EVALUATION_WARMUP

BOUNDED = "[c]"
OUTLIERS = "[o]"
FROM_TRUTH = "[t]"
FROM_OBSERVATION = "[y]"
OUTLIER_TOLERANCE = 0.01  # [o] when |Full RMSE - RMSE| > 1 % of the RMSE (or the Full RMSE is inf)

LEGEND = {
    BOUNDED: "bounded context: the model was validated, and is served, with every estimate seeing at most "
    "{context} steps of input (its card's training.recipe.val_context); the paper runs every model "
    "continuously over the whole horizon",
    OUTLIERS: "the outlier rule decides this figure: trajectories were dropped (log-MSE robust z-score > 6) and "
    "the RMSE over the kept ones differs from the Full RMSE over all of them by more than "
    f"{100 * OUTLIER_TOLERANCE:g} % (the Full RMSE is beside it)",
    FROM_TRUTH: "filter started at each trajectory's true x0 (--init truth), a start no live filter has; "
    "the paper's tables start from the prior",
    FROM_OBSERVATION: "filter started from the first observation where h is invertible (--init observation), "
    "the live pipeline's practical start; the paper's tables start from the prior",
    EXPECTED_MARK: "expected to fail here under the filters' start (the reason is given below the table)",
}
ORDER = (BOUNDED, OUTLIERS, FROM_TRUTH, FROM_OBSERVATION, EXPECTED_MARK)


def start_mark(method: str, init: str) -> str | None:
    """[t] or [y] for a method that takes a start mode (the classical filters; neural models read y only)
    started from the truth or the first observation; else None."""
    if not table.has(method, takes_init=True):
        return None
    return {"truth": FROM_TRUTH, "observation": FROM_OBSERVATION}.get(init)


def context_mark(context: int | None) -> str | None:
    """[c] for a bounded context (> 0), else None."""
    return BOUNDED if context else None


def rests_on_outliers(rmse: float | None, full_rmse: float | None) -> bool:
    """True when the RMSE (outliers dropped) and the Full RMSE differ by more than the tolerance."""
    if rmse is None or full_rmse is None or math.isnan(rmse) or math.isnan(full_rmse):
        return False
    if math.isinf(full_rmse) or math.isinf(rmse):
        return full_rmse != rmse
    return abs(full_rmse - rmse) > OUTLIER_TOLERANCE * max(abs(rmse), 1e-300)


def row_marks(method: str, *, context: int | None = 0, init: str = "prior") -> list[str]:
    """The marks a whole row of ``method`` carries: [c] and/or [t] / [y]."""
    return [m for m in (context_mark(context), start_mark(method, init)) if m]


def legend(used: Iterable[str], contexts: Iterable[int] = ()) -> list[str]:
    """One line per mark in ``used`` (each once, in :data:`ORDER`); ``contexts``: the bounded contexts
    shown, named in the [c] line."""
    used = set(used)
    ctx = sorted({int(c) for c in contexts if c})
    lines = []
    for mark in ORDER:
        if mark in used:
            lines.append(f"{mark} " + LEGEND[mark].format(context=" / ".join(map(str, ctx)) or "N"))
    return lines


def legend_text(used: Iterable[str], contexts: Iterable[int] = ()) -> list[str]:
    """:func:`legend` for a terminal: a "Marks:" line, then one indented line per mark (nothing when
    no mark is used). Indented, so no line starts with "[" (the launcher drops such lines as ROS logs)."""
    lines = legend(used, contexts)
    return ["Marks:"] + [f"  {line}" for line in lines] if lines else []


def scored_steps(warmup: int, every_step_flag: str = "--every-step") -> str:
    """The sentence naming the scored steps as this project's choice."""
    if not warmup:
        return "Every step scored."
    return (
        f"Scored steps: {warmup}.. of every trajectory, this project's choice (the paper states its "
        f"{EVALUATION_WARMUP}-step warm-up for the training loss only); {every_step_flag} scores every step."
    )


def marked_names(names: Iterable[str], marks: Mapping[str, Iterable[str]]) -> dict[str, str]:
    """{name: "name [c] [y]"}: each row name followed by its marks."""
    return {n: " ".join([n, *marks.get(n, ())]) for n in names}
