"""YAML from files and bags someone else wrote, read in bounded time and memory.

PyYAML's pure-Python loader recurses once per nesting level (a deeply nested robot spec raises
``RecursionError`` after super-linear time: 1,000 levels 2.7 s, 20,000 levels 38 s) and reads any
size. :func:`load_yaml` bounds the text's size first (a length check, O(1)), then parses with
libyaml's C loader (``CSafeLoader``: safe tags only, no Python objects), whose scanner refuses more
than 1,000 nesting levels in linear time; where PyYAML was built without libyaml, the pure-Python
``SafeLoader`` is used under the same size bound and its ``RecursionError`` is caught. Every
refusal is one :class:`YamlError` line naming what was read and why.
"""

from __future__ import annotations

import yaml


class YamlError(ValueError):
    """Text that is not YAML this package accepts; the message names the source and the problem."""


def load_yaml(text: str | bytes, what: str, max_bytes: int) -> object:
    """The document of ``text`` (at most ``max_bytes`` bytes), or :class:`YamlError` naming ``what``.

    YAML aliases are resolved by reference (no copy), so an alias bomb costs no memory here; a
    consumer that walks the result must still bound its own work.
    """
    size = len(text.encode("utf-8", "surrogatepass") if isinstance(text, str) else text)
    if size > max_bytes:
        raise YamlError(f"{what}: {size} bytes of YAML, over the bound of {max_bytes} bytes")
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    try:
        return yaml.load(text, Loader=loader)
    except yaml.YAMLError as exc:
        raise YamlError(f"{what}: not valid YAML ({_first_line(exc)})") from None
    except RecursionError:
        raise YamlError(f"{what}: YAML nested too deeply") from None
    except (ValueError, TypeError, OverflowError) as exc:  # e.g. a timestamp or number out of range
        raise YamlError(f"{what}: unreadable YAML value ({_first_line(exc)})") from None


def _first_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())  # libyaml's messages span lines
    return text[:200] if text else type(exc).__name__
