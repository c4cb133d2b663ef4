"""The table of methods: one frozen :class:`MethodSpec` per method, the one place a method is named.

Every question the package asks about methods ("which are classical?", "does this one take a start
mode?", "can its context be bounded by restarted copies?", "how many members does a stream hold?",
"in which row of the paper's tables?") is a query of this table (:func:`names`, :func:`spec`,
:func:`methods`), never a literal list of names; ``test/test_method_table.py`` counts the literal
collections of method names left in the package so that none comes back.

The table sits at layer 4, below the filters, the models and serving (layers 5-6) that implement the
methods. It names each method's factory *lazily*, as ``"module:attribute"`` text (the way Python
entry points name an object), resolved with :mod:`importlib` by :func:`resolve` only when a method
is built (:func:`neural_estimator.methods.registry.make_estimator`); the table itself imports
nothing above it. Registering a method is one more entry in :data:`TABLE` (see "Adding a method" in
docs/architecture.md); a test registers a toy one in a temporary table.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

from neural_estimator.core.options import did_you_mean

FAMILIES = ("classical", "neural", "hybrid", "baseline")  # a hybrid: the system's f and h with a learned part
ESTIMATOR_FAMILIES = ("classical", "neural", "hybrid")  # the methods compared; baselines are reference rows
CONTEXTS = ("recurrent", "window", "none")


@dataclass(frozen=True)
class MethodSpec:
    """One method: its names, where its factory is, its family and what it can do."""

    name: str  # the id on the command line, in params files, cards and result files (lower case)
    display: str  # the name in tables and figures (the paper's spelling for its ten)
    family: str  # one of FAMILIES
    factory: str  # "module:attribute" of what builds it, resolved when it is built (see the registry)
    needs_model: bool  # uses the scenario's f and h (so not on recorded data without a model)
    trainable: bool  # served from a trained checkpoint (the zoo ships one per scenario)
    takes_init: bool  # takes a start mode (init: prior or observation)
    uses_torch: bool  # builds and runs with torch (torch threads apply)
    seeded: bool  # its estimates depend on the seed (random draws)
    context: str = "none"  # how its context is bounded: recurrent (restarted copies), window (attention), none
    window_key: str | None = None  # context "window": the model's hyperparameter holding the window W
    state_space: bool = False  # a selective state-space model (the paper's "SSM" findings)
    exportable: bool = False  # its step exports to ONNX (models/onnx_step.py)
    members: tuple[str, str] | None = None  # (option, "module:Class.field" of its default): members a stream holds
    architecture: tuple[str, str] | None = None  # ("module:Config", "module:Model") of a network (models/)
    training_run: str | None = None  # "module:Class" of its training run where not the networks' windows
    paper_row: int | None = None  # its row in the paper's tables (None: not one of the paper's methods)

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            raise ValueError(f"{self.name}: family {self.family!r} is not one of {', '.join(FAMILIES)}")
        if self.context not in CONTEXTS:
            raise ValueError(f"{self.name}: context {self.context!r} is not one of {', '.join(CONTEXTS)}")
        if (self.context == "window") != (self.window_key is not None):
            raise ValueError(f"{self.name}: a window_key exactly when the context is a window")
        if ":" not in self.factory:
            raise ValueError(f"{self.name}: factory {self.factory!r} is not 'module:attribute'")


def _classical(name: str, display: str, cls: str, row: int, *, seeded: bool = False, members=None) -> MethodSpec:
    return MethodSpec(
        name,
        display,
        "classical",
        f"neural_estimator.filters.{name}:{cls}",
        needs_model=True,
        trainable=False,
        takes_init=True,
        uses_torch=False,
        seeded=seeded,
        members=members,
        paper_row=row,
    )


def _neural(
    name: str, display: str, cls: str, row: int, context: str, window_key=None, state_space=False
) -> MethodSpec:
    return MethodSpec(
        name,
        display,
        "neural",
        "neural_estimator.serving.load:load_neural_estimator",
        needs_model=False,
        trainable=True,
        takes_init=False,
        uses_torch=True,
        seeded=False,
        context=context,
        window_key=window_key,
        state_space=state_space,
        exportable=True,
        architecture=(f"neural_estimator.models.{name}:{cls}Config", f"neural_estimator.models.{name}:{cls}Model"),
        paper_row=row,
    )


def _hybrid(name: str, display: str, cls: str) -> MethodSpec:
    """A model-aided network: the scenario's f and h (needs_model) with a trained part, served by the
    networks' factory from a checkpoint; its model class takes the scenario (models.build_model)."""
    return MethodSpec(
        name,
        display,
        "hybrid",
        "neural_estimator.serving.load:load_neural_estimator",
        needs_model=True,
        trainable=True,
        takes_init=False,
        uses_torch=True,
        seeded=False,
        context="recurrent",
        exportable=True,
        architecture=(f"neural_estimator.models.{name}:{cls}Config", f"neural_estimator.models.{name}:{cls}Model"),
        training_run="neural_estimator.training.hybrid:HybridRun",  # whole trajectories from its prior (TBPTT)
    )


def _baseline(name: str, cls: str) -> MethodSpec:
    return MethodSpec(
        name,
        name,
        "baseline",
        f"neural_estimator.filters.baselines:{cls}",
        needs_model=True,
        trainable=False,
        takes_init=False,
        uses_torch=False,
        seeded=False,
    )


