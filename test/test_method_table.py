"""The table of methods (neural_estimator/methods/table.py) is the one place a method is named: its
specs hold together, every list of methods outside it is a query of it, and the lists the docs,
params/estimator.yaml and scripts/run_demo.sh show agree with it."""

from __future__ import annotations

import ast
import dataclasses
import re
import sys
from pathlib import Path

import pytest
import yaml

import neural_estimator
from neural_estimator.methods import interface, table
from neural_estimator.methods.interface import Estimator, EstimatorError, check_method

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = Path(neural_estimator.__file__).parent
sys.path.insert(0, str(ROOT / "docs" / "hooks"))
import generate  # noqa: E402  (docs/hooks/generate.py: the site's generated parts)

# The literal collections of method names the package may keep besides the table, by (file name,
# the name they are assigned to): both are the paper's own data, not a family or a capability.
ALLOWED = {
    # the paper's spellings -> our ids, for transcribing its LaTeX tables (layer 1, below the table)
    ("transcribe.py", "METHOD_IDS"),
    # which methods each of the paper's findings compares, per scenario (its pairs: PF/EKF, EnKF/EKF, ...)
    ("intervals.py", "NEEDED"),
}


# ---- the counter ------------------------------------------------------------------------------------
def _target(stmt: ast.stmt) -> str:
    if isinstance(stmt, ast.Assign) and isinstance(stmt.targets[0], ast.Name):
        return stmt.targets[0].id
    if isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name):
        return stmt.target.id
    return getattr(stmt, "name", f"line {stmt.lineno}")


def name_collections(source: str, names) -> list[tuple[str, int]]:
    """(the statement's name, line) of each statement of ``source`` holding a tuple, list, set or dict
    literal with two or more distinct method names among its own elements (a dict's keys or values);
    a module-level statement counts by the name it assigns, a function's by the function's name."""
    names = set(names)
    found = []
    for stmt in ast.parse(source).body:
        for node in ast.walk(stmt):
            if isinstance(node, ast.Dict):
                elts = [*node.keys, *node.values]
            elif isinstance(node, (ast.Tuple, ast.List, ast.Set)):
                elts = node.elts
            else:
                continue
            hits = {e.value for e in elts if isinstance(e, ast.Constant) and e.value in names}
            if len(hits) >= 2:
                found.append((_target(stmt), node.lineno))
                break  # one statement, one collection (a dict of tuples is one table of names)
    return found


def package_collections(names=None) -> set[tuple[str, str]]:
    """{(file name, statement)} of every literal collection of method names in the package but the table."""
    names = table.names(family=None) if names is None else names
    out = set()
    for path in sorted(PACKAGE.rglob("*.py")):
        if path == PACKAGE / "methods" / "table.py":
            continue
        out |= {(path.name, stmt) for stmt, _ in name_collections(path.read_text(), names)}
    return out


def test_the_counter_finds_a_list_of_names_in_any_of_its_forms():
    names = table.names(family=None)
    assert name_collections('X = ("ekf", "gru")', names) == [("X", 1)]
    assert name_collections('def f(m):\n    return m in {"ukf", "pf"}', names) == [("f", 2)]
    assert name_collections('D = {"ekf": 1, "mamba": 2}', names) == [("D", 1)]
    assert name_collections('L = [1, ["lstm", "gpt2"]]', names) == [("L", 1)]
    # one name, a scenario and a name, or names that are not methods are not a list of methods
    assert name_collections('A = ("ekf",)\nB = ("lorenz96", "pf")\nC = ("x", "y")\nq["pf"] / q["ekf"]', names) == []


@pytest.mark.slow  # a second or more: it imports torch, walks the package or runs a verb
def test_at_most_two_literal_collections_of_method_names_are_left_besides_the_table():
    found = package_collections()
    assert found <= ALLOWED, f"a literal collection of method names outside the table: {sorted(found - ALLOWED)}"
    assert len(found) <= 2


# ---- the specs --------------------------------------------------------------------------------------
@pytest.mark.slow  # a second or more: it imports torch, walks the package or runs a verb
def test_every_spec_holds_together():
    specs = table.methods(family=None)
    assert len({s.name for s in specs}) == len(specs) and len({s.display for s in specs}) == len(specs)
    rows = [s.paper_row for s in specs if s.paper_row is not None]
    assert sorted(rows) == list(range(len(rows)))  # the paper's rows: each once, none skipped
    for s in specs:
        assert s.name == s.name.strip().lower().replace("-", "") and s.family in table.FAMILIES
        assert not (s.trainable and s.family == "classical") and s.uses_torch == (s.family in ("neural", "hybrid"))
        factory = table.resolve(s.factory)
        assert callable(factory)
        if not s.trainable:  # the trained ones (networks, hybrids) are built by the checkpoint loader
            assert issubclass(factory, Estimator) and factory.method == s.name
        if s.members is not None:  # the option exists, and its default is the filter's own
            option, default = s.members
            hyper, field = default.rsplit(".", 1)
            assert field == option and option in table.resolve(hyper).__dataclass_fields__
            assert isinstance(table.resolve(default), int) and table.resolve(default) >= 1
        if s.architecture is not None:
            config, model = (table.resolve(r) for r in s.architecture)
            assert dataclasses.is_dataclass(config) and (
                s.window_key is None or s.window_key in config.__dataclass_fields__
            )


