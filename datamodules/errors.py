"""The project's error classes: what a command reports as one line instead of a traceback.

Every error the project raises about its input (a file, a folder, a setting) derives from
:class:`AauteError`, so the ``aaute`` command decides by type, not by message, whether it faces
bad input (one line naming the file and what was expected, exit code 2) or a programming error
(full traceback). Each class also derives from the built-in it refines (``ValueError``), so
callers that catch those keep working.
"""

from __future__ import annotations


class AauteError(Exception):
    """Base of every error about the user's input: printed as one line by the ``aaute`` command."""


class ConfigError(AauteError, ValueError):
    """A setting or command-line argument that cannot work (the message names it and what is allowed)."""


class NonFiniteLossError(AauteError, ArithmeticError):
    """A training or validation step produced a NaN or infinite loss (the message names the batch's data)."""
