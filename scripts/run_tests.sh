#!/usr/bin/env bash
# The test command: installs what is missing into .venv (scripts/bootstrap.sh test: the runtime set
# plus the test, lint, docs and reference tools), then lints, builds the documentation site and runs
# the whole test suite. Extra arguments go to pytest (e.g. scripts/run_tests.sh -k metrics).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh" test
venv="${NEURAL_ESTIMATOR_VENV:-$root/.venv}"
cd "$root"
# Each ROS test picks its own domain from NEURAL_ESTIMATOR_DOMAINS (LO-HI; set it to confine the run to
# a share of a shared host's domains); anything else keeps off any user's graph on ROS_DOMAIN_ID 77.
export NEURAL_ESTIMATOR_DOMAINS="${NEURAL_ESTIMATOR_DOMAINS:-200-232}"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-77}"
export MPLBACKEND=Agg
# One BLAS/torch thread per process: the tests use small arrays, where two threads on two cores
# (one of them also running the test's ROS nodes) only contend.
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}" MKL_NUM_THREADS="${MKL_NUM_THREADS:-1}"
# Lint and formatting first (ruff.toml; under a second): a style slip fails the run like a test.
"$venv/bin/ruff" check neural_estimator test scripts benchmarks experiments examples docs
"$venv/bin/ruff" format --check --quiet neural_estimator test scripts benchmarks experiments examples docs
# The documentation site (mkdocs.yml): a broken link, a missing page or a failing generator fails the run.
NO_MKDOCS_2_WARNING=1 "$venv/bin/python" -m mkdocs build --strict --quiet --site-dir "$root/.cache/site"
# Two pytest-xdist workers (NEURAL_ESTIMATOR_TEST_WORKERS; 0: one process): much of the suite waits on ROS
# discovery and node start-up, and the other core works meanwhile. --dist loadfile: a test file's tests
# stay on one worker (its module fixtures built once); each worker takes its own share of
# NEURAL_ESTIMATOR_DOMAINS (test/conftest.py), and each Ray test starts a Ray of its own.
exec "$venv/bin/python" -m pytest -q -n "${NEURAL_ESTIMATOR_TEST_WORKERS:-2}" --dist loadfile test "$@"
