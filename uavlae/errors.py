"""The errors a user can fix: what a command line, a config or an input file asks that cannot be
done. The entry points (:mod:`uavlae.entry`) print one of these as one message, ``error: ...``,
without a traceback; anything else is a bug and keeps its traceback.

Each subclasses the built-in type the code raised before (``ValueError``, ``FileNotFoundError``),
so a caller that catches those still catches these.
"""

from __future__ import annotations

__all__ = ["ConfigError", "InputError", "UserError"]


class UserError(Exception):
    """Something the user asked that cannot be done; the message says what would be accepted."""


class ConfigError(UserError, ValueError):
    """A setting out of its range, or settings that make no sense together: names each key."""


class InputError(UserError, ValueError):
    """A file the command reads (a scenario set, a checkpoint, progress files) that cannot be used."""
