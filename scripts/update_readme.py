"""Rewrite the README's generated blocks from the committed results.

    python scripts/update_readme.py           # rewrite README.md in place
    python scripts/update_readme.py --check   # exit 1, naming the stale blocks, if any differs

Each block sits between ``<!-- generated: NAME -->`` and ``<!-- /generated -->`` lines, and NAME is
one of the documentation site's generators (docs/hooks/generate.py): ``headline`` (the sealed
headline, docs/results/headline/headline.json, from ``neural-estimator headline --family sealed``)
and ``fidelity-summary`` (from ``scripts/fidelity_table.py``'s measurement). Run it after either.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _hooks():
    spec = importlib.util.spec_from_file_location("generate", ROOT / "docs" / "hooks" / "generate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--check", action="store_true", help="change nothing; exit 1 if a block is stale")
    p.add_argument("--readme", default=str(ROOT / "README.md"), help="the file to rewrite (default: the README)")
    a = p.parse_args(argv)
    hooks, path = _hooks(), Path(a.readme)
    text = path.read_text()
    try:
        updated = hooks.update_readme(text)
    except (ValueError, FileNotFoundError) as e:
        print(f"update_readme.py: {e}", file=sys.stderr)
        return 2
    old, new = hooks.readme_blocks(text), hooks.readme_blocks(updated)
    stale = [name for name in new if old[name] != new[name]]
    if a.check:
        if stale:
            print(f"update_readme.py: stale in {path.name}: {', '.join(stale)} (run python scripts/update_readme.py)")
        return 1 if stale else 0
    path.write_text(updated)
    print(f"{path.name}: {', '.join(stale) or 'nothing'} rewritten ({len(new)} generated blocks)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
