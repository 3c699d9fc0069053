"""The speed/accuracy trade of a wrinkle scene: sweep the knobs, time them, compare to a reference.

A *reference* run of the scene (default ``scenes/default.toml``) is made once with the
finest settings that fit (``--ref-levels`` subdivision levels, exact Hessian, shell Newton
``rtol = 1e-8``, P2 body) and stored under ``benchmarks/results/`` as
``speed_accuracy_reference_<scene>[_quick].npz`` (regenerated when missing or when its
settings changed; not committed). Then every configuration of the sweep (one knob at a time
from the scene's own settings, plus a few combinations) runs the same frames and is compared
with the reference at the final frame:

* shell position error, RMS and max over the compared points [m], and the RMS relative to
  the RMS displacement of the reference shell (``rms_rel``, the Pareto axis). Shells on the
  same body mesh share their first vertices (linear and Loop subdivision keep the coarse
  vertices first and the vertex order of every level), so a coarser shell is compared on
  its own vertices (common vertices); a shell on another body mesh is interpolated
  (barycentric, nearest rest triangle) at the reference's rest points;
* bending energy ``k_B W_B`` relative error;
* dominant wrinkle wavelength (:func:`wrinkles.measure.shell_wavelength` of the normal
  deviation from the target on the lateral faces along the longest axis) and its relative
  error;
* wall time per frame (mean over frames, output files off: XDMF, summary and checkpoint are
  not written; the shell set-up is reported apart), peak resident memory of the process
  during the configuration (VmHWM reset before each run), shell Newton iterations.

Knobs: subdivision levels, cluster count and sigma, Hessian mode (exact, gauss_newton,
projected, mixed = projected far from the minimum then exact), shell Newton tolerance and
iteration cap, linear solver (augmented low-rank penalty with MUMPS LDL^T or SuperLU_dist
LU, assembled penalty with MUMPS Cholesky), body P1/P2 and mesh size, frames per unit load
(time step), one- vs two-way (implicit) coupling.

Writes ``benchmarks/results/speed_accuracy.json`` (``--out``), the Pareto plot
``speed_accuracy.png`` (wall time of all frames vs rms_rel, log-log: every setting reaches
the same final load, so settings with other frame counts compare fairly) and the Markdown
table of the Pareto-optimal settings ``speed_accuracy_pareto.md`` (converged settings only;
a slower setting must lower the error by more than 1 % to be on the front).

Usage::

    python benchmarks/speed_accuracy.py --quick              # tiny sizes, ~30 s
    python benchmarks/speed_accuracy.py                      # default scene, full sweep
    python benchmarks/speed_accuracy.py --only subdivision hessian
    python benchmarks/speed_accuracy.py --scene scenes/ball_sofa.toml

Runs are serial (one rank); timings on a shared machine are contended.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402
from shell_solve import proc_status_mib, reset_peak_rss  # noqa: E402

from models.backend import MPI  # noqa: E402
from models.errors import InputError, SolverError  # noqa: E402
from wrinkles.measure import normal_heights, shell_wavelength  # noqa: E402
from wrinkles.runner import prepare, run_frames  # noqa: E402
from wrinkles.scene import load_scene  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
QUIET = ["shell.render=false", "shell.xdmf=false", "output.xdmf=false",
         "output.summary=false", "output.checkpoint=false"]
"""Overrides of every run: no output files, no rendering (timing the solve, not the disk)."""

QUICK_BASE = ["mesh.params.h=0.05", "time.frames=2", "body.dt=0.5",
              "shell.newton.max_iterations=200"]
"""``--quick``: coarse body mesh, 2 frames of the same total load (tiny, seconds)."""

REFERENCE = ["body.degree=2", "shell.energy.hessian_mode=\"exact\"",
             "shell.newton.far_hessian=\"\"", "shell.newton.rtol=1e-8",
             "shell.newton.max_iterations=500"]
"""The reference's settings besides its subdivision level."""


