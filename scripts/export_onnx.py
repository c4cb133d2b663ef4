"""Write a recurrent model's batch-1 step as an ONNX graph (for ONNX Runtime serving).

    python scripts/export_onnx.py --scenario lorenz96 --method gru --out gru_step.onnx
    python scripts/export_onnx.py --scenario lorenz96 --method mamba --checkpoint runs/my-mamba --out m.onnx

The graph is made from the checkpoint (card + safetensors weights) by
:func:`neural_estimator.models.onnx_step.export_step`: the same checkpoint gives the same bytes. By
default it is the whole estimator step, the card's normalisation included (y, u in float64 -> the
estimate x in float64, and a flag for a skipped non-finite observation); ``--network-only`` writes the
network alone (normalised z in, normalised mean out). Serving it needs only numpy and onnxruntime
(:class:`~neural_estimator.models.onnx_step.OrtStep`), not torch; exporting needs torch and onnx.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neural_estimator.estimator import EstimatorError  # noqa: E402
from neural_estimator.models.onnx_step import EXPORTABLE, OnnxError, export_step  # noqa: E402
from neural_estimator.serving.load import load_neural_estimator  # noqa: E402
from neural_estimator.scenarios import ScenarioError, make_scenario  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--method", required=True, choices=EXPORTABLE)
    ap.add_argument("--checkpoint", default=None, help="checkpoint directory or card.json (default: the shipped one)")
    ap.add_argument("--out", required=True, help="the .onnx file to write")
    ap.add_argument("--network-only", action="store_true", help="leave the normalisation out of the graph")
    a = ap.parse_args(argv)
    try:
        est = load_neural_estimator(a.method, make_scenario(a.scenario), checkpoint=a.checkpoint, context=0)
        data = export_step(est.model, a.method, a.out, normalizer=None if a.network_only else est.normalizer)
    except (EstimatorError, OnnxError, ScenarioError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"{a.out}: {len(data):,} bytes, sha256 {hashlib.sha256(data).hexdigest()[:16]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
