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

The presets are points of the speed/accuracy trade measured by
``benchmarks/speed_accuracy.py`` on ``scenes/default.toml`` at full size (compressed bar
with a stiff skin, body h = 2 cm, 4 frames, one-way coupling; :data:`MEASURED_RUN`); the
measured time per frame (process CPU time, the fair figure on the shared machine, and the
contended wall time) and the errors against the reference run (shell position RMS at the
final frame relative to the reference's RMS displacement, bending energy ``k_B W_B``,
wrinkle wavelength) are given with each preset in :data:`PRESET_NOTES`. Two fronts: on the
position error the 2-level exact solve (``balanced``) is the most accurate 2-level setting
(only the 3-level Gauss-Newton row is closer, at 6.4x its CPU time), while on the bending
energy error the error falls with every subdivision level (0.96 / 0.57 / 0.18 / 0.0014 at
0 / 1 / 2 / 3 levels, exact Hessian). The 3-level P1 shell lands on a
phase-shifted wrinkle branch (position RMS 0.169, but wavelength within 0.6 % and bending
energy within 0.14 % of the reference), so the position error alone does not rank the
levels. The Newton tolerance does not matter with the exact Hessian (rtol 1e-3 to 1e-8:
the same shell, within 1 % of the time). ``scenes/default.toml`` sets ``quality =
"balanced"`` and writes none of the preset's keys.
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

MEASURED_RUN = ("python benchmarks/speed_accuracy.py --resume --budget 50 "
                "(benchmarks/results/speed_accuracy.json, 2026-11-22T13:25-14:06Z, and the "
                "row L3+gauss_newton+rtol=0.001 14:23-14:29Z by --resume --only combo; serial, "
                "machine shared with other jobs: 1-minute load 3.7-7.7 on 2 cores, wall "
                "times about 3x the CPU times)")
"""The run the numbers of :data:`PRESET_NOTES` come from: ``scenes/default.toml`` as it is
(h = 2 cm, so 165 / 654 / 2610 / 10434 shell vertices at 0 / 1 / 2 / 3 levels), 4 frames;
reference: 3 levels, P2 body, exact Hessian, rtol 1e-8, 10434 vertices, 42.2 s/frame CPU
(125 s/frame wall), wrinkle wavelength 2.18 cm (:func:`wrinkles.measure.shell_wavelength`).
The earlier coarse-body sweep (h = 5 cm, session 2) chose the same presets."""

PRESET_ROWS: dict[str, str] = {"preview": "levels=1", "balanced": "base", "final": "reference"}
"""Quality name -> the row of :data:`MEASURED_RUN`'s JSON that measured the preset ("base" is
the scene's own settings, i.e. ``balanced``; "reference" the reference run). The benchmark
copies this map into its JSON (``presets``) and ``make paper`` tabulates those rows."""

PRESET_NOTES: dict[str, str] = {
    "preview": "row 'levels=1': 0.41 s/frame CPU (1.26 s/frame wall, contended), 654 "
               "vertices; shell position RMS error 0.198 of the reference RMS displacement "
               "(max 8.3 mm), bending energy error 57 %, wavelength 2.01 cm (7.9 % error); on "
               "both Pareto fronts",
    "balanced": "row 'base': 5.74 s/frame CPU (17.5 s/frame wall, contended), 2610 "
                "vertices; RMS error 0.135 (max 5.2 mm), the lowest at 2 levels; bending "
                "energy error 18 %, wavelength 2.05 cm (6.0 % error). A measured cheaper "
                "point on both fronts: the Gauss-Newton Hessian with rtol 1e-3 ('L2+gauss_"
                "newton+rtol=0.001'), 1.90 s/frame CPU (3.0x less), RMS error 0.146, bending "
                "energy error 15.5 %, wavelength error 9.0 %: worse positions and wavelength, "
                "so not the preset (set it with --set for speed). Gauss-Newton at rtol 1e-6 "
                "did not converge in 300 iterations (826 over 4 frames)",
    "final": "row 'reference' (the reference settings): 42.2 s/frame CPU (125 s/frame "
             "wall, contended), 10434 vertices; error 0 by construction (not compared with a "
             "finer run). The 3-level P1 shell at rtol 1e-6 ('levels=3') costs 37.4 s/frame "
             "CPU with bending energy error 0.14 % and wavelength error 0.6 %; with the "
             "Gauss-Newton Hessian at rtol 1e-3 ('L3+gauss_newton+rtol=0.001') 36.6 s/frame "
             "CPU, RMS error 0.128 (the lowest of the sweep), bending energy error 3.5 %: "
             "neither is much cheaper than the reference",
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


__all__ = ["MEASURED_RUN", "PRESETS", "PRESET_NOTES", "PRESET_ROWS", "QUALITY_KEY",
           "apply_quality", "preset_keys"]
