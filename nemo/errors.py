"""User-facing errors.

Every problem caused by the user's input (wrong file, missing axis, empty mask, bad option)
is raised as :class:`NemoError` with a message that names the problem and the fix. The CLI
prints such messages on one line and exits with status 2; anything else is a bug.
"""

from __future__ import annotations


class NemoError(Exception):
    """An error in the user's input or configuration, with a message meant for people."""


class NemoWarning(UserWarning):
    """A recoverable problem the user should know about (missing calibration, fallback)."""
