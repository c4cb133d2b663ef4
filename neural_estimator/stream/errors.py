"""Errors of the message format and of the bags that store it: every message names the file or the
message and the problem. :mod:`neural_estimator.bags.errors` re-exports both (with ``BagWarning``)."""

from __future__ import annotations


class BagError(ValueError):
    """A bag file that cannot be written or read as asked (missing, not MCAP, wrong topic type...)."""


class MessageError(BagError):
    """One message that does not follow the layout of :mod:`neural_estimator.stream.messages`."""