PARETO_MARGIN = 0.01
"""Relative error decrease below which a slower setting is not counted as more accurate."""


@dataclasses.dataclass(frozen=True)
class Config:
    """One point of the sweep.

    Attributes:
        name: unique label.
        group: the knob swept ("subdivision", "hessian", ...; "combo" for combinations).
        overrides: ``key=value`` scene overrides on top of the base.

    """

    name: str
    group: str
    overrides: tuple[str, ...] = ()


# --------------------------------------------------------------------------------------------
# The sweep


def single_knobs(levels: list[int], quick: bool) -> list[Config]:
    """One knob at a time away from the scene's own settings."""
    c = [Config("base", "base")]
    c += [Config(f"levels={n}", "subdivision", (f"shell.subdivision.levels={n}",))
          for n in levels]
    c += [Config(f"hessian={m}", "hessian", (f'shell.energy.hessian_mode="{m}"',))
          for m in ("exact", "gauss_newton", "projected")]
    c += [Config("hessian=mixed", "hessian", ('shell.energy.hessian_mode="exact"',
                                              'shell.newton.far_hessian="projected"'))]
    c += [Config(f"rtol={r:g}", "newton_rtol", (f"shell.newton.rtol={r!r}",))
          for r in (1e-3, 1e-4, 1e-5, 1e-7)]
    c += [Config(f"max_it={k}", "newton_cap", (f"shell.newton.max_iterations={k}",))
          for k in (10, 30)]
    if quick:
        return c
    c += [Config(f"clusters={k}", "clusters", (f"shell.clusters.count={k}",))
          for k in (50, 100, 200, 400)]
    c += [Config(f"sigma={s:g}", "sigma", ("shell.clusters.spacing=0.0105",
                                           f"shell.clusters.sigma={s!r}"))
          for s in (0.0035, 0.0067, 0.013)]
    c += [Config("linear=superlu_dist", "linear",
                 ('shell.newton.augmented_linear.backend="superlu_dist"',
                  'shell.newton.augmented_linear.symmetric="lu"')),
          Config("linear=assembled_mumps", "linear", ('shell.energy.penalty_hessian="assembled"',
                                                      'shell.newton.linear.backend="mumps"'))]
    c += [Config("body=P2", "body", ("body.degree=2",))]
    c += [Config(f"h={h:g}", "mesh", (f"mesh.params.h={h!r}",)) for h in (0.04, 0.03)]
    c += [Config(f"frames={n}", "time", (f"time.frames={n}", f"body.dt={1.0 / n!r}"))
          for n in (2, 8)]
    c += [Config("two_way", "coupling", ('shell.coupling.mode="two_way"',
                                         'shell.coupling.scheme="implicit"'))]
    return c


def combinations(levels: list[int]) -> list[Config]:
    """Combinations of the knobs that move the Pareto front (the preset candidates)."""
    out = []
    for n in levels:
        for mode, rtol in (("projected", 1e-3), ("projected", 1e-5), ("mixed", 1e-7)):
            hess = (('shell.energy.hessian_mode="exact"', 'shell.newton.far_hessian="projected"')
                    if mode == "mixed" else (f'shell.energy.hessian_mode="{mode}"',))
            out.append(Config(f"L{n}+{mode}+rtol={rtol:g}", "combo",
                              (f"shell.subdivision.levels={n}", *hess,
                               f"shell.newton.rtol={rtol!r}")))
    return out


def sweep(levels: list[int], quick: bool, only: list[str] | None) -> list[Config]:
    """All configurations, optionally only some groups."""
    configs = single_knobs(levels, quick) + combinations(levels)
    return [c for c in configs if not only or c.group in only or c.group == "base"]


# --------------------------------------------------------------------------------------------
# Running one configuration


