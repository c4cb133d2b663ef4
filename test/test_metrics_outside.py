"""``metrics`` scores a bag's announced run and says, in one note, how many messages it set aside
because their identity lies outside that run (here one estimate claiming step 3,000,000)."""

from __future__ import annotations

from pathlib import Path

from neural_estimator.stream import messages as MSG
from neural_estimator.bags.reader import BagReader
from neural_estimator.bags.writer import BagWriter
from neural_estimator.cli.app import main

ROOT = Path(__file__).resolve().parents[1]


def _table(out: str) -> list[str]:
    return [line for line in out.splitlines() if line.startswith("ekf")]


def test_metrics_says_a_message_outside_the_run_was_set_aside(tmp_path, capsys):
    scored = tmp_path / "scored.mcap"
    assert main(["replay", str(ROOT / "bags" / "lorenz96.mcap"), "--methods", "ekf", "--out", str(scored)]) == 0
    capsys.readouterr()
    assert main(["metrics", str(scored)]) == 0
    clean = capsys.readouterr()
    assert "outside the announced run" not in clean.err

    forged = tmp_path / "forged.mcap"
    with BagReader(scored) as src, BagWriter(forged) as out:
        for conn in src.connections:
            out.add_topic(conn.topic, conn.msgtype)
        last = None
        for conn, t, raw in src.messages():
            out.write(conn.topic, t, raw)
            if conn.topic == "/estimates/ekf":
                last = (t, MSG.decode_vector(raw))
        t, vec = last
        out.write("/estimates/ekf", t + 1, MSG.encode_vector(t + 1, vec.frame_id, 0, 3_000_000, vec.names, vec.values))
    assert main(["metrics", str(forged)]) == 0
    got = capsys.readouterr()
    assert _table(got.out) == _table(clean.out)  # the table is the announced run's, unchanged
    notes = [line for line in got.err.splitlines() if "outside the announced run" in line]
    assert notes == ["neural-estimator: note: 1 message outside the announced run set aside (estimates/ekf 1)"], got.err
