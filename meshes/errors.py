"""Error types shared by every layer, mapped to the CLI's exit codes.

``InputError`` (exit code 1) is raised for anything the user supplied that cannot be used:
a scene key, a parameter value, a mesh file or one of its elements. Its message names the
offending file, key or element so the user can fix it without reading a traceback.

``SolverError`` (exit code 2) is raised when a solve fails after every fallback (step
halving, shifted Hessian) was tried; the message carries the diagnostic.
"""

from __future__ import annotations


class WrinklesError(Exception):
    """Base class of every error this code raises on purpose."""

    exit_code: int = 2


class InputError(WrinklesError, ValueError):
    """Bad user input: a scene key, parameter, mesh file or mesh element (exit code 1)."""

    exit_code = 1


class SolverError(WrinklesError, RuntimeError):
    """A solve failed after every fallback was tried (exit code 2)."""

    exit_code = 2
