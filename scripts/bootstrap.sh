#!/usr/bin/env bash
# Creates .venv (once) and installs what is missing into it. Idempotent: a second run that finds
# everything in place does nothing but a quick import check.
#
#   scripts/bootstrap.sh [runtime|test]
#
# runtime (the default; scripts/run_demo.sh): what the package, its nodes and the live pipeline run
#   (scripts/requirements.txt).
# test (scripts/run_tests.sh): runtime plus the references, fuzzing, lint, tests, docs, colcon and
#   Ray (scripts/requirements-test.txt).
# NEURAL_ESTIMATOR_VENV=DIR puts the environment elsewhere; PYTHON=python3.X picks the interpreter.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
mode="${1:-runtime}"
case "$mode" in
  runtime) reqs="$root/scripts/requirements.txt"; check="import neural_estimator, torch, rclpy" ;;
  test) reqs="$root/scripts/requirements-test.txt"; check="import neural_estimator, torch, rclpy, pytest, ray, mkdocs" ;;
  *) echo "bootstrap.sh: unknown mode '$mode' (runtime or test)" >&2; exit 2 ;;
esac
venv="${NEURAL_ESTIMATOR_VENV:-$root/.venv}"
py="${PYTHON:-python3}"

if [ ! -x "$venv/bin/python" ]; then
  echo "[bootstrap] creating virtual environment in $venv"
  "$py" -m venv "$venv"
fi
vpy="$venv/bin/python"

# One stamp per mode records the hash of its requirement lists and of setup.py: when one changes,
# reinstall. The import check runs from / so that a checkout on the path cannot hide a stale
# editable install. A test environment also satisfies the runtime mode.
want="$(cat "$root/scripts/requirements.txt" "$reqs" "$root/setup.py" | sha256sum | cut -d' ' -f1)"
stamp="$venv/.neural_estimator_stamp.$mode"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && (cd / && "$vpy" -c "$check") 2>/dev/null; then
  exit 0
fi
if [ "$mode" = runtime ] && [ -f "$venv/.neural_estimator_stamp.test" ] \
  && [ "$(cat "$venv/.neural_estimator_stamp.test")" = "$(cat "$root/scripts/requirements.txt" "$root/scripts/requirements-test.txt" "$root/setup.py" | sha256sum | cut -d' ' -f1)" ] \
  && (cd / && "$vpy" -c "$check") 2>/dev/null; then
  exit 0
fi

echo "[bootstrap] installing the $mode dependencies into $venv (first run takes a few minutes)"
"$vpy" -m pip install -q --disable-pip-version-check --upgrade pip
"$vpy" -m pip install -q --disable-pip-version-check -r "$reqs"
"$vpy" -m pip install -q --disable-pip-version-check --no-deps -e "$root"
echo "$want" > "$stamp"
echo "[bootstrap] ready"