def run_config(scene_path: Path, overrides: list[str]) -> dict[str, Any]:
    """Run the scene with ``overrides`` (serial, output off); time it and keep the final shell.

    Returns:
        times, peak memory, iterations and the final shell arrays (``rest``, ``x``,
        ``target``, ``faces``) plus the bending energy and vertex count.

    """
    scene = load_scene(scene_path, [*overrides, *QUIET])
    if scene.shell is None:
        raise InputError(f"{scene_path}: the speed/accuracy sweep needs a [shell] table")
    reset_peak_rss()
    rss0 = proc_status_mib("VmRSS")
    with tempfile.TemporaryDirectory(prefix="speed_accuracy_") as tmp:
        t0 = time.perf_counter()
        run = prepare(scene, Path(tmp), MPI.COMM_WORLD)
        setup = time.perf_counter() - t0
        run_frames(run, log=lambda line: None)
    shell = run.shell
    assert shell is not None
    walls = [r.wall_time for r in run.records]
    terms = shell.energy.evaluate(shell.x, order=0).terms
    return {"setup_time": setup, "frame_times": walls,
            "time_per_frame": float(np.mean(walls)), "peak_rss_mib": proc_status_mib("VmHWM"),
            "peak_rss_delta_mib": proc_status_mib("VmHWM") - rss0,
            "shell_iterations": [r.details.get("shell_iterations") for r in run.records],
            "shell_converged": [r.details.get("shell_converged") for r in run.records],
            "coupling_iterations": [r.details.get("coupling_iterations") for r in run.records],
            "vertices": int(shell.rest.shape[0]), "bending_energy": float(terms.get("bending",
                                                                                    0.0)),
            "arrays": {"rest": shell.rest.copy(), "x": shell.x.copy(), "target": shell.y.copy(),
                       "faces": shell.topology.faces.copy()}}


# --------------------------------------------------------------------------------------------
# Comparison with the reference


def barycentric_interpolate(rest: np.ndarray, faces: np.ndarray, values: np.ndarray,
                            points: np.ndarray, candidates: int = 8) -> np.ndarray:
    """Interpolate nodal ``values`` of a triangle mesh at ``points`` (closest triangle).

    For each point the ``candidates`` triangles with the nearest centroids are tried; the
    point is projected onto each triangle's plane, its barycentric coordinates clipped to the
    triangle and renormalised, and the triangle at the smallest distance is used.
    """
    tri = rest[faces]
    _, idx = cKDTree(tri.mean(axis=1)).query(points, k=min(candidates, len(faces)))
    idx = idx.reshape(len(points), -1)
    best = np.full(len(points), np.inf)
    out = np.zeros((len(points),) + values.shape[1:])
    for j in range(idx.shape[1]):
        f = idx[:, j]
        lam = _barycentric(tri[f], points)
        p = np.einsum("nk,nkd->nd", lam, tri[f])
        dist = np.linalg.norm(p - points, axis=1)
        better = dist < best
        best[better] = dist[better]
        out[better] = np.einsum("nk,nk...->n...", lam[better], values[faces[f[better]]])
    return out


