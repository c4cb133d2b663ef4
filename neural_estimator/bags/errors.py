"""Errors of the bag layer: every message names the file or the message and the problem.

``BagError`` and ``MessageError`` are defined with the message format (:mod:`neural_estimator.stream.errors`:
a malformed message is a ``BagError`` whether it came from a bag or from a live topic) and importable
from here as before."""

from __future__ import annotations

from neural_estimator.stream.errors import BagError, MessageError

__all__ = ["BagError", "BagWarning", "MessageError"]


class BagWarning(UserWarning):
    """A damaged bag was read as far as possible; the text says what was recovered and lost."""
