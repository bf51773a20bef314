"""The one base of every error a user can cause: a bad file, key, value or instrument answer.

The command line prints a ``SkinlayersError`` (and an ``OSError``: a missing file, a full disk) as one
line and exits 1; anything else is a bug and keeps its traceback. Each part derives its own errors
from these, keeping the built-in class it has always been (``ValueError`` for bad input,
``RuntimeError`` for instruments), so ``except ValueError`` in a caller goes on working.

``file`` and ``key``, when given, are kept as attributes and lead the message:
``FILE: KEY: problem``.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["InputError", "SettingsError", "SkinlayersError"]


class SkinlayersError(Exception):
    """An error the user can act on; the message names the file, key or value at fault."""

    def __init__(self, message: str, *, file: str | Path | None = None, key: str | None = None) -> None:
        self.file = None if file is None else str(file)
        self.key = key
        self.problem = message
        lead = "".join(f"{part}: " for part in (self.file, key) if part)
        super().__init__(lead + message)


class InputError(SkinlayersError, ValueError):
    """A value, option or file content that cannot be used."""


class SettingsError(InputError):
    """A settings file or value that cannot be used (the base of each part's settings error)."""
