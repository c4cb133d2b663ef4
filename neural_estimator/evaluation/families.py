"""The two seed families of the evaluation sets: one for development, one sealed.

A figure that decisions were tuned against is no longer a fresh measurement. So every seed of the
evaluation sets belongs to one of two families:

- **development** (``DEVELOPMENT``): every seed below :data:`SEALED_FLOOR`, among them 0 (the
  default of ``evaluate``) and 777 (the fidelity table's). Development, calibration, selection and
  every experiment use these, as often as they like.
- **sealed** (``SEALED``): every seed from :data:`SEALED_FLOOR` on. The README and docs headline is
  measured on :data:`SEALED_SEED` once, at the end, by ``neural-estimator headline --family
  sealed``; nothing else may read it: :func:`~neural_estimator.evaluation.protocol.evaluate`
  refuses a sealed seed unless the headline asks for it (``sealed=True``), and
  ``test/test_families.py`` checks that no other file names the sealed seed.
"""

from __future__ import annotations

DEVELOPMENT = "development"
SEALED = "sealed"
FAMILIES = (DEVELOPMENT, SEALED)
SEALED_FLOOR = 1 << 40  # every evaluation seed from here on is sealed
SEALED_SEED = SEALED_FLOOR + 40  # the one seed the headline measures the sealed family on
DEVELOPMENT_SEED = 777  # the headline's development run (the fidelity table's fresh seed)


def family_of(seed: int) -> str:
    """The family a seed of the evaluation sets belongs to."""
    return SEALED if int(seed) >= SEALED_FLOOR else DEVELOPMENT


def family_seed(family: str) -> int:
    """The seed the headline measures a family on; a one-line ValueError for an unknown family."""
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {', '.join(FAMILIES)}; got {family!r}")
    return SEALED_SEED if family == SEALED else DEVELOPMENT_SEED


def check_unsealed(seed: int, sealed: bool = False) -> int:
    """``seed`` if it is a development seed (or ``sealed`` is asked for); else a one-line ValueError:
    the sealed family is measured once, by the headline command, and read by nothing else."""
    if family_of(seed) == SEALED and not sealed:
        raise ValueError(
            f"seed {seed} is in the sealed evaluation family (seeds >= {SEALED_FLOOR}), measured once by "
            "`neural-estimator headline --family sealed`; develop on a seed below it"
        )
    return int(seed)
