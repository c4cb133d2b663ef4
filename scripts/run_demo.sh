#!/usr/bin/env bash
# The main job (README, docs/getting-started.md): installs what is missing into .venv, then runs the
# live ROS 2 pipeline on the default scenario: a simulator node publishes noisy observations and ground
# truth, estimator nodes (classical and neural) update once per message, and the evaluator records
# every stream into one MCAP bag, then prints the paper's metrics table. Ends with the table and the
# bag's path.
#
#   scripts/run_demo.sh                          # lorenz96: every method of the table, filters started from y0
#   scripts/run_demo.sh --init prior             # the paper's start (the Lorenz 96 PF then collapses, marked (!))
#   scripts/run_demo.sh --scenario bearings --methods ukf,pf,enkf --trajectories 4
#
# Any argument is passed to `neural-estimator live` (see its --help). It installs only what it
# runs (scripts/bootstrap.sh runtime); the test command adds the test and docs tools.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh" runtime
venv="${NEURAL_ESTIMATOR_VENV:-$root/.venv}"
cd "$root"
args=("$@")
has() { local f; for f in "${args[@]}"; do [ "$f" = "$1" ] && return 0; done; return 1; }
# The filters start from the first observation (Lorenz 96: x0 = y0, h = I; docs/metrics.md, "Filter
# starts"), as a practitioner would start them; --init prior gives the paper's start. Only on the
# default scenario: where h determines no state component (bearings) the start is refused.
has --scenario || has --init || args+=(--init observation)
has --scenario || args+=(--scenario lorenz96)
# every method of the table of methods (neural_estimator/methods/table.py), in its order
has --methods || args+=(--methods "$("$venv/bin/python" -m neural_estimator.methods.table)")
has --trajectories || args+=(--trajectories 4)
has --rate-hz || args+=(--rate-hz 200)
has --output || args+=(--output "runs/demo-$(date +%Y%m%d-%H%M%S).mcap")
exec "$venv/bin/neural-estimator" live "${args[@]}"
