"""MkDocs hook: the generated parts of the documentation site.

A page holds a marker, an HTML comment ``<!-- generate: NAME [ARG] -->`` on its own line, and the
hook replaces it with text generated from the code or from committed result files, so that no
reference table or result is typed by hand:

    node-params NODE     the parameter table of a ROS 2 node, from its parameter dataclass
    cli VERB             ``neural-estimator VERB --help``
    scoreboard           the neural scoreboard, from docs/results/neural_scoreboard.json
    headline             the headline answer (per system: best filter, best network, paired ratio, verdict),
                         measured once on the sealed family, from docs/results/headline/headline.json
    headline-findings    the paper's seven findings judged on that measurement's paired intervals
    defaults-table       the paper's main table at the defaults, ours · the paper's, cell by cell, from
                         benchmarks/results/fidelity_measured (scripts/fidelity_table.py)
    fidelity-summary     how many of those cells are within 1.5x of the paper's, the NRMSE accounting and
                         the findings' count, from the same measurement
    fidelity-measured    the whole fidelity section of that measurement
    report-section TITLE a section of the committed small-scale report (docs/results/small/report.md)
    zoo                  the shipped models, from their cards (neural_estimator/serving/zoo/*/card.json)
    zoo-instances        the trained instances of the pairs that have several, from their cards
    fidelity             the classical rows against the paper, from benchmarks/results/fidelity/*.txt
                         and neural_estimator/paper/paper_results.json
    methods              the table of methods and what each can do (neural_estimator/methods/table.py)
    mismatch             the mismatch crossovers, from docs/results/mismatch/*.json (neural-estimator mismatch)

The README cannot run a hook, so its generated parts sit between ``<!-- generated: NAME -->`` and
``<!-- /generated -->`` lines, rewritten by ``python scripts/update_readme.py`` (:func:`update_readme`);
``test/test_docs.py`` fails when one differs from its generator.

The node parameters are read from the source with ``ast`` (the node modules import rclpy; the
site builds without it). ``test/test_docs.py`` holds the params/*.yaml files to the same dataclasses.
"""

from __future__ import annotations

import ast
import importlib
import json
import re
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]

# the parameter groups shared by the estimator nodes: standard outputs and input diagnostics
_OUTPUTS = ("neural_estimator/nodes/outputs.py", "OutputParams")
_INPUTS = ("neural_estimator/nodes/diagnostics.py", "InputDiagnosticsParams")
# node executable -> the (source file, parameter dataclass) pairs it declares, in declaration order
NODE_PARAMS = {
    "simulator": (("neural_estimator/nodes/simulator_node.py", "SimulatorParams"),),
    "estimator": (("neural_estimator/nodes/estimator_params.py", "EstimatorParams"), _OUTPUTS, _INPUTS),
    "evaluator": (("neural_estimator/nodes/evaluator_node.py", "EvaluatorParams"),),
    "player": (("neural_estimator/nodes/player_node.py", "PlayerParams"),),
    "robot_estimator": (
        ("neural_estimator/nodes/robot_estimator_node.py", "RobotEstimatorParams"),
        _OUTPUTS,
        _INPUTS,
    ),
}
# executables that declare another node's parameters (the lifecycle estimator: the estimator's)
NODE_ALIASES = {"lifecycle_estimator": "estimator"}

MARKER = re.compile(r"^<!-- generate: ([a-z-]+)(?: (.*?))? -->$", re.M)


# ---- node parameters ----------------------------------------------------------------------------
def _name(name: str, tree: ast.Module) -> Any:
    """A module-level name of a node module: imported from a module that does not import rclpy, or
    assigned a literal there."""
    for stmt in tree.body:
        if isinstance(stmt, ast.ImportFrom) and any(a.name == name for a in stmt.names):
            return getattr(importlib.import_module(stmt.module), name)
        if isinstance(stmt, ast.Assign) and any(getattr(t, "id", None) == name for t in stmt.targets):
            return ast.literal_eval(stmt.value)
    raise ValueError(f"cannot resolve {name!r}")


