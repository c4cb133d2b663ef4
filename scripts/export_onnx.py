"""Write a neural model's (or the KalmanNet hybrid's) batch-1 step as an ONNX graph (for ONNX Runtime serving).

    python scripts/export_onnx.py --scenario lorenz96 --method gru --out gru_step.onnx
    python scripts/export_onnx.py --scenario lorenz96 --method mamba --checkpoint runs/my-mamba --out m.onnx
    python scripts/export_onnx.py --scenario lorenz96 --method gpt2 --checkpoint runs/my-gpt2 --beside

``--beside`` writes the network-only graph as ``step.onnx`` in the checkpoint's directory, next to
its card, with the digests of the card's weights and covariance head in the graph (``train`` does
this itself when it saves a model, and the zoo ships them): there the per-message estimators (the
estimator nodes and replay, backend ``auto``) serve it with numpy and onnxruntime only, without
importing torch (docs/performance.md, "Serving without torch"). GPT-2 and Filterformer are
exported with the attention window they serve with (the card's validation context, or ``--context``):
their key/value cache of the last W steps is the graph's state. A recurrent model validated with a
bounded context (the card's ``val_context``: L steps, K restarted copies) is exported ``--beside``
as the step of its K copies as one batch (the server restarts the copies' rows); ``--out``
exports its unbounded step. The covariance head's covariance (or Filterformer's own) is a graph
output.

The graph is made from the checkpoint (card + safetensors weights) by
:func:`neural_estimator.models.onnx_step.export_step`: the same checkpoint gives the same bytes. By
default it is the whole estimator step, the card's normalisation included (y, u in float64 -> the
estimate x in float64, and a flag for a skipped non-finite observation); ``--network-only`` writes the
network alone (normalised z in, normalised mean out). Serving it needs only numpy and onnxruntime
(:class:`~neural_estimator.serving.onnx_runtime.OrtStep`), not torch; exporting needs torch and onnx.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neural_estimator.methods.interface import EstimatorError  # noqa: E402
from neural_estimator.methods import table  # noqa: E402
from neural_estimator.models.onnx_step import OnnxError, export_step  # noqa: E402
from neural_estimator.serving.export import export_beside, torch_only_reason  # noqa: E402
from neural_estimator.serving.card import checkpoint_paths  # noqa: E402
from neural_estimator.serving.card import default_checkpoint  # noqa: E402
from neural_estimator.serving.load import load_neural_estimator  # noqa: E402
from neural_estimator.serving.onnx_runtime import ONNX_FILE, served_files  # noqa: E402
from neural_estimator.scenarios import ScenarioError, make_scenario, scenario_from_description  # noqa: E402
from neural_estimator.serving.card import read_card  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--method", required=True, choices=table.names(exportable=True))
    ap.add_argument("--checkpoint", default=None, help="checkpoint directory or card.json (default: the shipped one)")
    ap.add_argument("--out", default=None, help="the .onnx file to write")
    ap.add_argument(
        "--beside", action="store_true", help=f"write the network-only graph as {ONNX_FILE} beside the card"
    )
    ap.add_argument("--network-only", action="store_true", help="leave the normalisation out of the graph")
    ap.add_argument(
        "--context",
        type=int,
        default=None,
        help="GPT-2, Filterformer: the attention window W (default: as the card validated the model)",
    )
    a = ap.parse_args(argv)
    if (a.out is None) == (not a.beside):
        ap.error("give --out or --beside (one of them)")
    attention = table.has(a.method, context="window")
    try:
        if a.beside and a.context is None:  # the checkpoint's own serving configuration
            directory = checkpoint_paths(a.checkpoint or default_checkpoint(a.scenario, a.method))[0]
            written = export_beside(directory)  # the scenario as the card describes it
            if written is None:
                print(f"error: {directory}: {_why_torch(directory)}", file=sys.stderr)
                return 1
            data = written.read_bytes()
            print(f"{written}: {len(data):,} bytes, sha256 {hashlib.sha256(data).hexdigest()[:16]}")
            return 0
        context = a.context if attention else 0  # the recurrent models' graph is the unbounded step
        est = load_neural_estimator(a.method, make_scenario(a.scenario), checkpoint=a.checkpoint, context=context)
        directory = checkpoint_paths(a.checkpoint or default_checkpoint(a.scenario, a.method))[0]
        out = Path(a.out) if a.out else directory / ONNX_FILE
        data = export_step(
            est.model,
            a.method,
            out,
            normalizer=None if (a.network_only or a.beside) else est.normalizer,
            covariance=est.has_covariance,
            metadata=served_files(est.card),
        )
    except (EstimatorError, OnnxError, ScenarioError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"{out}: {len(data):,} bytes, sha256 {hashlib.sha256(data).hexdigest()[:16]}")
    return 0


def _why_torch(directory: Path) -> str:
    """Why ``export_beside`` wrote no graph for ``directory`` (a hybrid's system without an ONNX form)."""
    _, card = read_card(directory)
    est = load_neural_estimator(card["method"], scenario_from_description(card["scenario"]), directory)
    return torch_only_reason(est) or "its step is not exported"


if __name__ == "__main__":
    sys.exit(main())
