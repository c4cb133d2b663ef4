"""The README and the documentation site stay true: their commands parse with the real parsers,
their node parameters exist, their tables come from committed files, their links and figures point
at committed files, and the params files agree with the node parameter dataclasses."""

from __future__ import annotations

import importlib.util
import re
import shlex
import subprocess
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
PAGES = {p: p.read_text() for p in sorted((ROOT / "docs").glob("*.md"))}
DOCUMENTS = {ROOT / "README.md": README, **PAGES}


def _hooks():
    spec = importlib.util.spec_from_file_location("docs_generate", ROOT / "docs" / "hooks" / "generate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


GENERATE = _hooks()


def _tracked() -> set[str]:
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True)
    if out.returncode != 0:
        pytest.skip("not a git checkout")
    return set(out.stdout.splitlines())


def _code_blocks(text: str) -> list[str]:
    """The shell code blocks (fenced ```bash, ```sh or bare ```), indented ones included."""
    blocks, current, lang = [], None, ""
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("```"):
            if current is None:
                current, lang = [], stripped[3:].strip()
            else:
                if lang in ("", "bash", "sh"):
                    blocks.append("\n".join(current) + "\n")
                current = None
        elif current is not None:
            current.append(stripped)
    return blocks


def _command_lines(text: str, program: str) -> list[str]:
    """Shell command lines starting with ``program`` in the fenced code blocks (continuations joined,
    comments dropped)."""
    found = []
    for block in _code_blocks(text):
        block = block.replace("\\\n", " ")
        for line in block.splitlines():
            line = line.split("   #")[0].split("  #")[0].strip()
            if line.startswith(program + " "):
                found.append(line)
    return found


# ---- the README -------------------------------------------------------------------------------------
def test_readme_is_a_front_page():
    lines = README.splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines"
    for heading in ("## Install", "## Quick start", "## Read more"):
        assert heading in README
    assert "[ros]" in README and "colcon build" in README  # the extra the nodes need, and the workspace


def test_readme_generated_blocks_come_from_the_committed_measurements():
    """The README's first table is the sealed headline (docs/results/headline), followed by the count of
    the paper's cells it matches (benchmarks/results/fidelity_measured); each block equals what its
    generator makes of the committed results now (else: python scripts/update_readme.py)."""
    blocks = GENERATE.readme_blocks(README)
    assert list(blocks)[:2] == ["headline", "fidelity-summary"], list(blocks)
    assert README.index("<!-- generated: headline -->") < README.index("| ")  # the first table
    for name, text in blocks.items():
        assert text == GENERATE.GENERATORS[name](), f"README block {name!r} is stale: python scripts/update_readme.py"
    assert "sealed evaluation family" in blocks["headline"]
    assert "of the 49 measured cells are within 1.5x" in blocks["fidelity-summary"]


def test_update_readme_rewrites_a_stale_block_and_check_names_it(tmp_path, capsys):
    import runpy

    script = runpy.run_path(str(ROOT / "scripts" / "update_readme.py"))
    readme = tmp_path / "README.md"
    stale = README.replace(GENERATE.fidelity_summary(), "**0 of the 49 measured cells** (stale)")
    assert stale != README
    readme.write_text(stale)
    assert script["main"](["--check", "--readme", str(readme)]) == 1
    assert "stale in README.md: fidelity-summary" in capsys.readouterr().out
    assert readme.read_text() == stale  # --check writes nothing
    assert script["main"](["--readme", str(readme)]) == 0
    assert readme.read_text() == README
    assert script["main"](["--check", "--readme", str(readme)]) == 0
    # empty blocks are filled, and the text between two blocks stays
    end = "<!-- /generated -->\n"
    readme.write_text(f"<!-- generated: headline -->\n{end}prose\n<!-- generated: fidelity-summary -->\n{end}")
    assert script["main"](["--readme", str(readme)]) == 0
    assert GENERATE.readme_blocks(readme.read_text()) == {
        "headline": GENERATE.headline_table(),
        "fidelity-summary": GENERATE.fidelity_summary(),
    }
    assert "\n<!-- /generated -->\nprose\n<!-- generated: fidelity-summary -->\n" in readme.read_text()
    readme.write_text("<!-- generated: nosuch -->\nx\n<!-- /generated -->\n")
    assert script["main"](["--readme", str(readme)]) == 2
    assert "unknown generator 'nosuch'" in capsys.readouterr().err


def test_readme_and_docs_name_every_cli_verb():
    from neural_estimator.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    for verb in sub.choices:
        assert f"neural-estimator {verb}" in README, f"verb {verb!r} is not in the README's table"
        assert f"<!-- generate: cli {verb} -->" in PAGES[ROOT / "docs" / "cli.md"], verb


# ---- commands ---------------------------------------------------------------------------------------
def _parse_cli(line: str) -> None:
    from neural_estimator.cli import build_parser
    from neural_estimator.core.arguments import OneLineParser
    from neural_estimator.nodes.launch import build_parser as live_parser

    argv = shlex.split(line)[1:]
    argv = [a for a in argv if a != "..."]
    if argv[:1] == ["ros2"]:
        return
    parser = live_parser() if argv[:1] == ["live"] else build_parser()
    assert isinstance(parser, OneLineParser)
    parser.parse_args(argv[1:] if argv[:1] == ["live"] else argv)


