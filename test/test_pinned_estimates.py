"""Estimates are bit-identical to those of the code before the issue #14 restructuring.

The pin file holds the four filters' and three freshly initialised neural estimators' outputs on
small stored inputs (see ``test/data/pinned_estimates.py``); any change to the arithmetic, the
order of operations or the random streams shows here as an exact mismatch.
"""

import importlib.util

import numpy as np
import pytest

from conftest import ROOT

_spec = importlib.util.spec_from_file_location("pinned_estimates", ROOT / "test" / "data" / "pinned_estimates.py")
PIN = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(PIN)


@pytest.fixture(scope="module")
def pinned():
    with np.load(PIN.PIN_FILE) as f:
        return {k: f[k] for k in f.files}


def test_estimates_equal_the_pinned_ones_bit_for_bit(pinned):
    now = PIN.compute(pinned)
    expected = {k: v for k, v in pinned.items() if k.count("/") == 2}
    assert sorted(now) == sorted(expected)
    for key, value in expected.items():
        np.testing.assert_array_equal(now[key], value, err_msg=key, strict=True)


def test_the_pin_covers_every_filter_the_covariances_and_a_skipped_observation(pinned):
    assert all(f"ballistic/{m}/cov" in pinned for m in PIN.FILTERS)
    assert "bearings/filterformer/cov" in pinned
    assert np.isnan(pinned["ballistic/Y"][1, 5]).all()