def _barycentric(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Clipped, renormalised barycentric coordinates of ``p`` projected onto triangles."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (np.einsum("ij,ij->i", u, v) for u, v in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("ij,ij->i", v2, v0), np.einsum("ij,ij->i", v2, v1)
    den = np.where(np.abs(d00 * d11 - d01 * d01) > 0, d00 * d11 - d01 * d01, 1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    lam = np.clip(np.stack([1.0 - v - w, v, w], axis=1), 0.0, None)
    return lam / np.maximum(lam.sum(axis=1, keepdims=True), 1e-300)


def compared_positions(ref: dict[str, np.ndarray], cand: dict[str, np.ndarray]
                       ) -> tuple[np.ndarray, np.ndarray, str]:
    """Reference and candidate final positions on common points, and how they were matched."""
    n = min(len(ref["rest"]), len(cand["rest"]))
    if np.allclose(ref["rest"][:n], cand["rest"][:n], rtol=0.0, atol=1e-12):
        return ref["x"][:n], cand["x"][:n], "common_vertices"
    disp = cand["x"] - cand["rest"]
    at_ref = barycentric_interpolate(cand["rest"], cand["faces"], disp, ref["rest"])
    return ref["x"], ref["rest"] + at_ref, "interpolated"


def wrinkle_wavelength(arrays: dict[str, np.ndarray]) -> float | None:
    """Dominant wrinkle wavelength [m] of the final shell (:mod:`wrinkles.measure`).

    The normal deviation from the target, ``(x - y) . n_y``, on the flat lateral faces
    parallel to the longest axis of the rest shell (the compression axis of the bar), one
    mean edge length inside the faces' borders (2 leave no vertex on the 5 cm faces of a
    2-level shell on h = 5 cm tets), lines one edge length wide.
    ``None`` when the shell has no such faces (e.g. a curved body).
    """
    rest, faces = arrays["rest"], arrays["faces"]
    edge = float(np.mean(np.linalg.norm(rest[faces[:, 1]] - rest[faces[:, 0]], axis=1)))
    axis = int(np.argmax(np.ptp(rest, axis=0)))
    heights = normal_heights(arrays["x"], arrays["target"], faces)
    try:
        return shell_wavelength(rest, faces, heights, axis, edge, edge).wavelength
    except InputError:
        return None


def errors(ref: dict[str, Any], cand: dict[str, Any]) -> dict[str, Any]:
    """Error metrics of a run against the reference (final frame)."""
    xr, xc, how = compared_positions(ref["arrays"], cand["arrays"])
    d = np.linalg.norm(xc - xr, axis=1)
    scale = float(np.sqrt(np.mean(np.sum((ref["arrays"]["x"] - ref["arrays"]["rest"]) ** 2,
                                         axis=1))))
    lam_ref, lam = ref.get("wavelength"), wrinkle_wavelength(cand["arrays"])
    eb_ref = ref["bending_energy"]
    return {"matched": how, "points": int(len(d)), "rms": float(np.sqrt(np.mean(d * d))),
            "max": float(d.max()), "rms_rel": float(np.sqrt(np.mean(d * d))) / max(scale, 1e-300),
            "wavelength": lam,
            "wavelength_rel_error": (abs(lam - lam_ref) / lam_ref if lam and lam_ref else None),
            "bending_energy_rel_error": (abs(cand["bending_energy"] - eb_ref) / eb_ref
                                         if eb_ref > 0 else None)}


# --------------------------------------------------------------------------------------------
# The reference (stored, regenerated when missing)


def reference_path(results: Path, scene: Path, quick: bool) -> Path:
    """File of the stored reference run."""
    return results / f"speed_accuracy_reference_{scene.stem}{'_quick' if quick else ''}.npz"


def load_or_make_reference(path: Path, scene: Path, overrides: list[str],
                           log: Callable[[str], None]) -> dict[str, Any]:
    """Read the stored reference if its settings match, else run and store it."""
    key = json.dumps({"scene": str(scene.resolve()), "overrides": overrides, "version": 3})
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) == key:
                log(f"reference: {path.name} (stored)")
                meta = json.loads(str(data["meta"]))
                return {**meta, "arrays": {k: data[k] for k in ("rest", "x", "target",
                                                                "faces")}}
    log(f"reference: running {' '.join(overrides)} ...")
    ref = run_config(scene, overrides)
    ref["wavelength"] = wrinkle_wavelength(ref["arrays"])
    meta = {k: v for k, v in ref.items() if k != "arrays"}
    np.savez(path, key=np.array(key), meta=np.array(json.dumps(meta)), **ref["arrays"])
    log(f"reference: {ref['vertices']} vertices, {ref['time_per_frame']:.2f} s/frame, "
        f"stored in {path.name}")
    return ref


# --------------------------------------------------------------------------------------------
# Pareto front, table, plot


def converged(row: dict[str, Any]) -> bool:
    """Whether every frame's shell solve of a row converged (rows without the record: yes)."""
    return all(c is not False for c in row.get("shell_converged", []))


def run_time(row: dict[str, Any]) -> float:
    """Wall time [s] of all frames of a row: every row reaches the same final load, so this
    (not the time per frame) compares settings with different frame counts fairly."""
    return float(sum(row["frame_times"]))


def pareto(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Converged rows not dominated in (run time, rms_rel): no other row is at least as
    fast and at least as accurate and strictly better in one; sorted by time.

    Rows whose shell solve stopped unconverged (an iteration cap) are left out: their
    distance to the reference is not an accuracy the setting can promise. A slower row must
    lower the error by more than ``PARETO_MARGIN`` (relative) to count as more accurate.
    """
    ok = sorted((r for r in rows if r.get("rms_rel") is not None and converged(r)),
                key=lambda r: (run_time(r), r["rms_rel"]))
    front: list[dict[str, Any]] = []
    for r in ok:
        if not front or r["rms_rel"] < (1.0 - PARETO_MARGIN) * front[-1]["rms_rel"]:
            front.append(r)
    return front


def _fmt(value: Any, spec: str = ".3g") -> str:
    """Format a number (or '-' for None)."""
    return "-" if value is None else format(value, spec)


def markdown_table(front: list[dict[str, Any]]) -> str:
    """Markdown table of the Pareto-optimal settings."""
    lines = ["| setting | overrides | frames | s/frame | run s | peak MiB | rms_rel | max [m] | "
             "E_B rel | lambda [m] | shell its |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in front:  # shell its: shell Newton iterations summed over the frames
        lines.append(f"| {r['name']} | `{' '.join(r['overrides']) or '(scene)'}` | "
                     f"{len(r['frame_times'])} | {r['time_per_frame']:.3g} | "
                     f"{run_time(r):.3g} | {r['peak_rss_mib']:.0f} | "
                     f"{_fmt(r['rms_rel'])} | {_fmt(r['max'])} | "
                     f"{_fmt(r['bending_energy_rel_error'])} | {_fmt(r['wavelength'])} | "
                     f"{sum(i or 0 for i in r['shell_iterations'])} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict[str, Any]], front: list[dict[str, Any]], path: Path) -> None:
    """Pareto plot: run time vs rms_rel (log-log), one colour per knob."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    groups = sorted({r["group"] for r in rows if r.get("rms_rel")})
    colors = plt.get_cmap("tab20")(np.linspace(0.0, 1.0, max(len(groups), 1)))
    for g, color in zip(groups, colors, strict=False):
        for ok, marker in ((True, "o"), (False, "x")):
            pts = [r for r in rows if r["group"] == g and r.get("rms_rel")
                   and converged(r) == ok]
            if pts:
                ax.scatter([run_time(r) for r in pts], [r["rms_rel"] for r in pts],
                           color=color, marker=marker,
                           label=g if ok else f"{g} (unconverged)")
    ax.plot([run_time(r) for r in front], [r["rms_rel"] for r in front], "k--",
            lw=1, label="Pareto front")
    for r in front:
        ax.annotate(r["name"], (run_time(r), r["rms_rel"]), fontsize=7)
    ax.set(xscale="log", yscale="log", xlabel="wall time of all frames (same final load) [s]",
           ylabel="shell position RMS error / reference RMS displacement")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=150)
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# Main


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line flags."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", type=Path, default=Path("scenes/default.toml"))
    p.add_argument("--quick", action="store_true", help="tiny sizes (seconds), few knobs")
    p.add_argument("--levels", type=int, nargs="+", default=None,
                   help="subdivision levels swept (default 0 1 2; --quick 0 1)")
    p.add_argument("--ref-levels", type=int, default=None,
                   help="subdivision levels of the reference (default 3; --quick 2)")
    p.add_argument("--only", nargs="+", default=None, help="only these knob groups")
    p.add_argument("--set", dest="overrides", action="append", default=[],
                   metavar="KEY=VALUE", help="scene override applied to every run")
    p.add_argument("--out", type=Path, default=RESULTS / "speed_accuracy.json")
    p.add_argument("--from-json", action="store_true",
                   help="only redo the Pareto front, table and plot of the JSON in --out")
    return p.parse_args(argv)


