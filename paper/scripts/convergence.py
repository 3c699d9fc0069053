"""Body convergence: manufactured-solution L2 errors of P1/P2 and Saint-Venant torsion.

Calls :func:`validation.manufactured.l2_error` (the Neo-Hookean manufactured problem on
the unit cube) and :mod:`validation.torsion` (the twisted P2 cylinder: torque against
T = G J theta / L). Writes ``data/convergence.json`` and ``figures/body_convergence.png``,
``figures/torsion.png``.
"""

from __future__ import annotations

import math
import time
from typing import Any

from common import figure_path, fitted_slope, loglog_figure, parse_args, write_json


def body_rates(quick: bool) -> dict[str, Any]:
    """L2 errors and fitted rates of P1 and P2 on n^3 unit cubes (h = 1/n)."""
    from validation.manufactured import l2_error

    sizes = {1: (2, 4) if quick else (4, 8, 16), 2: (2, 4) if quick else (2, 4, 8)}
    out: dict[str, Any] = {}
    for degree, ns in sizes.items():
        errors = [l2_error(n, degree) for n in ns]
        h = [1.0 / n for n in ns]
        out[f"P{degree}"] = {"n": list(ns), "h": h, "l2_error": errors,
                             "rate": fitted_slope(h, errors), "expected_rate": degree + 1}
    return out


def torsion(quick: bool) -> dict[str, Any]:
    """Relative torque errors of the twisted P2 cylinder against circular J and meshed J_h."""
    import validation.torsion as rot

    theta, sizes = 0.01, (0.5, 0.35) if quick else (0.5, 0.35, 0.25)
    exact = rot.SHEAR * math.pi * rot.R**4 / 2.0 * theta / rot.L
    errors, errors_h = [], []
    for h in sizes:
        body, j_h = rot.twisted_cylinder(h, theta)
        torque = float(rot.end_torque(body, rot.L)[2])
        errors.append(abs(torque / exact - 1.0))
        errors_h.append(abs(torque / (rot.SHEAR * j_h * theta / rot.L) - 1.0))
    return {"h": list(sizes), "theta": theta, "radius": rot.R, "length": rot.L,
            "shear_modulus": rot.SHEAR, "rel_error": errors, "rel_error_meshed_section":
            errors_h, "rate": fitted_slope(sizes, errors), "finest_rel_error": errors[-1],
            "max_rel_error_meshed_section": max(errors_h)}


def main() -> None:
    """Compute, plot and write ``data/convergence.json``."""
    args = parse_args(__doc__ or "")
    started = time.perf_counter()
    rates, tors = body_rates(args.quick), torsion(args.quick)
    fig1 = loglog_figure(figure_path(args.build, "body_convergence"),
                         [(f"{k} (rate {v['rate']:.2f})", v["h"], v["l2_error"])
                          for k, v in rates.items()],
                         "h", "L2 error of u", "Neo-Hookean manufactured solution")
    fig2 = loglog_figure(figure_path(args.build, "torsion"),
                         [(f"circular J (rate {tors['rate']:.2f})", tors["h"],
                           tors["rel_error"]),
                          ("meshed section J_h", tors["h"], tors["rel_error_meshed_section"])],
                         "h", "|T / (G J theta / L) - 1|", "Twisted P2 cylinder")
    write_json(args.build, "convergence", {"body": rates, "torsion": tors,
                                           "figures": [fig1, fig2]}, args.quick, started)


if __name__ == "__main__":
    main()
