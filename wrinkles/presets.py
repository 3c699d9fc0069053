"""Quality presets: ``quality = "preview" | "balanced" | "final"`` in a scene file.

A preset is a *dotted-key overlay*: a table of scene keys (``shell.solver.rtol``, ...) and
values that the scene loader (:func:`wrinkles.config.load`) merges into the TOML document
before the dataclasses are built, so a preset goes through exactly the same conversion and
validation as keys written by hand (and ``wrinkles check`` prints the resolved values).

Precedence, highest first:

1. ``--set key=value`` on the command line;
2. keys written in the scene file;
3. the preset selected by ``quality`` (itself settable with ``--set quality=...``);
4. the dataclass defaults.

A preset key is applied only when the key is absent from the document after the ``--set``
overrides, and only when its top-level table is present: a preset tunes the physics a scene
already has and never switches physics on (a body-only scene with ``quality = "preview"``
gets no ``[shell]``). ``quality`` itself is consumed by the overlay (it is not a field of
:class:`wrinkles.scene.Scene`); the resolved scene records the values it chose.

The presets are points of the speed/accuracy trade measured by
``benchmarks/speed_accuracy.py`` on ``scenes/default.toml`` (:data:`PRESET_ROWS` names the row
of each); the measured times and errors are in docs/notes/presets.md.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from meshes.errors import InputError

QUALITY_KEY = "quality"
"""Top-level scene key selecting a preset."""

PRESETS: dict[str, dict[str, Any]] = {
    "preview": {
        "shell.subdivision.levels": 1,
        "shell.solver.rtol": 1.0e-4,
        "shell.solver.max_iterations": 300,
    },
    "balanced": {
        "shell.subdivision.levels": 2,
        "shell.solver.rtol": 1.0e-4,
        "shell.solver.max_iterations": 300,
    },
    "final": {
        "shell.subdivision.levels": 3,
        "shell.solver.rtol": 1.0e-8,
        "shell.solver.max_iterations": 500,
        "body.degree": 2,
    },
}
"""Quality name -> dotted scene keys and values (the overlay)."""

PRESET_ROWS: dict[str, str] = {"preview": "levels=1", "balanced": "base", "final": "reference"}
"""Quality name -> the row of ``benchmarks/speed_accuracy.py``'s sweep that measured it ("base" is
the scene's own settings, i.e. ``balanced``; "reference" the reference run). The benchmark
copies this map into its JSON (``presets``) and ``make paper`` tabulates those rows."""


def preset_keys(quality: str, where: str = "<dict>") -> dict[str, Any]:
    """Return the dotted keys and values of preset ``quality``.

    Args:
        quality: one of :data:`PRESETS`.
        where: file name for the error message.

    Raises:
        InputError: unknown quality, naming the key ``quality`` and the choices.

    """
    if not isinstance(quality, str) or quality not in PRESETS:
        choices = ", ".join(repr(q) for q in PRESETS)
        raise InputError(f"{where}: {QUALITY_KEY}: must be one of {choices}, got {quality!r}")
    return dict(PRESETS[quality])


def _has_key(doc: Mapping[str, Any], parts: list[str]) -> bool:
    """Whether the nested document holds the dotted key given by ``parts``.

    A table may spell the rest of the path as one dotted key (``[shell.solver.options]
    "newton.shift.growth" = 5``): that counts too.
    """
    if not parts:
        return True
    if not isinstance(doc, Mapping):
        return False
    for k in range(1, len(parts) + 1):
        key = ".".join(parts[:k])
        if key in doc and _has_key(doc[key], parts[k:]):
            return True
    return False


def _set_key(doc: dict[str, Any], parts: list[str], value: Any) -> bool:
    """Set a dotted key, creating inner tables but never the top-level one; return if set.

    A key whose path crosses a non-table value is left alone (the loader reports that
    value's own type error).
    """
    if parts[0] not in doc:
        return False
    table: Any = doc
    for part in parts[:-1]:
        table = table.setdefault(part, {}) if isinstance(table, dict) else None
        if not isinstance(table, dict):
            return False
    table[parts[-1]] = value
    return True


def apply_quality(doc: dict[str, Any], where: str = "<dict>") -> list[str]:
    """Consume ``doc["quality"]`` and fill the preset's keys missing from ``doc`` (in place).

    Args:
        doc: the TOML document with the ``--set`` overrides already applied.
        where: file name for error messages.

    Returns:
        The dotted keys the preset set (empty without ``quality``).

    Raises:
        InputError: unknown quality (message names ``quality``).

    """
    if QUALITY_KEY not in doc:
        return []
    keys = preset_keys(doc.pop(QUALITY_KEY), where)
    applied = []
    for key, value in keys.items():
        parts = key.split(".")
        if not _has_key(doc, parts) and _set_key(doc, parts, value):
            applied.append(key)
    return applied


__all__ = ["PRESETS", "PRESET_ROWS", "QUALITY_KEY",
           "apply_quality", "preset_keys"]
