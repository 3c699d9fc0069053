"""Where a run's code comes from: the project's version and git commit (no dolfinx import)."""

from __future__ import annotations

import subprocess
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
"""The checkout the package runs from (editable install)."""


def _git(*args: str) -> str | None:
    """Output of ``git -C ROOT ARGS`` (stripped), ``None`` if git fails or is missing."""
    try:
        proc = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True,
                              timeout=10, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return proc.stdout.strip() if proc.returncode == 0 else None


def source_commit() -> str | None:
    """Return the git commit of the code that runs, ``-dirty`` when tracked files changed."""
    commit = _git("rev-parse", "HEAD")
    if not commit:
        return None
    dirty = _git("status", "--porcelain", "--untracked-files=no")
    return commit + ("-dirty" if dirty else "")


def wrinkles_version() -> str:
    """Return the installed version of this project (``pyproject.toml``)."""
    try:
        return metadata.version("wrinkles")
    except metadata.PackageNotFoundError:
        return "unknown"


def version_text() -> str:
    """``wrinkles X.Y.Z (commit abc1234)``: what ``wrinkles --version`` prints."""
    commit = source_commit()
    return f"wrinkles {wrinkles_version()}" + (f" (commit {commit[:12]})" if commit else "")