def test_a_spec_refuses_what_it_cannot_mean():
    base = table.spec("ekf")
    with pytest.raises(ValueError, match="family"):
        dataclasses.replace(base, family="quantum")
    with pytest.raises(ValueError, match="window_key"):
        dataclasses.replace(base, context="window")
    with pytest.raises(ValueError, match="module:attribute"):
        dataclasses.replace(base, factory="neural_estimator.filters.ekf.ExtendedKalmanFilter")


def test_queries_answer_from_the_table():
    assert interface.METHODS == table.names() and set(table.names()) == {
        s.name for s in table.TABLE if s.family != "baseline"
    }
    assert interface.CLASSICAL_METHODS + interface.NEURAL_METHODS == table.names(family=("classical", "neural"))
    assert table.names(family="baseline") == tuple(s.name for s in table.TABLE if s.family == "baseline")
    assert all(table.has(m, takes_init=True) for m in table.names(family="classical"))
    assert not any(table.has(m, takes_init=True) for m in table.names(family="neural"))
    assert table.has("pf", family="classical") and not table.has("pf", family="neural") and not table.has("nope")
    assert set(table.names(context="window")) | set(table.names(context="recurrent")) == set(
        table.names(trainable=True)
    )
    assert table.paper_methods(state_space=True) == table.names(state_space=True)
    assert list(table.paper_names()) == list(table.names(family=("classical", "neural")))
    with pytest.raises(TypeError, match="no field"):
        table.names(colour="blue")
    with pytest.raises(KeyError, match="did you mean"):
        table.spec("ekff")
    with pytest.raises(EstimatorError, match="choose one of: " + ", ".join(table.names())):
        check_method("kalman")


def test_the_members_of_a_stream_come_from_the_spec():
    from neural_estimator.filters.enkf import EnKFHyperParams
    from neural_estimator.filters.pf import PFHyperParams
    from neural_estimator.core.options import parse_value

    assert table.members_per_stream("pf", {}, parse_value) == PFHyperParams.n_particles
    assert table.members_per_stream("enkf", None, parse_value) == EnKFHyperParams.n_members
    assert table.members_per_stream("pf", {"n_particles": "64"}, parse_value) == 64
    assert table.members_per_stream("ekf", {}, parse_value) is None


@pytest.mark.slow  # a second or more: it imports torch, walks the package or runs a verb
def test_the_registry_imports_a_factory_only_when_it_builds_it():
    """The table names factories as text: the registry imports no filter, and building an EKF no torch
    (a fresh interpreter)."""
    import subprocess

    code = (
        "import sys; from neural_estimator.methods.registry import make_estimator;"
        "assert 'neural_estimator.filters' not in sys.modules;"
        "from neural_estimator.scenarios import make_scenario;"
        "make_estimator('ekf', make_scenario('ballistic'));"
        "assert 'torch' not in sys.modules and 'neural_estimator.serving' not in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


# ---- the lists shown to people ---------------------------------------------------------------------
def demo_methods() -> str:
    """What scripts/run_demo.sh passes as --methods when none is given: the table's module run as a
    script (checked to be what the script calls), answered in-process."""
    text = (ROOT / "scripts" / "run_demo.sh").read_text()
    (line,) = [ln for ln in text.splitlines() if ln.startswith("has --methods ||")]
    assert '-m neural_estimator.methods.table)"' in line, line
    return ",".join(table.names())


def params_file_methods() -> list[str]:
    """The methods params/estimator.yaml's ``method`` comment lists."""
    text = (ROOT / "params" / "estimator.yaml").read_text()
    (comment,) = re.findall(r"^ {4}method:.*#\s*estimation method: one of (.*?)\s*$", text, re.M)
    return comment.split(", ")


def node_help_methods() -> list[str]:
    """The methods the estimator node's ``method`` help lists, evaluated from the source now."""
    (method,) = [p for p in generate.node_params("estimator") if p["name"] == "method"]
    return method["help"].split("one of ", 1)[1].split(", ")


def documented_methods() -> list[str]:
    """The methods of the generated table on docs/methods.md."""
    assert "<!-- generate: methods -->" in (ROOT / "docs" / "methods.md").read_text()
    return re.findall(r"^\| `([a-z0-9_]+)` \|", generate.methods_table(), re.M)


def test_the_lists_people_read_agree_with_the_table():
    assert demo_methods() == ",".join(table.names())
    assert params_file_methods() == list(table.names()) == node_help_methods()
    assert documented_methods() == list(table.names(family=None))


def test_the_readme_names_the_papers_filters_and_networks():
    text = (ROOT / "README.md").read_text()
    intro = " ".join(text.split("\n\n")[1].split())
    words = {4: "four", 6: "six"}
    filters, networks = table.paper_methods(family="classical"), table.paper_methods(family="neural")
    assert f"{words[len(filters)]} classical filters ({', '.join(map(table.label, filters))})" in intro
    assert f"{words[len(networks)]} neural estimators" in intro
    for m in networks:
        assert table.label(m) in intro, m


def test_the_table_module_prints_the_names(capsys):
    assert table.main([]) == 0 and capsys.readouterr().out.strip() == ",".join(table.names())
    assert table.main(["baseline"]) == 0 and capsys.readouterr().out.strip() == ",".join(table.names(family="baseline"))


def test_the_params_file_is_valid_yaml_with_a_method():
    doc = yaml.safe_load((ROOT / "params" / "estimator.yaml").read_text())
    (params,) = [v["ros__parameters"] for v in doc.values()]
    assert params["method"] in table.names()
