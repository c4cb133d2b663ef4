"""The ``.npz`` dataset and estimate file format.

A dataset file holds

    x     (N, T, dx) float64   true states
    y     (N, T, dy) float64   noisy observations
    u     (N, T, du) float64   controls, u[:, k] acts from step k to k+1 (du may be 0)
    meta  0-d unicode array    JSON: scenario and every constant, seed, names, units, horizon
    labelled (N, T) bool       only where some step has no ground truth (recorded data): True where
                               x is ground truth; x holds a placeholder elsewhere, never scored;
                               every step False where meta "ground_truth" is false (a recording
                               with no state topic, whose spec names a model)

An estimate file adds

    x_hat (N, T, dx) float64   estimates (NaN/inf where a method diverged)
    P_hat (N, T, dx, dx)       optional covariances
    and ``meta["method"]`` naming the method.

Files are written deterministically (fixed zip timestamps), so the same data give the same bytes,
and read with ``allow_pickle=False``: loading a file can never run code.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator.core.atomic import replaced_atomically
from neural_estimator.data.simulate import Trajectories

_FIXED_TIME = (1980, 1, 1, 0, 0, 0)


class DataError(ValueError):
    """A dataset or estimate file that cannot be used; the message names the file and the problem."""


def save_npz(path: str | Path, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> Path:
    """Write ``arrays`` and ``meta`` (as JSON) to ``path`` byte-for-byte reproducibly."""
    path = Path(path)
    items = dict(arrays)
    items["meta"] = np.array(json.dumps(meta, sort_keys=True, allow_nan=True))
    # Written under a temporary name of this process and thread, renamed when whole: parallel jobs
    # (reproduce's Ray workers) that simulate the same cached set must not rename each other's file,
    # and a full disk or read-only directory leaves nothing under ``path`` (a WriteError says why).
    with replaced_atomically(path) as tmp:
        with open(tmp, "wb") as raw:
            with zipfile.ZipFile(raw, "w", compression=zipfile.ZIP_DEFLATED) as zf:
                for name in sorted(items):
                    buf = io.BytesIO()
                    np.lib.format.write_array(buf, np.asarray(items[name]), allow_pickle=False)
                    info = zipfile.ZipInfo(name + ".npy", date_time=_FIXED_TIME)
                    info.compress_type = zipfile.ZIP_DEFLATED
                    zf.writestr(info, buf.getvalue())
            raw.flush()
            os.fsync(raw.fileno())  # a full disk may report itself only here
    return path


def save_trajectories(path: str | Path, data: Trajectories) -> Path:
    """Write a dataset file."""
    return save_npz(path, {"x": data.x, "y": data.y, "u": data.u, **_labelled_array(data)}, data.meta)


def _labelled_array(data: Trajectories) -> dict[str, np.ndarray]:
    """{"labelled": mask} when some step is unlabelled, else {} (a fully labelled file stays as it was)."""
    if data.labelled is None or bool(np.all(data.labelled)):
        return {}
    return {"labelled": np.asarray(data.labelled, dtype=bool)}


def save_estimates(
    path: str | Path,
    data: Trajectories,
    x_hat: np.ndarray,
    method: str,
    P_hat: np.ndarray | None = None,
    extra_meta: dict[str, Any] | None = None,
) -> Path:
    """Write an estimate file: the dataset plus ``x_hat`` (and ``P_hat``) of ``method``."""
    if x_hat.shape != data.x.shape:
        raise DataError(f"{path}: x_hat has shape {x_hat.shape}, the states have {data.x.shape}")
    arrays = {"x": data.x, "y": data.y, "u": data.u, "x_hat": x_hat, **_labelled_array(data)}
    if P_hat is not None:
        arrays["P_hat"] = P_hat
    meta = dict(data.meta, method=method, **(extra_meta or {}))
    return save_npz(path, arrays, meta)


def load_npz(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a file written by :func:`save_npz`: (arrays, meta). Errors name the file and the problem."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise DataError(f"{path}: not a readable .npz file ({exc})") from None
    if "meta" not in arrays:
        raise DataError(f"{path}: missing 'meta' (not written by neural-estimator?)")
    try:
        meta = json.loads(str(arrays.pop("meta")))
    except json.JSONDecodeError as exc:
        raise DataError(f"{path}: 'meta' is not valid JSON ({exc.msg})") from None
    return arrays, meta


def load_trajectories(
    path: str | Path, *, allow_nonfinite_estimates: bool = True
) -> tuple[Trajectories, dict[str, np.ndarray]]:
    """Read and validate a dataset or estimate file.

    Returns:
        (trajectories, extras) where extras holds ``x_hat`` / ``P_hat`` when present.

    Raises:
        DataError: missing arrays, inconsistent shapes, or NaN/inf in x, y or u.
    """
    arrays, meta = load_npz(path)
    for key in ("x", "y", "u"):
        if key not in arrays:
            raise DataError(f"{path}: missing array {key!r} (has {sorted(arrays)})")
    x, y, u = (np.asarray(arrays[k], dtype=np.float64) for k in ("x", "y", "u"))
    for key, a in (("x", x), ("y", y), ("u", u)):
        if a.ndim != 3:
            raise DataError(f"{path}: {key!r} must be 3-D (N, T, dim), got shape {a.shape}")
        if a.shape[:2] != x.shape[:2]:
            raise DataError(f"{path}: {key!r} has shape {a.shape} but x has {x.shape}: N and T must agree")
        bad = ~np.isfinite(a)
        if bad.any():
            n_bad = int(bad.any(axis=(1, 2)).sum())
            raise DataError(
                f"{path}: {key!r} contains NaN or inf in {n_bad} trajectories "
                f"(first: {int(np.argmax(bad.any(axis=(1, 2))))})"
            )
    labelled = _checked_labelled(path, arrays, x.shape[:2], meta.get("ground_truth") is False)
    names = meta.get("state_names")
    if names is not None and len(names) != x.shape[2]:
        raise DataError(f"{path}: x has {x.shape[2]} state components but meta names {len(names)}")
    extras = {}
    if "x_hat" in arrays:
        xh = np.asarray(arrays["x_hat"], dtype=np.float64)
        if xh.shape != x.shape:
            raise DataError(f"{path}: x_hat has shape {xh.shape}, x has {x.shape}")
        if not allow_nonfinite_estimates and not np.all(np.isfinite(xh)):
            raise DataError(f"{path}: x_hat contains NaN or inf")
        extras["x_hat"] = xh
    if "P_hat" in arrays:
        P = np.asarray(arrays["P_hat"], dtype=np.float64)
        if P.shape != x.shape + (x.shape[2],):
            raise DataError(f"{path}: P_hat has shape {P.shape}, expected {x.shape + (x.shape[2],)}")
        extras["P_hat"] = P
    return Trajectories(x, y, u, meta, labelled), extras


def _checked_labelled(path, arrays: dict[str, np.ndarray], shape: tuple[int, int], none: bool) -> np.ndarray | None:
    """The file's ``labelled`` mask (N, T) bool, or None when absent or all True. ``none``: the meta
    says the recording has no ground truth (``ground_truth: false``), so the mask must mark no step."""
    if "labelled" not in arrays:
        if none:
            raise DataError(f"{path}: its meta says it has no ground truth, but it has no 'labelled' mask")
        return None
    m = np.asarray(arrays["labelled"])
    if m.dtype != np.bool_ or m.shape != tuple(shape):
        raise DataError(f"{path}: 'labelled' must be a ({shape[0]}, {shape[1]}) bool array, got {m.dtype} {m.shape}")
    if none:
        if m.any():
            raise DataError(f"{path}: its meta says it has no ground truth, but 'labelled' marks some steps")
        return m
    if not m.any(axis=1).all():
        raise DataError(f"{path}: 'labelled' marks no step of trajectory {int(np.argmin(m.any(axis=1)))}")
    return None if m.all() else m


def load_estimates(path: str | Path, truth: Trajectories) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """(x_hat, P_hat or None, meta) of an estimate file for ``truth``'s trajectories.

    An estimate file needs only ``x_hat`` (N, T, dx) (and optionally ``P_hat`` (N, T, dx, dx)), as a
    user's own estimator writes it; when it also carries ``x`` (the package's own estimate files),
    those states must be ``truth``'s, so that estimates of another dataset are never scored.
    """
    arrays, meta = load_npz(path)
    if "x_hat" not in arrays:
        raise DataError(f"{path}: no 'x_hat' array: not an estimate file (has {sorted(arrays)})")
    xh = np.asarray(arrays["x_hat"], dtype=np.float64)
    if xh.shape != truth.x.shape:
        raise DataError(f"{path}: x_hat has shape {xh.shape}, the truth's x has {truth.x.shape}")
    if "x" in arrays:
        x = np.asarray(arrays["x"], dtype=np.float64)
        if x.shape != truth.x.shape or not np.array_equal(x, truth.x):
            raise DataError(f"{path}: its states differ from the truth file's: estimates of another dataset")
    P = None
    if "P_hat" in arrays:
        P = np.asarray(arrays["P_hat"], dtype=np.float64)
        if P.shape != xh.shape + (xh.shape[2],):
            raise DataError(f"{path}: P_hat has shape {P.shape}, expected {xh.shape + (xh.shape[2],)}")
    return xh, P, meta


def load_truth_and_estimates(
    files: list[str | Path],
) -> tuple[Trajectories, dict[str, tuple[np.ndarray, np.ndarray | None]], tuple[int, ...]]:
    """What ``metrics`` scores: a truth (or estimate) file followed by estimate files.

    Returns (truth, {name: (x_hat, P_hat or None)}, angle_states). The first file's own ``x_hat``
    counts when it has one. Each estimate is named by its meta's ``method``, else its file stem; a
    name already taken gets ``:<stem>`` appended. Estimate files need only ``x_hat`` (see
    :func:`load_estimates`).
    """
    truth, extras = load_trajectories(files[0])
    estimates = {}
    if "x_hat" in extras:
        estimates[truth.meta.get("method", Path(files[0]).stem)] = (extras["x_hat"], extras.get("P_hat"))
    for f in files[1:]:
        x_hat, P_hat, meta = load_estimates(f, truth)  # x_hat alone is enough (your own estimator's output)
        name = meta.get("method", Path(f).stem)
        estimates[name if name not in estimates else f"{name}:{Path(f).stem}"] = (x_hat, P_hat)
    if not estimates:
        raise DataError(f"{files[0]}: no 'x_hat' array and no estimate files given")
    return truth, estimates, tuple(truth.meta.get("angle_states", ()))
