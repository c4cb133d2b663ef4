"""``reproduce``: plan the scale's jobs, run them on Ray, write the report (markdown + PNGs + JSON)."""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from neural_estimator.paper.reproduce.engine import Outcome, run_jobs
from neural_estimator.paper.reproduce.jobs import Job
from neural_estimator.paper.reproduce.plan import plan_jobs
from neural_estimator.paper.reproduce.report import write_report
from neural_estimator.paper.reproduce.settings import ReproduceError, Settings, describe_settings

STATE_FILE = "reproduce.json"  # in --out: the run's settings and every job's status


def check_out_dir(out: Path, settings: Settings, resume: bool) -> None:
    state = out / STATE_FILE
    if not state.is_file():
        return
    if not resume:
        raise ReproduceError(
            f"{out} holds a previous reproduce run ({STATE_FILE}); pass --resume to continue it, "
            "or choose another --out"
        )
    try:
        before = json.loads(state.read_text()).get("settings")
    except ValueError:
        raise ReproduceError(f"{state} is damaged; remove it or choose another --out") from None
    if before != json.loads(json.dumps(settings.to_json())):  # compared as stored (tuples read back as lists)
        raise ReproduceError(
            f"--resume: {out} holds a run with other settings (scale, scenarios, methods, init or experiments); "
            "choose another --out"
        )


def previous_wall(out: Path) -> tuple[float, int]:
    """(seconds, invocations) that earlier invocations of the run in ``out`` spent, from its state file."""
    try:
        state = json.loads((out / STATE_FILE).read_text())
    except (OSError, ValueError):
        return 0.0, 0
    total = state.get("wall_total_s", state.get("wall_s"))
    if not isinstance(total, (int, float)) or not math.isfinite(total):
        return 0.0, 0  # an interrupted invocation records no time
    return float(total), int(state.get("invocations", 1))


def reproduce(settings: Settings, out: str | Path, *, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    """Run every experiment of the scale and write ``out``/report.md, figures/*.png and reproduce.json."""
    out = Path(out)
    check_out_dir(out, settings, resume)
    jobs = plan_jobs(
        settings.scale,
        settings.scenarios,
        settings.methods,
        gpu=settings.gpu,
        init=settings.init,
        experiments=settings.experiments,
    )
    print(describe_settings(settings, len(jobs)), file=sys.stderr, flush=True)
    out.mkdir(parents=True, exist_ok=True)
    before_s, before_n = previous_wall(out) if resume else (0.0, 0)
    _write_state(out, settings, jobs, None, None, (before_s, before_n))
    t0 = time.time()
    outcome = run_jobs(
        jobs,
        settings.cache_dir,
        address=settings.address,
        num_cpus=settings.num_cpus,
        progress=progress,
        plugins=settings.plugins,
    )
    wall = time.time() - t0
    _write_state(out, settings, jobs, outcome, wall, (before_s, before_n))
    write_report(out, settings, jobs, outcome, wall, (before_s, before_n))
    return {
        "jobs": len(jobs),
        "computed": outcome.computed,
        "cached": outcome.cached,
        "failed": len(outcome.failed),
        "wall_s": wall,
        "report": str(out / "report.md"),
    }


def _write_state(
    out: Path,
    settings: Settings,
    jobs: Sequence[Job],
    outcome: Outcome | None,
    wall: float | None,
    before: tuple[float, int] = (0.0, 0),
) -> None:
    """The state file; ``before``: (seconds, invocations) of the earlier invocations a resumed run continues."""
    from neural_estimator.metrics import to_json

    rows = []
    for i, job in enumerate(jobs):
        row: dict[str, Any] = {"job": job.to_json(), "status": "pending"}
        if outcome is not None and i in outcome.results:
            r = outcome.results[i]
            row.update(status="cached" if r["cached"] else "computed", seconds=r["seconds"], result=r["result"])
            row["node"] = r.get("node")
        elif outcome is not None and i in outcome.failed:
            row.update(status="failed", error=outcome.failed[i])
        rows.append(row)
    payload = to_json(
        {
            "settings": settings.to_json(),
            "complete": outcome is not None and not outcome.failed,
            "wall_s": wall,
            # an unfinished invocation keeps the earlier total, so a second interruption loses nothing
            "wall_total_s": before[0] + wall if wall is not None else (before[0] if before[1] else None),
            "invocations": before[1] + (wall is not None),
            "jobs": rows,
        }
    )
    tmp = out / (STATE_FILE + ".tmp")
    tmp.write_text(json.dumps(payload, indent=1, allow_nan=False))
    tmp.replace(out / STATE_FILE)
