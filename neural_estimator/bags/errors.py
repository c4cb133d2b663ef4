"""Errors of the bag layer: every message names the file or the message and the problem."""

from __future__ import annotations


class BagError(ValueError):
    """A bag file that cannot be written or read as asked (missing, not MCAP, wrong topic type...)."""


class MessageError(BagError):
    """One message that does not follow the layout of :mod:`neural_estimator.bags.messages`."""


class BagWarning(UserWarning):
    """A damaged bag was read as far as possible; the text says what was recovered and lost."""