def summarize(doc: dict[str, Any], out: Path) -> str:
    """Pareto front of ``doc``'s rows into ``doc``, JSON, Markdown table and plot; the table."""
    front = pareto([r for r in doc["rows"] if "error" not in r])
    doc["pareto"] = [r["name"] for r in front]
    out.write_text(json.dumps(doc, indent=2) + "\n")
    table = markdown_table(front)
    out.with_name(out.stem + "_pareto.md").write_text(table)
    plot([r for r in doc["rows"] if "error" not in r], front, out.with_suffix(".png"))
    return table


def run_row(scene: Path, base: list[str], config: Config, ref: dict[str, Any]
            ) -> dict[str, Any]:
    """Run one configuration and compare it; a failed solve becomes a row with its error."""
    row: dict[str, Any] = {"name": config.name, "group": config.group,
                           "overrides": list(config.overrides)}
    try:
        result = run_config(scene, [*base, *config.overrides])
    except (SolverError, InputError) as exc:
        return {**row, "error": f"{type(exc).__name__}: {exc}"}
    except Exception as exc:  # noqa: BLE001  (a crash of one setting is a result too)
        return {**row, "error": "".join(traceback.format_exception_only(exc)).strip()}
    arrays_free = {k: v for k, v in result.items() if k != "arrays"}
    return {**row, **arrays_free, **errors(ref, result)}