# The methods, in the paper's row order (then the reference rows). Read it through the queries
# below: a test swaps this tuple for one with a toy method in it.
TABLE: tuple[MethodSpec, ...] = (
    _classical("ekf", "EKF", "ExtendedKalmanFilter", 0),
    _classical("ukf", "UKF", "UnscentedKalmanFilter", 1),
    _classical(
        "enkf",
        "EnKF",
        "EnsembleKalmanFilter",
        2,
        seeded=True,
        members=("n_members", "neural_estimator.filters.enkf:EnKFHyperParams.n_members"),
    ),  # fmt: skip
    _classical(
        "pf",
        "PF",
        "ParticleFilter",
        3,
        seeded=True,
        members=("n_particles", "neural_estimator.filters.pf:PFHyperParams.n_particles"),
    ),  # fmt: skip
    _neural("gru", "GRU", "GRU", 4, "recurrent"),
    _neural("lstm", "LSTM", "LSTM", 5, "recurrent"),
    _neural("gpt2", "GPT-2", "GPT2", 6, "window", window_key="decode_chunk"),
    _neural("filterformer", "Filterformer", "Filterformer", 7, "window", window_key="window"),
    _neural("mamba", "Mamba", "Mamba", 8, "recurrent", state_space=True),
    _neural("mamba2", "Mamba-2", "Mamba2", 9, "recurrent", state_space=True),
    _hybrid("kalmannet", "KalmanNet", "KalmanNet"),  # not a paper row: its f and h with a learned gain
    _baseline("openloop", "OpenLoop"),
    _baseline("obsonly", "ObservationOnly"),
)


def methods(
    *, family: str | tuple[str, ...] | None = ESTIMATOR_FAMILIES, **capabilities: Any
) -> tuple[MethodSpec, ...]:
    """The specs of ``family`` (one name, a tuple of them, or None for all; default: the methods
    compared, baselines left out) whose fields equal ``capabilities`` (e.g. ``takes_init=True``,
    ``context="recurrent"``), in table order."""
    fams = FAMILIES if family is None else (family,) if isinstance(family, str) else tuple(family)
    for k in capabilities:
        if k not in MethodSpec.__dataclass_fields__:
            raise TypeError(f"MethodSpec has no field {k!r}")
    return tuple(s for s in TABLE if s.family in fams and all(getattr(s, k) == v for k, v in capabilities.items()))


def names(*, family: str | tuple[str, ...] | None = ESTIMATOR_FAMILIES, **capabilities: Any) -> tuple[str, ...]:
    """The names of :func:`methods` (same arguments): ``names()`` is every method compared,
    ``names(family="classical")`` the filters, ``names(context="recurrent")`` ..."""
    return tuple(s.name for s in methods(family=family, **capabilities))


def find(name: str) -> MethodSpec | None:
    """The spec of ``name`` (any family, exact id), None if the table has none."""
    return next((s for s in TABLE if s.name == name), None)


def spec(name: str) -> MethodSpec:
    """The spec of ``name`` (any family); a KeyError naming the valid ones otherwise."""
    s = find(name)
    if s is None:
        valid = names(family=None)
        raise KeyError(f"unknown method {name!r}{did_you_mean(name, valid)}; choose one of: {', '.join(valid)}")
    return s


def has(name: str, **capabilities: Any) -> bool:
    """``name`` is in the table (any family when ``family`` is not given) with these field values:
    ``has(m, family="classical")``, ``has(m, takes_init=True)``."""
    s = find(name)
    return s is not None and all(getattr(s, k) == v for k, v in capabilities.items())


def paper_names() -> dict[str, str]:
    """{name: display} of the paper's methods, in the paper's row order."""
    rows = sorted((s for s in TABLE if s.paper_row is not None), key=lambda s: s.paper_row)
    return {s.name: s.display for s in rows}


def paper_methods(**capabilities: Any) -> tuple[str, ...]:
    """The paper's methods with these field values, in its row order: ``paper_methods(family="neural")``,
    ``paper_methods(state_space=True)`` (its SSMs)."""
    return tuple(m for m in paper_names() if has(m, **capabilities))


def labels(*, family: str | tuple[str, ...] | None = ESTIMATOR_FAMILIES, **capabilities: Any) -> tuple[str, ...]:
    """The display names of :func:`methods` (same arguments)."""
    return tuple(s.display for s in methods(family=family, **capabilities))


def label(name: str) -> str:
    """The display name of ``name`` (the name itself when the table has none)."""
    s = find(name)
    return s.display if s is not None else name


def resolve(ref: str) -> Any:
    """The object ``"package.module:attribute[.attribute]"`` names (imported now, not before)."""
    module, _, attr = ref.partition(":")
    obj: Any = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def members_per_stream(name: str, options: dict[str, Any] | None, parse: Any) -> int | None:
    """The members a stream of ``name`` holds (the EnKF's members, the PF's particles): its option in
    ``options`` read by ``parse(value, minimum, option)``, else its default; None for a method with
    no members."""
    s = find(name)
    if s is None or s.members is None:
        return None
    option, default = s.members
    return parse((options or {}).get(option, resolve(default)), 1, option)


def main(argv: list[str] | None = None) -> int:
    """``python -m neural_estimator.methods.table [FAMILY ...]``: the names of the methods compared
    (or of those families), comma-separated, in table order; scripts/run_demo.sh's default methods."""
    import sys

    args = sys.argv[1:] if argv is None else argv
    print(",".join(names(family=tuple(args)) if args else names()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
