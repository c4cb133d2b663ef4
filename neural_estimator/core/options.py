"""One grammar for option values written as text, typed by the field they set.

Scenario constants (``--set``, the nodes' ``set``), filter hyperparameters (``--option``, the nodes'
``options``), neural estimator options and node parameters all arrive as text at some point; each
is parsed here, against the type of the dataclass field (its default, or its annotation where the
default is None), so that the same word means the same thing everywhere:

    bool     true / false, yes / no, on / off, 1 / 0 (any case)
    int      an integer (``3``, ``3.0``, ``1e3``); a bool is not an int
    float    a number (``0.5``, ``1e-3``, ``inf``)
    str      the text itself
    tuple    a JSON list (``[1, 2.5]``, nested for matrices) or comma-separated text (``a,b``), each
             element like the default's elements; a default of a given shape requires that shape
    None     ``none`` or ``null`` where the field may be None (``float | None``)

Values that already have the right type pass through. A value that does not fit is an
:class:`OptionError` naming the option and what it must be, in one line.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

TRUE = ("true", "yes", "on", "1")
FALSE = ("false", "no", "off", "0")
NONE = ("none", "null")


class OptionError(ValueError):
    """An option value that does not fit its field; the message names the option."""


def did_you_mean(word: str, choices: Any) -> str:
    """``" (did you mean 'ukf'?)"`` for the closest of ``choices`` to a mistyped ``word``, or ``""``
    when none is close (difflib's ratio of at least 0.6), for one-line errors on unknown names."""
    import difflib

    close = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def parse_bool(value: Any, name: str = "option") -> bool:
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)) and int(value) in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in TRUE + FALSE:
        return value.strip().lower() in TRUE
    raise OptionError(f"{name} must be true or false (also yes/no, on/off, 1/0), got {value!r}")


def parse_value(value: Any, like: Any, name: str = "option", optional: bool = False) -> Any:
    """``value`` converted to the type of ``like`` (a field's default); see the module docstring.

    Args:
        optional: the field may be None (then ``none``/``null`` and None are accepted).
    """
    if value is None or (isinstance(value, str) and value.strip().lower() in NONE):
        if optional or like is None:
            return None
        raise OptionError(f"{name} must be {_describe(like)}, got {value!r}")
    if isinstance(like, bool):
        return parse_bool(value, name)
    if isinstance(like, int):
        return _parse_int(value, name)
    if isinstance(like, float):
        return _parse_float(value, name)
    if isinstance(like, str):
        if not isinstance(value, str):
            raise OptionError(f"{name} must be a string, got {value!r}")
        return value
    if isinstance(like, tuple):
        return _parse_tuple(value, like, name)
    if like is None:  # an optional field without a typed default: the text's JSON value, else the text
        if isinstance(value, str):
            try:
                return json.loads(value)
            except json.JSONDecodeError:
                return value
        return value
    return value


def _parse_int(value: Any, name: str) -> int:
    if isinstance(value, (bool, np.bool_)):
        raise OptionError(f"{name} must be an integer, got {value!r}")
    try:
        f = float(value.strip()) if isinstance(value, str) else float(value)
    except (TypeError, ValueError):
        raise OptionError(f"{name} must be an integer, got {value!r}") from None
    if not math.isfinite(f) or f != int(f):
        raise OptionError(f"{name} must be an integer, got {value!r}")
    return int(f)


def _parse_float(value: Any, name: str) -> float:
    if isinstance(value, (bool, np.bool_)):
        raise OptionError(f"{name} must be a number, got {value!r}")
    try:
        return float(value.strip()) if isinstance(value, str) else float(value)
    except (TypeError, ValueError):
        raise OptionError(f"{name} must be a number, got {value!r}") from None


def _parse_tuple(value: Any, like: tuple, name: str) -> tuple:
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):
            try:
                value = json.loads(text)
            except json.JSONDecodeError as exc:
                raise OptionError(f"{name}: cannot parse {value!r} as a list ({exc.msg})") from None
        else:
            value = [v.strip() for v in text.split(",") if v.strip()]
    if not isinstance(value, (list, tuple, np.ndarray)):
        value = [value]
    of_text = like if like else value  # the default's elements say the type; an empty default, the value's
    if all(isinstance(v, str) for v in of_text):
        return tuple(str(v) for v in value)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise OptionError(f"{name} must be numbers like {like!r}, got {value!r}") from None
    if like and arr.shape != np.asarray(like).shape:
        raise OptionError(f"{name} must have the shape of {like!r} ({np.asarray(like).shape}), got {value!r}")
    return _to_tuple(arr)


def _to_tuple(arr: np.ndarray) -> Any:
    return tuple(_to_tuple(a) for a in arr) if arr.ndim else float(arr)


def _describe(like: Any) -> str:
    if isinstance(like, bool):
        return "true or false"
    if isinstance(like, int):
        return "an integer"
    if isinstance(like, float):
        return "a number"
    if isinstance(like, str):
        return "a string"
    return f"like {like!r}"


def is_optional(annotation: Any) -> bool:
    """True for a field annotation that admits None (``float | None``, ``Optional[int]``, as text too)."""
    return "None" in str(annotation) or "Optional" in str(annotation)
