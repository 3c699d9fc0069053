"""Shell bending energy against the analytic cylinder and sphere values as meshes refine.

Calls :mod:`validation.bending_limits`: the hinge sum ``sum_h w_h theta_h^2`` of a plate
rolled on a unit cylinder (per unit area; the limit density is 3 for the equilateral lattice
and for the right grid bent along a lattice axis) and of an icosphere (over
``int (k1 + k2)^2 dA = 16 pi``; the limit is the triangle-shape prediction, 1.6 % above 1).
Writes ``data/shell_limits.json`` and ``figures/shell_limits.png``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from common import figure_path, fitted_slope, loglog_figure, parse_args, write_json

CYLINDERS = (("equilateral", 0.0), ("right", 0.0), ("right", 45.0))


def cylinder_case(lattice: str, angle: float, sizes: tuple[int, ...]) -> dict[str, Any]:
    """Energy density ratios, Richardson limit, fitted order and error against closed form."""
    import validation.bending_limits as lim
    from meshes.shells import wrap_on_cylinder

    u = np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle))])
    predicted = lim.closed_form_density(lattice, np.outer(u, u))
    ratios = []
    for n in sizes:
        p, f = lim.plate(lattice, n)
        q = lim.rotate_to(p, u)
        ratios.append(lim.hinge_sum(wrap_on_cylinder(q, 1.0), f, q) / lim.flat_area(p, f))
    limit, order = lim.richardson(np.array(ratios), sizes)
    errors = [abs(r / predicted - 1.0) for r in ratios]
    return {"lattice": lattice, "angle_deg": angle, "n": list(sizes), "density": ratios,
            "limit": limit, "order": order, "predicted": float(predicted),
            "limit_rel_error": abs(limit / predicted - 1.0), "rel_error": errors,
            "error_slope": fitted_slope([1.0 / n for n in sizes], errors)}


def sphere_case(levels: tuple[int, ...]) -> dict[str, Any]:
    """Icosphere hinge sum over 16 pi: Richardson limit against the triangle-shape value."""
    import validation.bending_limits as lim
    from meshes.shells import icosphere

    ratios = [lim.hinge_sum(p, f, p) / (16 * np.pi)
              for p, f in (icosphere(lv, radius=2.0) for lv in levels)]
    limit, order = lim.richardson(np.array(ratios), tuple(2**lv for lv in levels))
    predicted = lim.isotropic_shape_factor(*icosphere(levels[-1], radius=2.0))
    return {"levels": list(levels), "ratio": ratios, "limit": limit, "order": order,
            "predicted": predicted, "limit_abs_error": abs(limit - predicted),
            "excess_over_smooth": limit - 1.0}


def main() -> None:
    """Compute, plot and write ``data/shell_limits.json``."""
    args = parse_args(__doc__ or "")
    started = time.perf_counter()
    sizes = (8, 16, 32) if args.quick else (8, 16, 32, 64)
    cyl = {f"{lat}_{int(ang)}": cylinder_case(lat, ang, sizes) for lat, ang in CYLINDERS}
    sph = sphere_case((3, 4, 5) if args.quick else (5, 6, 7))
    fig = loglog_figure(figure_path(args.build, "shell_limits"),
                        [(f"cylinder {k} (slope {v['error_slope']:.2f})",
                          [1.0 / n for n in v["n"]], v["rel_error"]) for k, v in cyl.items()],
                        "h (plate spacing)", "|density / limit - 1|",
                        "Hinge bending energy on a unit cylinder")
    write_json(args.build, "shell_limits", {"cylinder": cyl, "sphere": sph, "figures": [fig]},
               args.quick, started)


if __name__ == "__main__":
    main()
