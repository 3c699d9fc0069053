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
wrinkle wavelength) are given with each preset in :data:`PRESET_NOTES`. Two fronts (position
RMS, bending energy); with the x5 / 2 shift schedule (:data:`SHIFT_SCHEDULE`, session 5) the
3-level P1 shell lands on the reference's branch (position RMS 0.030, bending energy 3.6 %,
wavelength 0.4 %), so the levels rank the same on both. The 2-level exact solve (``balanced``)
is on neither front but no 2-level setting beats it on all three errors at less CPU time: the
Gauss-Newton Hessian at rtol 1e-3 is cheaper (0.68x) with a lower bending energy error but
worse positions and wavelength, a coarser body (h = 3 cm, a scene choice, not a preset key) is
cheaper with better positions but two to three times the bending energy and wavelength errors.
The Newton tolerance does not matter with the exact Hessian (rtol 1e-3 to 1e-8: RMS error
0.148 throughout, within 10 % of the time). ``scenes/default.toml`` sets ``quality =
"balanced"`` and writes none of the preset's keys.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from models.errors import InputError

QUALITY_KEY = "quality"
"""Top-level scene key selecting a preset."""

SHIFT_SCHEDULE: dict[str, Any] = {
    "shell.newton.shift.growth": 5.0,
    "shell.newton.shift_decay": 2.0,
    "shell.newton.shift.max_shifts": 20,
}
"""The shifted-Hessian factors of every preset: growth 5, decay 2 (the solver's defaults are
the textbook 10 / 10); measured by benchmarks/shift_schedule.py and by the sweep's row
'shift=10/10' (see :class:`solvers.linear.ShiftOptions`)."""

PRESETS: dict[str, dict[str, Any]] = {
    "preview": {
        "shell.subdivision.levels": 1,
        "shell.energy.hessian_mode": "exact",
        "shell.newton.rtol": 1.0e-6,
        "shell.newton.max_iterations": 300,
        **SHIFT_SCHEDULE,
    },
    "balanced": {
        "shell.subdivision.levels": 2,
        "shell.energy.hessian_mode": "exact",
        "shell.newton.rtol": 1.0e-6,
        "shell.newton.max_iterations": 300,
        **SHIFT_SCHEDULE,
    },
    "final": {
        "shell.subdivision.levels": 3,
        "shell.energy.hessian_mode": "exact",
        "shell.newton.rtol": 1.0e-8,
        "shell.newton.max_iterations": 500,
        "body.degree": 2,
        **SHIFT_SCHEDULE,
    },
}
"""Quality name -> dotted scene keys and values (the overlay)."""

MEASURED_RUN = ("python benchmarks/speed_accuracy.py --resume --budget 60 "
                "(benchmarks/results/speed_accuracy.json, 2026-11-25T16:28-17:35Z, serial, "
                "the machine running one other benchmark: 1-minute load 1.8-2.1 on 2 cores, "
                "wall times 0-10 % above the CPU times)")
"""The run the numbers of :data:`PRESET_NOTES` come from: ``scenes/default.toml`` as it is
(h = 2 cm, so 165 / 654 / 2610 / 10434 shell vertices at 0 / 1 / 2 / 3 levels), 4 frames;
reference: 3 levels, P2 body, exact Hessian, rtol 1e-8, 10434 vertices, 25.6 s/frame CPU,
wrinkle wavelength 2.20 cm (:func:`wrinkles.measure.shell_wavelength`). The sweeps of
sessions 2-4 (ten-fold shift schedule) chose the same presets. Rerun 2026-11-26 (session 7,
another 2-core machine, load 1.2-1.3): the same errors, ``preview`` again on both fronts and
``balanced`` on neither; CPU per frame preview 0.22 s, balanced 2.51 s, final (the reference)
19.3 s. The new row 'modified' (modified Newton at 2 levels, 2.24 s) joins the position front
(rms 0.131) but has larger bending-energy and wavelength errors (17.9 % / 6.3 % against 16.2 %
/ 3.7 %), so it does not beat ``balanced`` on all three and the presets stay."""

PRESET_ROWS: dict[str, str] = {"preview": "levels=1", "balanced": "base", "final": "reference"}
"""Quality name -> the row of :data:`MEASURED_RUN`'s JSON that measured the preset ("base" is
the scene's own settings, i.e. ``balanced``; "reference" the reference run). The benchmark
copies this map into its JSON (``presets``) and ``make paper`` tabulates those rows."""

PRESET_NOTES: dict[str, str] = {
    "preview": "row 'levels=1': 0.32 s/frame CPU, 654 vertices; shell position RMS error "
               "0.187 of the reference RMS displacement (max 8.7 mm), bending energy error "
               "57 %, wavelength 2.01 cm (8.8 % error); on both Pareto fronts",
    "balanced": "row 'base': 3.35 s/frame CPU, 2610 vertices; RMS error 0.148 (max 5.6 mm), "
                "bending energy error 16 %, wavelength 2.12 cm (3.7 % error). Measured "
                "neighbours: the Gauss-Newton Hessian with rtol 1e-3 ('L2+gauss_newton+"
                "rtol=0.001') 2.27 s/frame CPU (0.68x), RMS error 0.162, bending energy error "
                "13 %, wavelength error 8.0 % (set it with --set for speed); the solver's "
                "default ten-fold shift schedule ('shift=10/10') 6.92 s/frame CPU (2.1x), RMS "
                "error 0.168, wavelength error 6.8 %; narrower clusters ('sigma=0.0035', a "
                "scene key) 3.52 s/frame, RMS error 0.145, bending energy error 9.7 %, "
                "wavelength error 1.9 %",
    "final": "row 'reference' (the reference settings): 25.6 s/frame CPU, 10434 vertices; "
             "error 0 by construction (not compared with a finer run). The 3-level P1 shell "
             "at rtol 1e-6 ('levels=3') costs 25.9 s/frame CPU with RMS error 0.030, "
             "bending energy error 3.6 % and wavelength error 0.4 %; with the Gauss-Newton "
             "Hessian at rtol 1e-3 ('L3+gauss_newton+rtol=0.001') 45.6 s/frame CPU (it "
             "needs 427 iterations), RMS error 0.151: neither is cheaper than the reference",
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
