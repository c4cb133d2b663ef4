"""The package stays readable: modules of one job at most 600 lines, functions of at most 100 lines of
code and at most 100 lines with their signature and docstring (a function that long is split into
named steps; the maths beside the equations is wanted, so a long docstring leaves less room for code,
not more), and no import cycle at all, counting the imports inside functions too
(test_layers.py holds the layers and the module-level imports)."""

from __future__ import annotations

import ast
from pathlib import Path

from test_layers import PACKAGE, imports, module_name

MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 100
# Modules allowed over the limit, each with the reason and the way out (none today).
OVERSIZED: set[str] = set()


def _modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if "zoo" not in p.relative_to(PACKAGE).parts)


def function_lengths(path: Path) -> list[tuple[str, int, int]]:
    """(name, first line, lines of code after the docstring) of every function and method in ``path``."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if len(body) > 1 and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                body = body[1:]
            out.append((node.name, node.lineno, node.end_lineno - body[0].lineno + 1))
    return out


def test_no_module_is_over_600_lines():
    long = []
    for path in _modules():
        rel = path.relative_to(PACKAGE).as_posix()
        n = len(path.read_text().splitlines())
        if n > MAX_MODULE_LINES and rel not in OVERSIZED:
            long.append(f"neural_estimator/{rel}: {n} lines")
    assert not long, f"modules over {MAX_MODULE_LINES} lines (split them by job):\n" + "\n".join(long)


def test_the_oversized_list_is_not_stale():
    for rel in OVERSIZED:
        path = PACKAGE / rel
        assert path.is_file() and len(path.read_text().splitlines()) > MAX_MODULE_LINES, (
            f"{rel}: drop it from OVERSIZED"
        )


def test_no_function_is_over_100_lines_of_code():
    long = [
        f"{path.relative_to(PACKAGE.parent)}:{line} {name}: {n} lines"
        for path in _modules()
        for name, line, n in function_lengths(path)
        if n > MAX_FUNCTION_LINES
    ]
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines of code:\n" + "\n".join(long)


def whole_lengths(path: Path) -> list[tuple[str, int, int]]:
    """(name, first line, lines from ``def`` to the last line, signature and docstring included) of
    every function and method in ``path``."""
    return [
        (node.name, node.lineno, node.end_lineno - node.lineno + 1)
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
    ]


def test_no_function_is_over_100_lines_with_its_docstring():
    long = [
        f"{path.relative_to(PACKAGE.parent)}:{line} {name}: {n} lines"
        for path in _modules()
        for name, line, n in whole_lengths(path)
        if n > MAX_FUNCTION_LINES
    ]
    assert not long, (
        f"functions over {MAX_FUNCTION_LINES} lines, docstring included (split them into named steps):\n"
        + "\n".join(long)
    )


def test_whole_lengths_count_the_signature_and_the_docstring(tmp_path):
    f = tmp_path / "m.py"
    body = "\n".join(f"    a{i} = {i}" for i in range(96))
    f.write_text(f'def f(\n    x,\n):\n    """doc\n    """\n{body}\n\n\nasync def g():\n    pass\n')
    assert whole_lengths(f) == [("f", 1, 101), ("g", 104, 2)]
    assert function_lengths(f)[0] == ("f", 1, 96)  # the code-only count would let f pass


def test_function_lengths_count_code_not_the_docstring(tmp_path):
    f = tmp_path / "m.py"
    f.write_text('def f():\n    """doc\n\n    more doc\n    """\n    a = 1\n    return a\n\n\ndef g():\n    pass\n')
    assert function_lengths(f) == [("f", 1, 2), ("g", 10, 1)]


def import_graph() -> dict[str, set[str]]:
    """{module: the package modules it imports, at module level or inside a function}; a package's
    ``__init__`` importing its own submodules is how packages work, and is left out."""
    modules = {module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph = {}
    for name, path in modules.items():
        targets = {t for t, _ in imports(path) if t in modules and t != name}
        if path.name == "__init__.py":
            targets = {t for t in targets if not t.startswith(name + ".")}
        graph[name] = targets
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycle_even_inside_functions():
    assert not cycles(import_graph()), "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles(import_graph()))


def test_the_cycle_finder_finds_a_forwarder():
    # the shape the bags reader and directory once had: a function-level import back
    graph = {"a": {"b"}, "b": {"a"}, "c": {"a"}}
    assert cycles(graph) == [["a", "b"]]


def test_no_module_imports_its_own_package():
    """A module of a package importing the package's ``__init__`` (which imports the module) is a
    cycle waiting for its first module-level use."""
    wrong = []
    for path in PACKAGE.rglob("*.py"):
        name = module_name(path)
        if path.name != "__init__.py":
            wrong += [f"{name} imports {t}" for t, _ in imports(path) if name.startswith(t + ".") and "." in t]
    assert not wrong, "\n".join(wrong)