def _value(node: ast.expr, tree: ast.Module) -> Any:
    """A default or a help text: a literal, or an expression over module-level names (an f-string)."""
    try:
        return ast.literal_eval(node)
    except ValueError:
        pass
    names = {n.id: _name(n.id, tree) for n in ast.walk(node) if isinstance(n, ast.Name)}
    return eval(compile(ast.Expression(body=node), "<param>", "eval"), {"__builtins__": {}}, names)  # noqa: S307


def node_params(node: str) -> list[dict[str, Any]]:
    """[{name, type, default, help}] of a node's parameter dataclasses, in declaration order (read
    from the source: the node modules import rclpy, and the site builds without it)."""
    return [p for path, cls in NODE_PARAMS[node] for p in _dataclass_params(path, cls)]


def _dataclass_params(path: str, cls: str) -> list[dict[str, Any]]:
    tree = ast.parse((ROOT / path).read_text())
    klass = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == cls)
    out = []
    for stmt in klass.body:
        if not (isinstance(stmt, ast.AnnAssign) and isinstance(stmt.value, ast.Call)):
            continue
        call = stmt.value
        if getattr(call.func, "id", None) not in ("param", "_param"):
            continue
        out.append(
            {
                "name": stmt.target.id,
                "type": ast.unparse(stmt.annotation),
                "default": _value(call.args[0], tree),
                "help": _value(call.args[1], tree),
            }
        )
    return out


