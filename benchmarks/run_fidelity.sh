#!/usr/bin/env bash
# The README's "Fidelity to the paper" rows: the classical filters on every scenario, 3 sets, seed 1,
# both initialisation readings. EKF/UKF/EnKF at $N trajectories, the PF at $NPF (slower). Outputs in
# benchmarks/results/fidelity/<scenario>-<methods>-<init>.txt.
#   N=1000 NPF=100 nice -n 10 bash benchmarks/run_fidelity.sh [scenario ...]
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
N=${N:-1000}; NPF=${NPF:-100}
out=benchmarks/results/fidelity; mkdir -p "$out"
for s in "${@:-bearings nlink quadrotor ballistic lorenz96}"; do
  for s1 in $s; do
    for init in prior truth; do
      .venv/bin/neural-estimator evaluate --scenario "$s1" --methods ekf,ukf,enkf --trajectories "$N" --sets 3 --seed 1 \
        --init "$init" --no-cache --quiet > "$out/$s1-ekf_ukf_enkf-$init-$N.txt" 2>&1
      .venv/bin/neural-estimator evaluate --scenario "$s1" --methods pf --trajectories "$NPF" --sets 3 --seed 1 \
        --init "$init" --no-cache --quiet > "$out/$s1-pf-$init-$NPF.txt" 2>&1
    done
  done
done
