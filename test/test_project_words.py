"""Tracked code and docs speak about the product, not about how it was built: no "session N",
"issue N" or "wave N" (JSON data, such as the shipped models' cards, records history and is left
out), and nothing points outside the repository or at one machine's paths."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BUILD_WORDS = re.compile(r"\b(sessions?|issues?|waves?)[\s#-]*\d+", re.I)
OUTSIDE = re.compile(r"\.\./shared/|/work/(main|wt|exp|shared|notes)\b")
TEXT_SUFFIXES = {".py", ".md", ".sh", ".yaml", ".yml", ".txt", ".cfg", ".toml", ".xml", ".launch", ""}


def _tracked_text_files() -> list[Path]:
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True)
    if out.returncode != 0:
        pytest.skip("not a git checkout")
    files = []
    for name in out.stdout.splitlines():
        path = ROOT / name
        if path.suffix in TEXT_SUFFIXES and path.is_file() and path.stat().st_size < 2_000_000:
            files.append(path)
    return files


def _hits(pattern: re.Pattern) -> list[str]:
    hits = []
    for path in _tracked_text_files():
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            continue
        for n, line in enumerate(text.splitlines(), 1):
            if pattern.search(line) and path != Path(__file__).resolve():
                hits.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()[:100]}")
    return hits


def test_no_words_about_how_the_project_was_built():
    hits = _hits(BUILD_WORDS)
    assert not hits, "words about how the project was built:\n" + "\n".join(hits)


def test_no_paths_outside_the_repository():
    # docs/results/ holds generated reports, which record where their run kept its cache
    hits = [h for h in _hits(OUTSIDE) if not h.startswith("docs/results/")]
    assert not hits, "paths outside the repository or of one machine:\n" + "\n".join(hits)
