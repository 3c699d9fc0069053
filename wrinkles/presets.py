"""Quality presets: ``quality = "preview" | "balanced" | "final"`` in a scene file.

A preset is a *dotted-key overlay*: a table of scene keys (``shell.newton.rtol``, ...) and
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

The presets are Pareto points of the speed/accuracy trade measured by
``benchmarks/speed_accuracy.py`` on ``scenes/default.toml`` (compressed bar with a stiff skin,
4 frames, one-way coupling) on a coarser body mesh (:data:`MEASURED_RUN`); the measured wall
time per frame and error against the reference run (shell position RMS at the final frame,
relative to the reference's RMS displacement; bending energy ``k_B W_B``) are given with each
preset in :data:`PRESET_NOTES`. At that size every converged 2-level setting on the same
body mesh lies within 0.22-0.26 of the 3-level reference: the subdivision level (and the
body mesh, whose surface the shell refines) sets the error, the solver knobs mostly select
one of several nearby wrinkle branches (compare the wavelengths). ``scenes/default.toml``
writes ``levels``, ``rtol``, ``max_iterations`` and ``body.degree`` itself, so there these
keys of a preset do not apply (precedence).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from models.errors import InputError

QUALITY_KEY = "quality"
"""Top-level scene key selecting a preset."""

PRESETS: dict[str, dict[str, Any]] = {
    "preview": {
        "shell.subdivision.levels": 1,
        "shell.energy.hessian_mode": "exact",
        "shell.newton.rtol": 1.0e-6,
        "shell.newton.max_iterations": 300,
    },
    "balanced": {
        "shell.subdivision.levels": 2,
        "shell.energy.hessian_mode": "exact",
        "shell.newton.rtol": 1.0e-6,
        "shell.newton.max_iterations": 300,
    },
    "final": {
        "shell.subdivision.levels": 3,
        "shell.energy.hessian_mode": "exact",
        "shell.newton.rtol": 1.0e-8,
        "shell.newton.max_iterations": 500,
        "body.degree": 2,
    },
}
"""Quality name -> dotted scene keys and values (the overlay)."""

MEASURED_RUN = ("benchmarks/speed_accuracy.py --set mesh.params.h=0.05 --levels 0 1 2 "
                "--ref-levels 3 (benchmarks/results/speed_accuracy.json, 2026-11-22T11:29Z, "
                "serial, machine shared with other jobs: timings contended)")
"""The run the numbers of :data:`PRESET_NOTES` come from: ``scenes/default.toml`` on a
coarser body mesh (h = 5 cm instead of 2 cm, so 38 / 146 / 578 / 2306 shell vertices at
0 / 1 / 2 / 3 levels), 4 frames; reference: 3 levels, P2 body, exact Hessian, rtol 1e-8,
wrinkle wavelength 2.75 cm (:func:`wrinkles.measure.shell_wavelength`)."""

PRESET_NOTES: dict[str, str] = {
    "preview": "0.067 s/frame (0.27 s for 4 frames), 146 vertices; shell position RMS error "
               "0.256 of the reference RMS displacement (max 6.2 mm), bending energy 94 % "
               "below the reference; no wavelength measurable (a 1-level shell cannot "
               "resolve the 2.75 cm wrinkles)",
    "balanced": "1.30 s/frame (5.2 s for 4 frames), 578 vertices; RMS error 0.245 (max "
                "8.5 mm), bending energy error 45 %, wavelength 2.81 cm (2.2 % error); row "
                "'base'. The Gauss-Newton Hessian has a smaller RMS error (0.225) but a 19 % "
                "wavelength error, costs 2.17 s/frame there and 35.8 against 24.7 s/frame "
                "(exact) on the full default scene (h = 2 cm; benchmarks/profile_frame.py "
                "--set quality=balanced before the preset chose exact; contended)",
    "final": "the reference settings: 15.4 s/frame, 2306 vertices (error 0 by construction; "
             "not compared with a finer run)",
}
"""Quality name -> measured time per frame and error of the preset (:data:`MEASURED_RUN`)."""


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
    """Whether the nested document holds the dotted key given by ``parts``."""
    table: Any = doc
    for part in parts:
        if not isinstance(table, Mapping) or part not in table:
            return False
        table = table[part]
    return True


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


__all__ = ["MEASURED_RUN", "PRESETS", "PRESET_NOTES", "QUALITY_KEY", "apply_quality",
           "preset_keys"]