@pytest.mark.parametrize("path", sorted(DOCUMENTS), ids=lambda p: p.name)
def test_every_documented_command_line_parses(path):
    """Each `neural-estimator ...` line of a code block parses with the real parser (a renamed or
    removed flag fails here), and each `ros2 run neural_estimator NODE --ros-args -p k:=v` names a
    node and its parameters."""
    text = DOCUMENTS[path]
    for line in _command_lines(text, "neural-estimator"):
        if "[" in line or "|" in line or "<" in line:  # a synopsis, not a command
            continue
        try:
            _parse_cli(line)
        except SystemExit as exc:
            raise AssertionError(f"{path.name}: does not parse: {line}") from exc
    for line in _command_lines(text, "ros2") + _command_lines(text, "neural-estimator"):
        words = shlex.split(line)
        if "run" not in words or "neural_estimator" not in words:
            continue
        node = words[words.index("neural_estimator") + 1]
        if node == "neural-estimator":
            continue
        node = GENERATE.NODE_ALIASES.get(node, node)
        assert node in GENERATE.NODE_PARAMS, f"{path.name}: no node {node!r}: {line}"
        known = {p["name"] for p in GENERATE.node_params(node)} | {"use_sim_time"}
        for i, w in enumerate(words):
            if w == "-p":
                name = words[i + 1].split(":=")[0]
                assert name in known, f"{path.name}: {node} has no parameter {name!r}: {line}"


# ---- links and figures --------------------------------------------------------------------------------
def test_readme_links_point_at_committed_files():
    tracked = _tracked()
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", README):
        if target.startswith(("http://", "https://", "mailto:")):
            continue
        assert target in tracked, f"README.md links to {target}, which is not a committed file"


def test_every_figure_of_the_site_is_a_committed_file():
    tracked = _tracked()
    for path, text in PAGES.items():
        text = GENERATE.expand(text)
        for target in re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", text):
            rel = (path.parent / target).resolve().relative_to(ROOT).as_posix()
            assert rel in tracked, f"{path.name}: figure {target} is not a committed file"
            assert rel.startswith("docs/"), f"{path.name}: figure {target} is outside docs/"


def test_results_tables_are_generated_not_typed():
    """The results page holds markers only where its tables are; the generated tables carry the
    numbers of the committed files."""
    import json

    text = PAGES[ROOT / "docs" / "results.md"]
    assert "<!-- generate: scoreboard -->" in text and "<!-- generate: report-section Main accuracy -->" in text
    board = json.loads((ROOT / "docs/results/neural_scoreboard.json").read_text())
    table = GENERATE.scoreboard()
    for scenario, models in board.items():
        for model, cell in models.items():
            assert f"{cell['rmse']:.4g} ± " in table, (scenario, model)
    assert not re.search(r"^\| (ekf|ukf|gru|mamba) \|", text, re.M), "a results table typed into results.md"


# ---- node parameters ----------------------------------------------------------------------------------
@pytest.mark.parametrize("node", sorted(GENERATE.NODE_PARAMS))
def test_params_file_agrees_with_the_node_dataclass(node):
    """params/NODE.yaml lists exactly the dataclass's parameters, with its defaults and its help as
    each line's comment; the generated table (read from the source) equals the imported dataclass."""
    pytest.importorskip("rclpy")
    import dataclasses
    import importlib

    fields = {}
    for path, cls in GENERATE.NODE_PARAMS[node]:
        module = importlib.import_module(path[:-3].replace("/", "."))
        fields |= {f.name: f for f in dataclasses.fields(getattr(module, cls))}
    doc = yaml.safe_load((ROOT / "params" / f"{node}.yaml").read_text())
    (params,) = [v["ros__parameters"] for v in doc.values()]
    assert list(params) == list(fields), f"params/{node}.yaml: names or order differ from {cls}"
    for name, value in params.items():
        default = fields[name].default
        want = list(default) if isinstance(default, tuple) else default
        assert value == want or (isinstance(want, float) and value == pytest.approx(want)), (node, name, value, want)
    comments = dict(
        re.findall(r"^ {4}(\w+):[^#\n]*#\s*(.*?)\s*$", (ROOT / "params" / f"{node}.yaml").read_text(), re.M)
    )
    for name, field in fields.items():  # the comment is the dataclass's help, word for word: one source
        assert comments.get(name) == field.metadata["help"].strip(), f"params/{node}.yaml: {name}'s comment"
    generated = GENERATE.node_params(node)
    assert [p["name"] for p in generated] == list(fields)
    for p in generated:
        default = fields[p["name"]].default
        assert p["default"] == default and p["help"] == fields[p["name"]].metadata["help"], p


def test_every_node_has_a_generated_parameter_table():
    text = PAGES[ROOT / "docs" / "nodes.md"]
    for node in GENERATE.NODE_PARAMS:
        assert f"<!-- generate: node-params {node} -->" in text, node
