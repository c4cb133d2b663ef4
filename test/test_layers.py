"""Imports point downwards only, and module-level imports form no cycle, by the layers of the package
docstring (neural_estimator/__init__.py)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

import neural_estimator

PACKAGE = Path(neural_estimator.__file__).parent


# The top level of the package: at most 16 entries, files and folders alike.
TOP_LEVEL = {
    "core", "metrics", "paper", "scenarios", "data", "methods", "filters", "models",
    "serving", "stream", "bags", "training", "evaluation", "robot", "cli", "nodes",
}  # fmt: skip


def layers() -> dict[str, int]:
    """{name: layer number} from the numbered list in the package docstring (the ``names`` in lower
    case on each numbered item, its indented continuation lines included). A name is a top-level
    module or package, or a dotted path below one (``serving.uncertainty``) placed on its own floor."""
    out = {}
    text = re.sub(r"\n {3}(?=\S)", " ", neural_estimator.__doc__)  # an item's indented continuation lines
    for line in text.splitlines():
        m = re.match(r"(\d+)\. (.*)", line.strip())
        if m:
            for name in re.findall(r"``([a-z_0-9]+(?:\.[a-z_0-9]+)*)``", m.group(2)):
                out[name] = int(m.group(1))
    return out


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> list[tuple[str, bool]]:
    """(imported neural_estimator module, at module level?) of one file; ``from neural_estimator
    import x`` counts as importing ``neural_estimator.x`` when x is a module."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    top |= {id(c) for n in tree.body if isinstance(n, (ast.If, ast.Try)) for c in ast.walk(n)}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, id(node) in top) for a in node.names if a.name.startswith("neural_estimator")]
        elif (
            isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("neural_estimator")
        ):
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                is_module = (PACKAGE.parent / Path(*sub.split("."))).with_suffix(".py").exists() or (
                    PACKAGE.parent / Path(*sub.split("."))
                ).is_dir()
                found.append((sub if is_module else node.module, id(node) in top))
    return found


def layer_of(module: str, table: dict[str, int]) -> int:
    """The layer of ``neural_estimator.<module>``: that of the longest dotted entry of the table it
    starts with (``paper.reproduce.plan`` is on ``paper.reproduce``'s floor, ``paper.transcribe`` on
    ``paper``'s)."""
    parts = module.split(".")
    if len(parts) == 1:
        return 1  # the package itself holds only __version__
    for end in range(len(parts), 1, -1):
        if ".".join(parts[1:end]) in table:
            return table[".".join(parts[1:end])]
    raise AssertionError(f"{module}: the package docstring does not place '{parts[1]}' in a layer")


def top_level_entries() -> set[str]:
    """The files and folders at the top of the package, ``__init__.py`` and ``__pycache__`` aside."""
    return {p.stem if p.suffix == ".py" else p.name for p in PACKAGE.iterdir()} - {"__init__", "__pycache__"}


def test_a_dotted_entry_places_its_subtree_by_the_longest_prefix():
    table = {"paper": 1, "paper.reproduce": 9, "cli": 10}
    assert layer_of("neural_estimator.paper.reproduce.plan", table) == 9
    assert layer_of("neural_estimator.paper.reproduce", table) == 9
    assert layer_of("neural_estimator.paper.transcribe", table) == 1
    assert layer_of("neural_estimator.paper.reproducer", table) == 1  # whole names, not prefixes of text
    assert layer_of("neural_estimator", table) == 1
    with pytest.raises(AssertionError, match="does not place 'papers'"):
        layer_of("neural_estimator.papers.x", table)


def test_every_dotted_entry_names_a_part_of_the_package():
    for name in layers():
        path = PACKAGE.joinpath(*name.split("."))
        assert path.with_suffix(".py").is_file() or (path / "__init__.py").is_file(), (
            f"the package docstring places '{name}', which is no module or package of neural_estimator"
        )


def test_at_most_16_entries_at_the_top_of_the_package():
    entries = top_level_entries()
    assert entries <= TOP_LEVEL, f"not in the agreed top level: {sorted(entries - TOP_LEVEL)}"
    assert len(entries) <= 16


def test_every_part_of_the_package_has_a_layer():
    table = layers()
    assert set(table.values()) == set(range(1, 11)), "every one of the ten layers names something"
    for path in PACKAGE.iterdir():
        name = path.stem if path.suffix == ".py" else path.name
        if (path.suffix == ".py" and name != "__init__") or (path.is_dir() and (path / "__init__.py").exists()):
            assert name in table, f"neural_estimator.{name} is in no layer of the package docstring"


def test_imports_point_downwards_only():
    table = layers()
    upward = []
    for path in sorted(PACKAGE.rglob("*.py")):
        here = module_name(path)
        for target, _ in imports(path):
            if layer_of(target, table) > layer_of(here, table):
                upward.append(
                    f"{here} (layer {layer_of(here, table)}) imports {target} (layer {layer_of(target, table)})"
                )
    assert not upward, "upward imports:\n" + "\n".join(upward)


def test_module_level_imports_form_no_cycle():
    graph: dict[str, set[str]] = {}
    modules = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    for name, path in modules.items():
        graph[name] = {t for t, top in imports(path) if top and t in modules and t != name}
    # a package's __init__ importing its own submodules is how packages work, not a cycle
    for name in graph:
        graph[name] = {
            t for t in graph[name] if not (t.startswith(name + ".") and (modules[name].name == "__init__.py"))
        }
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                cycle = stack[stack.index(m) :] + [m]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if m not in state:
                visit(m)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n)


def test_the_architecture_page_lists_the_layers_of_the_docstring():
    """docs/architecture.md's layer table names, layer by layer, what the package docstring names."""
    page = (PACKAGE.parent / "docs" / "architecture.md").read_text()
    documented = {}
    for m in re.finditer(r"^\| (\d+) \| ([^|]+) \|", page, flags=re.M):
        for name in re.findall(r"`([a-z_0-9.]+)`", m.group(2)):
            documented[name] = int(m.group(1))
    assert documented == layers()
