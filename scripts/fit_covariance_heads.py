#!/usr/bin/env python3
"""Fit a covariance head (and its calibration scale) for every shipped model, resumably.

For each (scenario, method) of the shipped zoo (neural_estimator/serving/zoo/<scenario>-<method>/, or with
--instance K its trained instance K, zoo/instances/i<K>/<scenario>-<method>/) whose card
has no ``covariance_head`` yet (or every one with --force), fit a Gaussian head on the model's frozen
trunk on validation data (neural_estimator.serving.uncertainty.fit), write ``covariance_head.safetensors``
beside the weights and add the card's ``covariance_head`` entry. The weights and the estimate are
untouched. One pair at a time; a pair already done is skipped, so an interrupted run continues.

    OMP_NUM_THREADS=1 python scripts/fit_covariance_heads.py --scenarios bearings lorenz96 nlink
    python scripts/fit_covariance_heads.py --scenarios ballistic --methods gru --force
    python scripts/fit_covariance_heads.py --scenarios nlink lorenz96 --instance 1   # the zoo's instance 1
    python scripts/fit_covariance_heads.py --checkpoint my_gru --data held_out_a.npz --calibration-data held_out_b.npz
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from neural_estimator.methods.interface import NEURAL_METHODS
from neural_estimator.paper import PAPER_SCENARIOS
from neural_estimator.serving.export import export_beside
from neural_estimator.serving.card import CARD_FILE, read_card, write_json
from neural_estimator.serving.instances import instance_checkpoint
from neural_estimator.serving.load import load_neural_estimator
from neural_estimator.scenarios import scenario_from_description
from neural_estimator.serving.uncertainty.fit import FitSettings, calibrate_head, choose_shrink, fit_covariance_head
from neural_estimator.serving.uncertainty.heads import load_head, save_head


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", nargs="+", default=["bearings", "lorenz96", "nlink"], choices=PAPER_SCENARIOS)
    ap.add_argument("--methods", nargs="+", default=list(NEURAL_METHODS), choices=NEURAL_METHODS)
    ap.add_argument(
        "--instance",
        type=int,
        default=0,
        help="the trained instance whose heads to fit (default 0, the shipped model; K >= 1: zoo/instances/i<K>/)",
    )
    ap.add_argument("--force", action="store_true", help="refit pairs that already have a head")
    ap.add_argument("--head-trajectories", type=int, default=FitSettings.head_trajectories)
    ap.add_argument("--calibration-trajectories", type=int, default=FitSettings.calibration_trajectories)
    ap.add_argument("--steps", type=int, default=FitSettings.steps)
    ap.add_argument(
        "--choose-shrink",
        action="store_true",
        help="choose the heads' correlation shrinkage on a larger validation set (1000 trajectories of val 103)",
    )
    ap.add_argument(
        "--recalibrate",
        action="store_true",
        help="refit only the calibration scale of the heads already fitted (the calibration set's trunk pass)",
    )
    ap.add_argument("--checkpoint", type=Path, help="a model trained on recorded data (train --data): fit its head")
    ap.add_argument("--data", type=Path, help="with --checkpoint: held-out recorded trajectories to fit the head on")
    ap.add_argument(
        "--calibration-data", type=Path, help="with --checkpoint: other held-out trajectories for the scale"
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    settings = FitSettings(
        head_trajectories=args.head_trajectories,
        calibration_trajectories=args.calibration_trajectories,
        steps=args.steps,
    )
    if args.checkpoint is not None:
        return fit_recorded(args, settings)
    if args.instance < 0:
        print(f"--instance must be >= 0 (0: the shipped model), got {args.instance}", file=sys.stderr)
        return 2
    for scenario_name in args.scenarios:
        for method in args.methods:
            directory = instance_checkpoint(scenario_name, method, args.instance)
            if not (directory / CARD_FILE).is_file():
                what = "no shipped model" if args.instance == 0 else f"no instance {args.instance} in the zoo"
                print(f"{scenario_name}-{method}: {what}, skipped", flush=True)
                continue
            _, card = read_card(directory)
            if args.choose_shrink:
                if card.get("covariance_head"):
                    shrink(directory, scenario_name, method, card)
                continue
            if args.recalibrate:
                if card.get("covariance_head"):
                    recalibrate(directory, scenario_name, method, card, settings)
                continue
            if card.get("covariance_head") and not args.force:
                print(f"{scenario_name}-{method}: has a covariance head, skipped", flush=True)
                continue
            t0 = time.time()
            print(f"{scenario_name}-{method}: fitting", flush=True)
            scenario = scenario_from_description(card["scenario"])
            est = load_neural_estimator(method, scenario, directory, covariance=False)
            head, info = fit_covariance_head(est, settings, log=lambda m: print(m, flush=True))
            entry = save_head(directory, head, info)
            _, card = read_card(directory)  # re-read: write only our entry
            card["covariance_head"] = entry
            write_card(directory, card)
            cal = info["calibration"]
            print(
                f"{scenario_name}-{method}: scale {cal['scale']:.3g}; calibration set before "
                f"{_fmt(cal['before'])}; after {_fmt(cal['after'])} ({time.time() - t0:.0f} s)",
                flush=True,
            )
    return 0


def fit_recorded(args, settings: FitSettings) -> int:
    """The head of a model trained on recorded data, fitted on held-out recorded trajectories."""
    from neural_estimator.data import load_trajectories
    from neural_estimator.robot import DataScenario

    if args.data is None or args.calibration_data is None:
        print("--checkpoint needs --data and --calibration-data (held-out recorded trajectories)", file=sys.stderr)
        return 2
    fit_data, _ = load_trajectories(args.data)
    cal_data, _ = load_trajectories(args.calibration_data)
    _, card = read_card(args.checkpoint)
    est = load_neural_estimator(card["method"], DataScenario(fit_data.meta), args.checkpoint, covariance=False)
    head, info = fit_covariance_head(est, settings, print, head_data=fit_data, calibration_data=cal_data)
    _, card = read_card(args.checkpoint)
    card["covariance_head"] = save_head(args.checkpoint, head, info)
    write_card(Path(args.checkpoint), card, DataScenario(fit_data.meta))
    print(f"{args.checkpoint}: scale {info['calibration']['scale']:.3g}; after {_fmt(info['calibration']['after'])}")
    return 0


def write_card(directory: Path, card: dict, scenario=None) -> None:
    """The card with its new head entry, and step.onnx exported anew with that head (the graph
    records the head's digest and shrinkage; the per-message estimators refuse a stale one)."""
    write_json(Path(directory) / CARD_FILE, card)
    export_beside(directory, scenario)


def shrink(directory, scenario_name: str, method: str, card: dict) -> None:
    """Choose a fitted head's correlation shrinkage (the card's ``covariance_head.shrink``)."""
    entry = card["covariance_head"]
    scenario = scenario_from_description(card["scenario"])
    est = load_neural_estimator(method, scenario, directory, covariance=False)
    head = load_head(directory, entry, scenario.dx)
    record = choose_shrink(est, head)
    entry["shrink"] = record["value"]
    entry["shrink_choice"] = record
    write_card(directory, card)
    best = next(c for c in record["candidates"] if c["shrink"] == record["value"])
    print(f"{scenario_name}-{method}: shrink {record['value']}; {_fmt(best)}", flush=True)


def recalibrate(directory, scenario_name: str, method: str, card: dict, settings: FitSettings) -> None:
    """Refit the calibration scale of a fitted head in place (head file, its sha256 and the card entry)."""
    t0 = time.time()
    entry = card["covariance_head"]
    scenario = scenario_from_description(card["scenario"])
    est = load_neural_estimator(method, scenario, directory, covariance=False)
    head = load_head(directory, entry, scenario.dx)
    cal = calibrate_head(est, head, settings)
    entry = save_head(directory, head, {k: v for k, v in entry.items() if k not in ("file", "sha256", "form")})
    entry["calibration"] = cal
    entry["settings"] = dict(entry.get("settings", {}), scale_target=settings.scale_target)
    card["covariance_head"] = entry
    write_card(directory, card)
    print(
        f"{scenario_name}-{method}: recalibrated, scale {cal['scale']:.3g}; before {_fmt(cal['before'])}; "
        f"after {_fmt(cal['after'])} ({time.time() - t0:.0f} s)",
        flush=True,
    )


def _fmt(f: dict) -> str:
    return (
        f"cov95 {f['coverage95']:.3f}, NEES mean/dx {f['nees_mean_per_dim']:.2f}, med/dx {f['nees_median_per_dim']:.2f}"
    )


if __name__ == "__main__":
    sys.exit(main())
