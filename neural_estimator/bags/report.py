"""The paper's metrics of a recorded run, computed offline from its bag.

The evaluator node calls this once the run is over; ``neural-estimator metrics run.mcap`` reads the
same inputs through :func:`~neural_estimator.bags.dataset.load_bag_dataset`.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from neural_estimator import metrics as metrics_mod
from neural_estimator.bags.dataset import left_out_note, load_bag_dataset
from neural_estimator.expected_failures import mark_rows, notes


@dataclasses.dataclass
class BagReport:
    """Metrics of every estimate stream of one bag (one run: median and IQR are over one value)."""

    path: Path
    scenario: str
    n_trajectories: int
    horizon: int
    dt: float
    reports: dict[str, metrics_mod.MetricReport]
    bag: dict[str, Any]  # received / missing / duplicates / rejected / left_out / complete

    def table(self, fmt: str = "text") -> str:
        """The paper's table, one row per method ("markdown", "text" or "csv").

        One run has no spread: the IQR is given as NaN, so cells show the value alone.
        """
        return metrics_mod.format_reports(self.reports, fmt=fmt)

    def to_json(self) -> dict[str, Any]:
        return metrics_mod.to_json(
            {
                "bag": str(self.path),
                "scenario": self.scenario,
                "trajectories": self.n_trajectories,
                "horizon": self.horizon,
                "streams": self.bag,
                "methods": self.reports,
            }
        )

    def summary(self) -> str:
        """A heading line and the text table."""
        note = left_out_note(self.bag)
        extra = f"; {note}" if note else ""
        lines = notes(self.scenario, sorted(self.reports))
        return (
            f"{self.scenario}: {self.n_trajectories} trajectories x {self.horizon} steps from {self.path.name}{extra}\n"
            + mark_rows(self.table("text"), self.scenario)
            + "".join(line + "\n" for line in lines)
        )


def evaluate_bag(path: str | Path, *, namespace: str = "/", description: dict[str, Any] | None = None) -> BagReport:
    """Metrics of each ``estimates/<method>`` stream against ``ground_truth`` (NEES where the
    method published covariances). Trajectories missing a message in any stream are left out for
    every method, so that all methods are scored on the same trajectories."""
    truth, estimates, angles = load_bag_dataset(path, namespace=namespace, description=description)
    reports = {m: metrics_mod.compute_metrics(truth.x, xh, angles, P_hat=P) for m, (xh, P) in estimates.items()}
    return BagReport(
        path=Path(path),
        scenario=str(truth.meta.get("scenario", "?")),
        n_trajectories=truth.n,
        horizon=truth.horizon,
        dt=float(truth.meta.get("dt", 1.0)),
        reports=reports,
        bag=truth.meta["bag"],
    )


def write_report(report: BagReport, prefix: str | Path | None = None) -> dict[str, Path]:
    """Write ``<prefix>.metrics.md``, ``.metrics.json`` and ``.rmse.png`` (default: beside the bag)."""
    from neural_estimator.plots import plot_rmse_over_time

    base = Path(prefix) if prefix is not None else report.path.with_suffix("")
    base.parent.mkdir(parents=True, exist_ok=True)
    paths = {
        "markdown": base.with_name(base.name + ".metrics.md"),
        "json": base.with_name(base.name + ".metrics.json"),
        "png": base.with_name(base.name + ".rmse.png"),
    }
    heading = (
        f"# {report.scenario}: {report.n_trajectories} trajectories x {report.horizon} steps ({report.path.name})\n\n"
    )
    paths["markdown"].write_text(heading + report.table("markdown"))
    paths["json"].write_text(json.dumps(report.to_json(), indent=1))
    if report.reports:
        plot_rmse_over_time(
            {m: [r.rmse_t] for m, r in report.reports.items()},
            paths["png"],
            title=f"{report.scenario} ({report.path.name})",
            dt=report.dt,
        )
    else:
        paths.pop("png")
    return paths
