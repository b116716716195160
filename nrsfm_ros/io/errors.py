"""The one error type raised for malformed messages and files."""
from __future__ import annotations

from typing import Any


class MessageError(ValueError):
    """A message (or file) does not match what the conversion needs.

    Always names the offending ``field`` and the ``value`` received, so a node can count it, log
    it once and report it on diagnostics.
    """

    def __init__(self, field: str, value: Any, reason: str) -> None:
        self.field = field
        self.value = value
        self.reason = reason
        shown = repr(value)
        if len(shown) > 80:
            shown = shown[:77] + '...'
        super().__init__(f'{field}={shown}: {reason}')
