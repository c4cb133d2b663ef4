#!/usr/bin/env bash
# Train every instance the findings need (docs/training.md, "Trained instances"), one worker per core.
#
# The queue: instances 1 and 2 of the nine pairs where a finding hinges on a ranking (the six N-link
# networks, the Lorenz 96 GRU, Mamba and Mamba-2); instance 0 is the shipped model. Each worker walks
# the whole queue from its own starting point, one `train_zoo.py --instance K` call per entry, so the
# workers start on different trainings and then share what is left: an entry another worker holds is
# skipped (train_zoo.py's lock), a finished or installed one returns at once, an unfinished one
# resumes from its last epoch. Run it again in a later session to go on; stop it with Ctrl-C (or
# `pkill -TERM -f train_zoo.py`), which loses at most the epoch in progress.
#
#   scripts/train_instances.sh            # one worker per core, in the foreground
#   scripts/train_instances.sh 1          # one worker
#   WORKERS=2 nohup scripts/train_instances.sh > instances.log 2>&1 &
#   .venv/bin/python scripts/train_zoo.py --instance 2 --scenarios nlink,lorenz96 --status   # progress
set -euo pipefail
cd "$(dirname "$0")/.."

workers="${1:-${WORKERS:-$(nproc)}}"
if ! [[ "$workers" =~ ^[1-9][0-9]*$ ]]; then
    echo "train_instances.sh: the number of workers must be a positive integer, got '$workers'" >&2
    exit 2
fi
python="${PYTHON:-.venv/bin/python}"
if ! [[ -x "$python" ]]; then
    echo "train_instances.sh: no Python at $python (run scripts/bootstrap.sh test first, or set PYTHON)" >&2
    exit 2
fi

# longest first within each instance, so the long trainings do not all come last
queue=()
for instance in 1 2; do
    for pair in nlink:mamba2 lorenz96:mamba nlink:mamba lorenz96:mamba2 nlink:gru nlink:gpt2 \
        lorenz96:gru nlink:lstm nlink:filterformer; do
        queue+=("$instance:$pair")
    done
done

walk() {  # worker $1 of $workers: the queue from entry $1 * len / workers on, wrapping round
    local n=${#queue[@]} i entry instance scenario method
    local start=$(($1 * n / workers))
    for ((i = 0; i < n; i++)); do
        entry="${queue[$(((start + i) % n))]}"
        IFS=: read -r instance scenario method <<<"$entry"
        # one thread per worker: two workers on two cores, no oversubscription
        OMP_NUM_THREADS=1 PYTHONPATH="$PWD" nice -n 10 "$python" scripts/train_zoo.py --threads 1 \
            --instance "$instance" --scenarios "$scenario" --methods "$method" --quiet ||
            echo "train_instances.sh: worker $1: instance $instance $scenario-$method exited with $?" >&2
    done
}

stop() {  # the workers first, so that none starts its next entry, then their trainings (which lose at most
    # the epoch in progress)
    trap - INT TERM
    local workers_pids trainings
    workers_pids=$(jobs -p)
    trainings=$(for pid in $workers_pids; do pgrep -P "$pid" || true; done)
    # shellcheck disable=SC2086  # word splitting wanted: lists of pids
    kill -TERM $workers_pids $trainings 2>/dev/null || true
    wait
}
trap stop INT TERM
for ((w = 0; w < workers; w++)); do
    walk "$w" &
done
wait
