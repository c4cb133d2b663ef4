"""neural_estimator.core.runtime: the allocator settings of the entry points."""

from __future__ import annotations

import platform
import sys

from neural_estimator.core.runtime import tune_allocator


def test_tune_allocator_applies_on_glibc_and_is_idempotent():
    first = tune_allocator()
    assert tune_allocator() is first
    if sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc":
        assert first is True
    else:  # pragma: no cover - other platforms: a no-op that says so
        assert first is False
