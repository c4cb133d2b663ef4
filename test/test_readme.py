"""The README stays true: every node parameter and every CLI verb it should list is there."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def test_every_node_parameter_is_in_the_readme():
    """In the README's tables or a docs page's (docs/*.md)."""
    docs = README + "".join(p.read_text() for p in sorted((ROOT / "docs").glob("*.md")))
    for yaml in sorted((ROOT / "params").glob("*.yaml")):
        for key in re.findall(r"^\s{4}(\w+):", yaml.read_text(), re.M):
            assert f"| `{key}` |" in docs, f"{yaml.name}: parameter {key!r} is not documented in README.md or docs/"


def test_every_cli_verb_is_in_the_readme():
    from neural_estimator.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    for verb in sub.choices:
        assert f"neural-estimator {verb}" in README, f"verb {verb!r} is not documented in README.md"
