"""Taylor remainders of the shell energy terms (edge and area membrane, hinge bending).

Calls the helpers of ``tests/test_models/shell/test_taylor.py`` (random shells, flat-vector oracles,
remainders ``r1 = |W(x + e d) - W - e g.d|`` (slope 2 when the gradient is right) and
``r2 = |g(x + e d) - g - e H d|`` (slope 2 when the Hessian is right)) and writes the fitted
slopes to ``data/taylor.json`` and the remainders to ``figures/taylor.png``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from common import figure_path, fitted_slope, loglog_figure, parse_args, write_json


def term_remainders(name: str) -> dict[str, Any]:
    """Remainders and fitted slopes of one term on the perturbed irregular plate."""
    import validation.taylor as tt
    from meshes.shells import perturb
    from models.shell.bending import hinge_bending
    from models.shell.membrane import area_membrane, edge_membrane

    p, top, rest = tt.random_shell("plate")
    scale = float(rest.rest_lengths.min())
    x = perturb(p, 0.2 * scale, 7).reshape(-1)
    oracles = {
        "membrane_edge": lambda: tt.term_oracle(edge_membrane, top.edges, top.n_vertices,
                                                rest_len=rest.rest_lengths),
        "membrane_area": lambda: tt.term_oracle(area_membrane, top.faces, top.n_vertices,
                                                rest_area=rest.rest_areas),
        "bending": lambda: tt.term_oracle(hinge_bending, top.hinges, top.n_vertices,
                                          theta0=rest.rest_angles,
                                          weights=rest.hinge_weights),
    }
    d = np.random.default_rng(5).standard_normal(x.size)
    eps = tt.EPS * scale
    r1, r2, _ = tt.remainders(oracles[name](), x, d, eps)
    return {"eps": eps.tolist(), "r_value": r1.tolist(), "r_gradient": r2.tolist(),
            "slope_value": fitted_slope(eps, r1), "slope_gradient": fitted_slope(eps, r2)}


def main() -> None:
    """Compute, plot and write ``data/taylor.json``."""
    args = parse_args(__doc__ or "")
    started = time.perf_counter()
    terms = {name: term_remainders(name) for name in ("membrane_edge", "membrane_area",
                                                       "bending")}
    series = [(f"{k} {kind} (slope {v['slope_' + kind]:.2f})", v["eps"], v["r_" + kind])
              for k, v in terms.items() for kind in ("value", "gradient")]
    fig = loglog_figure(figure_path(args.build, "taylor"), series, "step e",
                        "Taylor remainder", "Shell terms: Taylor remainders")
    write_json(args.build, "taylor", {"terms": terms, "min_slope": min(
        min(v["slope_value"], v["slope_gradient"]) for v in terms.values()), "figures": [fig]},
        args.quick, started)


if __name__ == "__main__":
    main()
