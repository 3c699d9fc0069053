"""Command-line interface (placeholder until the scene runner lands)."""

from __future__ import annotations


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``wrinkles`` console script."""
    raise SystemExit("wrinkles: the scene runner is not built yet")
