#!/usr/bin/env bash
# The classical rows of docs/fidelity.md: the classical filters on the given scenarios, 3 sets,
# seed 1, for each initialisation reading in $INITS. EKF/UKF/EnKF at $N trajectories per set, the PF
# at $NPF (it is far slower). Scored from step $WARMUP (default 10, the paper's warm-up; WARMUP=0 scores
# every step).
# Outputs: benchmarks/results/fidelity/<scenario>-<methods>-<init>-<n>.txt
#   N=1000 NPF=100 INITS="prior truth" nice -n 10 bash benchmarks/run_fidelity.sh bearings nlink
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
N=${N:-1000}; NPF=${NPF:-100}; INITS=${INITS:-prior truth}; WARMUP=${WARMUP:-10}
out=benchmarks/results/fidelity; mkdir -p "$out"
for s in "$@"; do
  for init in $INITS; do
    if [ "$N" -gt 0 ]; then
      .venv/bin/neural-estimator evaluate --scenario "$s" --methods ekf,ukf,enkf --trajectories "$N" --sets 3 --seed 1 \
        --init "$init" --warmup "$WARMUP" --no-cache --quiet > "$out/$s-ekf_ukf_enkf-$init-$N.txt" 2>&1
    fi
    if [ "$NPF" -gt 0 ]; then
      .venv/bin/neural-estimator evaluate --scenario "$s" --methods pf --trajectories "$NPF" --sets 3 --seed 1 \
        --init "$init" --warmup "$WARMUP" --no-cache --quiet > "$out/$s-pf-$init-$NPF.txt" 2>&1
    fi
  done
done
