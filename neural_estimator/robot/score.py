"""Score a recorded live run of recorded-data estimators against the spec's ground truth.

The evaluator node records the robot's topics and every ``estimates/<method>`` stream (JointState,
the spec's state names, stamped by the robot estimator with the tick it answers, on the inputs'
clock: :mod:`~neural_estimator.robot.ticker`). Scoring reads that bag through the spec: the state
from the spec's ground-truth fields, each estimate stream mapped onto the state by ``position[i]``
(angle components wrapped), all sampled at the spec's ticks by the spec's own ``stamp`` rule
(header stamps, or log times for ``stamp: log``), cut into trajectories of ``length`` steps, and
the paper's metrics computed per method: the dataset builder's sampling, so a live run scores the
trajectories ``neural-estimator evaluate`` scored on the recording's dataset. Where the ground
truth has gaps, those ticks are unlabelled and not scored (:mod:`neural_estimator.metrics.labelled`),
as in the dataset.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from neural_estimator import metrics as M
from neural_estimator.bags import open_bag
from neural_estimator.robot.dataset import build_dataset
from neural_estimator.robot.spec import Spec, SpecError, load_spec

ESTIMATES_PREFIX = "estimates/"


def scoring_spec(
    spec: Spec, topics: list[str], namespace: str = "/", stamp: str | None = None
) -> tuple[Spec, dict[str, str]]:
    """A spec that reads the ground truth of ``spec`` and every estimate topic among ``topics``,
    sampled by the spec's stamp rule (``stamp`` None) or by ``"header"`` stamps or ``"log"`` times.

    Returns the spec and {method: topic}.
    """
    ns = namespace.rstrip("/")
    methods = {}
    for t in topics:
        rel = t[len(ns) + 1 :] if ns and t.startswith(ns + "/") else t.lstrip("/")
        parts = rel.split("/")
        if len(parts) == 2 and parts[0] + "/" == ESTIMATES_PREFIX:
            methods[parts[1]] = t
    if not methods:
        raise SpecError(
            f"no {ESTIMATES_PREFIX}<method> stream recorded (topics: {', '.join(sorted(topics)) or 'none'})"
        )
    if not spec.has_state:
        raise SpecError("the spec reads no ground truth (a model and no state:): nothing to score against")
    state = {}
    for f in spec.vectors["state"]:
        state.setdefault(f.topic, []).append(f.expr)
    angles = set(spec.angles("state"))
    n = len(spec.vectors["state"])
    fields = [f"angle(position[{i}])" if i in angles else f"position[{i}]" for i in range(n)]
    raw = {
        "rate": spec.rate,
        "max_age": spec.max_age,
        "stamp": stamp or spec.stamp,
        # unused by the scoring, but the builder wants one: an estimate stream, not the truth, so that
        # a truth gap leaves its ticks unlabelled (not scored) instead of cutting the trajectories
        "observation": {methods[min(methods)]: fields[:1]},
        "state": state,
        "estimates": {m: {topic: fields} for m, topic in methods.items()},
        "names": {"state": list(spec.names["state"])},
        "units": {"state": list(spec.units["state"])},
    }
    return load_spec(raw), methods


def score_recording(
    bag: str | Path,
    spec: Spec | str | Path,
    length: int = 200,
    namespace: str = "/",
    warmup: int = M.EVALUATION_WARMUP,
    length_name: str = "--length",
    stamp: str | None = None,
) -> tuple[dict[str, Any], Any]:
    """({method: MetricReport}, the truth Trajectories) of every estimate stream of a recorded run,
    against the spec's ground truth; the first ``warmup`` steps of every trajectory are not scored.
    ``length_name`` is how the caller's user sets ``length`` (a CLI flag, a node parameter), for the
    error when no trajectory that long can be cut. ``stamp``: None (the spec's rule), "header" or "log"."""
    spec = spec if isinstance(spec, Spec) else load_spec(spec)
    with open_bag(bag) as reader:
        topics = list(reader.topics)
    scoring, _ = scoring_spec(spec, topics, namespace, stamp)
    truth, estimates, _ = build_dataset([bag], scoring, length, length_name=length_name)
    angles = scoring.angles("state")
    return {
        m: M.compute_labelled_metrics(truth.x, x_hat, angles, truth.labelled, warmup=warmup)
        for m, x_hat in estimates.items()
    }, truth