def print_row(r: dict[str, Any]) -> None:
    """One line of the table."""
    if "error" in r:
        print(f"{r['name']:28s} FAILED {r['error'][:90]}", flush=True)
        return
    print(f"{r['name'] + ('' if converged(r) else ' (unconv.)'):28s} {r['vertices']:7d} "
          f"{r['time_per_frame']:9.3f} "
          f"{r['peak_rss_mib']:8.0f} {r['rms_rel']:9.3e} {r['max']:9.3e} "
          f"{_fmt(r['bending_energy_rel_error'], '9.3e')} {_fmt(r['wavelength'], '8.4f')} "
          f"{sum(i or 0 for i in r['shell_iterations']):5d}", flush=True)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Reference, sweep, table, JSON, plot; return the JSON document."""
    args = parse_args(argv)
    if args.from_json:
        doc = json.loads(args.out.read_text())
        print("Pareto-optimal settings:\n" + summarize(doc, args.out))
        return doc
    levels = args.levels or ([0, 1] if args.quick else [0, 1, 2])
    ref_levels = args.ref_levels if args.ref_levels is not None else (2 if args.quick else 3)
    base = [*(QUICK_BASE if args.quick else []), *args.overrides]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    run_config(args.scene, [*base, "shell.subdivision.levels=0", "time.frames=1"])  # JIT warm-up
    ref = load_or_make_reference(reference_path(args.out.parent, args.scene, args.quick),
                                 args.scene, [*base, *REFERENCE,
                                              f"shell.subdivision.levels={ref_levels}"], print)
    print(f"{'setting':28s} {'verts':>7s} {'s/frame':>9s} {'peakMiB':>8s} {'rms_rel':>9s} "
          f"{'max[m]':>9s} {'E_B rel':>9s} {'lambda':>8s} {'its':>5s}")
    rows = []
    for config in sweep(levels, args.quick, args.only):
        rows.append(run_row(args.scene, base, config, ref))
        print_row(rows[-1])
    doc = {"scene": str(args.scene), "quick": args.quick, "base_overrides": base,
           "reference": {k: v for k, v in ref.items() if k != "arrays"} | {
               "levels": ref_levels, "overrides": REFERENCE},
           "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                       "note": "serial runs, machine possibly shared (timings contended)"},
           "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
           "rows": rows}
    print("\nPareto-optimal settings:\n" + summarize(doc, args.out))
    return doc


if __name__ == "__main__":
    main()