def _show(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return json.dumps(list(value))
    return repr(value)


def params_table(node: str) -> str:
    rows = ["| parameter | type | default | meaning |", "|---|---|---|---|"]
    for p in node_params(node):
        rows.append(f"| `{p['name']}` | {p['type']} | `{_show(p['default'])}` | {p['help'].replace('|', '/')} |")
    return "\n".join(rows)


# ---- command line ---------------------------------------------------------------------------------
def cli_help(verb: str) -> str:
    import contextlib
    import io

    if verb == "live":
        from neural_estimator.nodes.launch import build_parser as live_parser

        parser = live_parser()
    else:
        from neural_estimator.cli import build_parser

        top = build_parser()
        sub = next(a for a in top._actions if a.__class__.__name__ == "_SubParsersAction")
        parser = top if verb == "-" else sub.choices[verb]
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        parser.print_help()
    return "```text\n" + buf.getvalue().rstrip() + "\n```"


# ---- results ----------------------------------------------------------------------------------------
def _num(x: float) -> str:
    return f"{x:.4g}"


def scoreboard() -> str:
    data = json.loads((ROOT / "docs/results/neural_scoreboard.json").read_text())
    scenarios = list(data)
    models = list(next(iter(data.values())))
    rows = [
        "| model | " + " | ".join(scenarios) + " |",
        "|---|" + "---:|" * len(scenarios),
    ]
    for m in models:
        cells = []
        for s in scenarios:
            c = data[s][m]
            cells.append(f"{_num(c['rmse'])} ± {c['iqr']:.2g} · {c['paper']} <sub>{c['budget']}</sub>")
        rows.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def report_section(title: str) -> str:
    """The body of the committed small-scale report's section whose heading starts with ``title``
    (its figure links rewritten to the report's folder)."""
    text = (ROOT / "docs/results/small/report.md").read_text()
    m = re.search(rf"^## {re.escape(title)}.*?\n(.*?)(?=^## |\Z)", text, re.M | re.S)
    if not m:
        raise ValueError(f"docs/results/small/report.md has no section {title!r}")
    body = m.group(1).strip()
    return re.sub(r"\]\((figures/[^)]+)\)", r"](results/small/\1)", body)


ZOO = ROOT / "neural_estimator" / "serving" / "zoo"


def zoo() -> str:
    """The shipped models, one row per card of neural_estimator/serving/zoo: budget, stop, card metrics."""
    return _zoo_table([(p.parent.name, p) for p in sorted(ZOO.glob("*/card.json"))], "model")


def zoo_instances() -> str:
    """The further trained instances (neural_estimator/serving/zoo/instances/i<K>/), pair by pair,
    instance 0 (the shipped model) first: the spread that the tables' medians summarise."""
    pairs = sorted({p.parent.name for p in ZOO.glob("instances/i*/*/card.json")})
    named = []
    for pair in pairs:
        named.append((f"{pair} (0)", ZOO / pair / "card.json"))
        found = {int(p.parent.parent.name[1:]): p for p in ZOO.glob(f"instances/i*/{pair}/card.json")}
        named += [(f"{pair} ({k})", found[k]) for k in sorted(found)]
    return _zoo_table(named, "model (instance)")


def _zoo_table(named_cards: list[tuple[str, Path]], first: str) -> str:
    """One row per (name, card path)."""
    rows = [
        f"| {first} | loss units | epochs (best) | CPU hours | lr reductions | stopped | RMSE (NRMSE), card |",
        "|---|---|---:|---:|---:|---|---:|",
    ]
    for name, card_path in named_cards:
        card = json.loads(card_path.read_text())
        t = card["training"]
        recipe = t.get("recipe", {})
        ctx = f", ctx {recipe['val_context']}" if recipe.get("val_context") else ""
        hours = t.get("budget", {}).get("wall_seconds", 0) / 3600
        metrics = card.get("metrics", {})
        rmse = metrics.get("rmse")
        score = f"{rmse:.4g} ({metrics.get('nrmse', float('nan')):.3f})" if isinstance(rmse, (int, float)) else "—"
        stopped = str(t.get("stopped", "")).split(":")[0].replace("|", "/")
        rows.append(
            f"| {name}{ctx} | {recipe.get('loss_units', 'normalised')} | "
            f"{t.get('epochs_run')} ({t.get('best_epoch')}) | {hours:.2f} | {t.get('lr_reductions')} | "
            f"{stopped} | {score} |"
        )
    return "\n".join(rows)


FIDELITY_LINE = re.compile(r"^(ekf|ukf|enkf|pf)\s+(\S+)")


def fidelity() -> str:
    """Classical RMSE, median ± IQR over 3 sets, from the prior and from the truth, beside the paper's."""
    paper = json.loads((ROOT / "neural_estimator/paper/paper_results.json").read_text())["accuracy_main"]
    folder = ROOT / "benchmarks/results/fidelity"
    rows = [
        "| scenario | filters start | EKF | UKF | EnKF | PF |",
        "|---|---|---|---|---|---|",
    ]
    for scenario in sorted({p.name.split("-")[0] for p in folder.glob("*.txt")}):
        for init in ("prior", "truth"):
            found: dict[str, str] = {}
            for path in sorted(folder.glob(f"{scenario}-*-{init}-*.txt")):
                for line in path.read_text().splitlines():
                    m = FIDELITY_LINE.match(line)
                    if m:
                        found[m.group(1)] = m.group(2)
            cells = []
            for method in ("ekf", "ukf", "enkf", "pf"):
                ours = found.get(method, "—")
                theirs = paper[scenario][method]["rmse"]
                cells.append(f"{ours} · {theirs}" if init == "prior" else ours)
            rows.append(f"| {scenario} | {init} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def defaults_table() -> str:
    """The headline RMSE table at the defaults, fresh seeds (README, results page)."""
    from neural_estimator.paper.reproduce.fidelity import headline, load_measured

    return "\n".join(headline(load_measured(ROOT / "benchmarks/results/fidelity_measured")))


def fidelity_summary() -> str:
    """The count of the defaults' cells within 1.5x of the paper's, with the NRMSE accounting and the
    findings' count (README, under the headline)."""
    from neural_estimator.paper.reproduce.fidelity import load_measured, summary

    return summary(load_measured(ROOT / "benchmarks/results/fidelity_measured"))


HEADLINE = ROOT / "docs/results/headline/headline.json"


def headline_table() -> str:
    """The sealed headline (``neural-estimator headline --family sealed --out docs/results/headline``)."""
    from neural_estimator.evaluation.headline import render_headline

    return render_headline(json.loads(HEADLINE.read_text())).strip()


def headline_findings() -> str:
    """The paper's seven findings judged on the sealed headline's paired intervals
    (docs/results/headline/findings.json, written by the same command)."""
    from neural_estimator.paper.reproduce.intervals import render

    return render(json.loads((HEADLINE.parent / "findings.json").read_text())).strip()


def fidelity_measured() -> str:
    """The fidelity section measured on the default constants (scripts/fidelity_table.py)."""
    return (ROOT / "benchmarks/results/fidelity_measured/fidelity.md").read_text().strip()


def methods_table() -> str:
    """The table of methods (neural_estimator/methods/table.py): one row per method, in table order."""
    from neural_estimator.methods import table

    def yes(v: bool) -> str:
        return "yes" if v else ""

    rows = [
        "| method | name | family | needs f, h | trained | start modes | torch | seeded | context | ONNX step "
        "| members | paper row |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in table.methods(family=None):
        rows.append(
            f"| `{s.name}` | {s.display} | {s.family} | {yes(s.needs_model)} | {yes(s.trainable)} | "
            f"{yes(s.takes_init)} | {yes(s.uses_torch)} | {yes(s.seeded)} | "
            f"{s.context if s.context != 'none' else ''}{f' (`{s.window_key}`)' if s.window_key else ''} | "
            f"{yes(s.exportable)} | {f'`{s.members[0]}`' if s.members else ''} | "
            f"{'' if s.paper_row is None else s.paper_row + 1} |"
        )
    return "\n".join(rows)


def mismatch() -> str:
    """The exact model's row per scenario and the crossovers, two rows per sweep, of the committed
    sweeps (docs/results/mismatch/SCENARIO-PARAMETER.json, written by ``neural-estimator reproduce``
    or ``mismatch --experiment``): the reproduce report's tables
    (:func:`neural_estimator.evaluation.mismatch.exact_table`, ``crossover_table``)."""
    from neural_estimator.evaluation.mismatch import EXPERIMENT, crossover_table, exact_table

    paths = [ROOT / "docs/results/mismatch" / f"{s}-{p}.json" for s, ps in EXPERIMENT.items() for p in ps]
    results = [json.loads(p.read_text()) for p in paths if p.is_file()]
    return "\n".join(["At the exact model:", "", *exact_table(results), "", *crossover_table(results)])


GENERATORS = {
    "mismatch": lambda _=None: mismatch(),
    "methods": lambda _=None: methods_table(),
    "node-params": params_table,
    "cli": cli_help,
    "scoreboard": lambda _=None: scoreboard(),
    "report-section": report_section,
    "fidelity": lambda _=None: fidelity(),
    "fidelity-measured": lambda _=None: fidelity_measured(),
    "defaults-table": lambda _=None: defaults_table(),
    "fidelity-summary": lambda _=None: fidelity_summary(),
    "headline": lambda _=None: headline_table(),
    "headline-findings": lambda _=None: headline_findings(),
    "zoo": lambda _=None: zoo(),
    "zoo-instances": lambda _=None: zoo_instances(),
}


def expand(markdown: str) -> str:
    """Every marker of ``markdown`` replaced by its generated text."""

    return MARKER.sub(lambda m: generate(m.group(1), m.group(2)), markdown)


def generate(name: str, arg: str | None = None) -> str:
    """The text of generator ``name`` (with its argument where it takes one)."""
    if name not in GENERATORS:
        raise ValueError(f"unknown generator {name!r} (known: {', '.join(GENERATORS)})")
    return GENERATORS[name](arg) if arg is not None else GENERATORS[name]()


# ---- the README ---------------------------------------------------------------------------------
# the start line, the text (may be empty), the first end line after it
README_BLOCK = re.compile(r"^(<!-- generated: ([a-z-]+) -->)\n(.*?)\n?(<!-- /generated -->)$", re.M | re.S)


def readme_blocks(markdown: str) -> dict[str, str]:
    """The README's generated blocks: name -> the text between its markers."""
    return {m.group(2): m.group(3) for m in README_BLOCK.finditer(markdown)}


def update_readme(markdown: str) -> str:
    """``markdown`` with every generated block rewritten by its generator."""

    return README_BLOCK.sub(lambda m: f"{m.group(1)}\n{generate(m.group(2))}\n{m.group(4)}", markdown)


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ARG001 - MkDocs' hook signature
    return expand(markdown)
