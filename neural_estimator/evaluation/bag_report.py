"""The paper's metrics of a recorded run, computed offline from its bag.

The evaluator node calls this once the run is over; ``neural-estimator metrics run.mcap`` scores the
same way. Both score in memory that does not grow with the recording's length
(:func:`~neural_estimator.evaluation.bag_scoring.score_bag`).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from neural_estimator.paper import departures as D
from neural_estimator import metrics as M
from neural_estimator.bags.dataset import left_out_note
from neural_estimator.paper.expected_failures import mark_rows, notes


@dataclasses.dataclass
class BagReport:
    """Metrics of every estimate stream of one bag (one run: median and IQR are over one value)."""

    path: Path
    scenario: str
    n_trajectories: int
    horizon: int
    dt: float
    reports: dict[str, M.MetricReport]
    bag: dict[str, Any]  # received / missing / duplicates / rejected / left_out / complete
    warmup: int = 0  # leading steps of every trajectory not scored
    note: str = ""  # why the warm-up differs from the one asked for (a run too short for it)
    starts: dict[str, str] = dataclasses.field(default_factory=dict)  # {method: "prior" | "observation"}; absent: prior
    decision: dict[str, str] = dataclasses.field(default_factory=dict)  # {fmt: per-component table}, see evaluate_bag

    def table(self, fmt: str = "text", marked: bool = False) -> str:
        """The paper's table, one row per method ("markdown", "text" or "csv").

        One run has no spread: the IQR is given as NaN, so cells show the value alone. ``marked``:
        rows and cells that depart from the paper's protocol carry their marks (:meth:`marks`).
        """
        if not marked or fmt == "csv":
            return M.format_reports(self.reports, fmt=fmt)
        rows, cells, _ = self.marks()
        named = D.marked_names(self.reports, rows)
        return M.format_reports(
            {named[m]: r for m, r in self.reports.items()}, fmt=fmt, marks={named[m]: c for m, c in cells.items()}
        )

    def marks(self) -> tuple[dict[str, list[str]], dict[str, dict[str, str]], set[str]]:
        """(row marks, cell marks, marks used): [y] / [t] on filters not started from the prior,
        [o] on an RMSE the outlier rule decides (:mod:`neural_estimator.paper.departures`)."""
        rows = {m: D.row_marks(m, init=self.starts.get(m, "prior")) for m in self.reports}
        rows = {m: v for m, v in rows.items() if v}
        cells = {m: {"rmse": D.OUTLIERS} for m, r in self.reports.items() if D.rests_on_outliers(r.rmse, r.full_rmse)}
        used = {x for v in rows.values() for x in v} | ({D.OUTLIERS} if cells else set())
        return rows, cells, used

    def to_json(self) -> dict[str, Any]:
        return M.to_json(
            {
                "bag": str(self.path),
                "scenario": self.scenario,
                "trajectories": self.n_trajectories,
                "horizon": self.horizon,
                "warmup": self.warmup,
                "streams": self.bag,
                "methods": self.reports,
            }
        )

    def heading(self) -> str:
        scored = f" (steps {self.warmup}.. scored)" if self.warmup else ""
        return f"{self.scenario}: {self.n_trajectories} trajectories x {self.horizon} steps{scored}"

    def losses(self, expected: int | None = None, dropped: dict[str, dict[str, int]] | None = None) -> str:
        """What each stream lost and why (see :func:`loss_lines`); ``expected``: the messages the run
        announced per stream, ``dropped``: {stream: {reason: count}} the recorder did not write."""
        head = f"messages per stream (of {expected} announced)" if expected else "messages per stream"
        return head + ":\n" + "".join(f"  {line}\n" for line in loss_lines(self.bag, dropped))

    def consistency(self, fmt: str = "text") -> str:
        """The consistency table of the streams that carried a covariance (:mod:`neural_estimator.metrics.consistency`),
        or "" when none did."""
        from neural_estimator.metrics import consistency as C

        rows = {
            m: C.consistency_row(
                dict(r.scalars(), nees_median_all=r.nees_median_all),
                len(r.spread),
                r.coverage_curve,
                r.coverage_curve_all,
            )
            for m, r in self.reports.items()
            if r.has_covariance
        }
        return C.format_consistency_table(rows, fmt=fmt) if rows else ""

    def summary(self) -> str:
        """A heading line, the text table and the consistency table (streams with a covariance)."""
        note = "; ".join(n for n in (left_out_note(self.bag), self.note) if n)
        extra = f"; {note}" if note else ""
        lines = notes(self.scenario, sorted(self.reports), self.starts)
        _, _, used = self.marks()
        lines += D.legend_text(used) + [D.scored_steps(self.warmup, "--every-step (evaluator: warmup:=0)")]
        return (
            f"{self.heading()} from {self.path.name}{extra}\n"
            + mark_rows(self.table("text", marked=True), self.scenario, self.starts)
            + "".join(line + "\n" for line in lines)
            + (
                f"per component (own units) and against the best filter:\n{self.decision['text']}"
                if self.decision
                else ""
            )
            + self.consistency("text")
        )


def loss_lines(bag: dict[str, Any], dropped: dict[str, dict[str, int]] | None = None) -> list[str]:
    """One line per stream: (trajectory, step) cells without a message, and the messages that were
    not used and why (malformed, outside the announced run, duplicates, dropped by the recorder)."""
    dropped = dropped or {}
    missing = bag.get("missing") or {}
    lines = []
    for key in sorted(set(missing) | set(dropped)):
        unused = [
            (bag.get("rejected", {}).get(key, 0), "malformed"),
            (bag.get("outside", {}).get(key, 0), "outside the announced run"),
            (bag.get("duplicates", {}).get(key, 0), "duplicates"),
            *((n, why) for why, n in dropped.get(key, {}).items()),
        ]
        why = ", ".join(f"{n} {what}" for n, what in unused if n)
        lines.append(
            f"{key}: {bag.get('received', {}).get(key, 0)} received, {missing.get(key, 0)} lost"
            + (f"; not used: {why}" if why else "")
        )
    return lines


def evaluate_bag(
    path: str | Path,
    *,
    namespace: str = "/",
    description: dict[str, Any] | None = None,
    warmup: int = M.EVALUATION_WARMUP,
    short_runs: str = "error",
    starts: dict[str, str] | None = None,
) -> BagReport:
    """Metrics of each ``estimates/<method>`` stream against ``ground_truth`` (NEES where the
    method published covariances). Trajectories missing a message in any stream are left out for
    every method, so that all methods are scored on the same trajectories.

    ``warmup``: leading steps of every trajectory not scored (the protocol's 10 by default). A run
    with no more steps than that raises :class:`~neural_estimator.metrics.MetricsError` when
    ``short_runs`` is "error"; with "score_all" (the evaluator node, which must not lose a short
    run's table) every step is scored and the report says so in its heading.

    ``starts``: {method: "prior" | "observation" | "truth"}, how the recorded filters started (the
    launcher knows it; a bag does not record it); absent methods started from the prior.
    """
    if short_runs not in ("error", "score_all"):
        raise ValueError(f"short_runs must be 'error' or 'score_all', got {short_runs!r}")
    from neural_estimator.evaluation.bag_scoring import score_bag
    from neural_estimator.evaluation.decision import estimates_decision

    run = score_bag(path, namespace=namespace, description=description, warmup=warmup, short_runs=short_runs)
    decision = {
        f: estimates_decision(run, None, (), run.reports, run.warmup, f, errors=run.errors)
        for f in ("text", "markdown")
    }
    return BagReport(
        path=Path(path),
        scenario=str(run.meta.get("scenario", "?")),
        n_trajectories=run.n,
        horizon=run.horizon,
        dt=float(run.meta.get("dt", 1.0)),
        reports=run.reports,
        bag=run.meta["bag"],
        warmup=run.warmup,
        note=run.note,
        starts=dict(starts or {}),
        decision={f: t for f, t in decision.items() if t},
    )


STARTS_METADATA = "neural_estimator.starts"  # MCAP metadata record: {method: start mode} of the recorded filters


def recorded_starts(path: str | Path) -> dict[str, str]:
    """{method: "prior" | "observation" | "truth"} the evaluator recorded in a bag (empty when none)."""
    from neural_estimator.bags.directory import open_bag

    with open_bag(path) as reader:
        record = dict(getattr(reader, "metadata", {}).get(STARTS_METADATA) or {})
    return {m: v for m, v in record.items() if v in ("prior", "observation", "truth")}


def write_report(report: BagReport, prefix: str | Path | None = None) -> dict[str, Path]:
    """Write ``<prefix>.metrics.md``, ``.metrics.json`` and ``.rmse.png`` (default: beside the bag)."""
    from neural_estimator.metrics.plots import plot_rmse_over_time

    base = Path(prefix) if prefix is not None else report.path.with_suffix("")
    base.parent.mkdir(parents=True, exist_ok=True)
    paths = {
        "markdown": base.with_name(base.name + ".metrics.md"),
        "json": base.with_name(base.name + ".metrics.json"),
        "png": base.with_name(base.name + ".rmse.png"),
    }
    heading = f"# {report.heading()} ({report.path.name})\n\n"
    _, _, used = report.marks()
    legend = "".join(f"- {line}\n" for line in D.legend(used))
    steps = D.scored_steps(report.warmup, "--every-step (evaluator: warmup:=0)")
    paths["markdown"].write_text(
        heading
        + report.table("markdown", marked=True)
        + (f"\n{legend}" if legend else "")
        + f"\n{steps}\n"
        + (f"\n{report.decision['markdown']}" if report.decision else "")
        + (f"\n{report.consistency('markdown')}" if report.consistency() else "")
    )
    paths["json"].write_text(json.dumps(report.to_json(), indent=1))
    if report.reports:
        plot_rmse_over_time(
            {m: [r.rmse_t] for m, r in report.reports.items()},
            paths["png"],
            title=f"{report.scenario} ({report.path.name})",
            dt=report.dt,
            first_step=report.warmup,
        )
    else:
        paths.pop("png")
    return paths
