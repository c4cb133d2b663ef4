#!/usr/bin/env bash
# Creates .venv (once) and installs what is missing into it. Idempotent: a second run that finds
# everything in place does nothing but a quick import check. Sourced by scripts/run_demo.sh and
# scripts/run_tests.sh; may also be run directly.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${NEURAL_ESTIMATOR_VENV:-$root/.venv}"
py="${PYTHON:-python3}"

if [ ! -x "$venv/bin/python" ]; then
  echo "[bootstrap] creating virtual environment in $venv"
  "$py" -m venv "$venv"
fi
vpy="$venv/bin/python"

# The stamp records the hash of the requirement list and of setup.py: when either changes, reinstall.
# The import check runs from / so that a checkout on the path cannot hide a stale editable install.
stamp="$venv/.neural_estimator_stamp"
want="$(cat "$root/scripts/requirements.txt" "$root/setup.py" | sha256sum | cut -d' ' -f1)"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && (cd / && "$vpy" -c "import neural_estimator, torch, rclpy") 2>/dev/null; then
  exit 0
fi

echo "[bootstrap] installing dependencies into $venv (first run takes a minute)"
"$vpy" -m pip install -q --disable-pip-version-check --upgrade pip
# torch is pinned: the CPU build of 2.13.0 is on disk here; an unpinned torch pulls several GB of CUDA.
"$vpy" -m pip install -q --disable-pip-version-check -r "$root/scripts/requirements.txt"
"$vpy" -m pip install -q --disable-pip-version-check --no-deps -e "$root"
echo "$want" > "$stamp"
echo "[bootstrap] ready"
