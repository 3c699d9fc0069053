"""Every external mesh through ``wrinkles run``, as a user would try it.

For each mesh file of ``--dir`` (default ``../shared/meshes_external``: meshes written by
other projects, with their own formats, scales, up axes and cell types) a scene is written
that drops the body onto a frictionless floor at its lowest point with a stiff skin
(:func:`scene_text`: soft Neo-Hookean body, implicit Euler, one subdivision level, skin
thickness 1/400 of the body's extent and 1000 times its Young's modulus), and
``python -m wrinkles run SCENE --out DIR`` runs it in a subprocess. The table gives per file
the exit code, the frames completed (``summary.json``), the wall time, the shell's size and
the first error or warning lines the user sees. Meshes a correct program refuses (hexahedra,
pyramids, wedges) must exit 1 with the cell types named.

Writes ``benchmarks/results/external_meshes.json`` (``--out``).

Usage::

    python benchmarks/external_meshes.py
    python benchmarks/external_meshes.py --frames 4 --files ipc_bunny.msh
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import meshio
import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "external_meshes.json"
MESH_DIR = REPO.parent / "shared" / "meshes_external"
UP: dict[str, str] = {"ipc_bunny.msh": "y"}
"""Up axis of the meshes that are not z-up (from the directory's README)."""
SUFFIXES: tuple[str, ...] = (".mesh", ".msh", ".vtk", ".vtu", ".xdmf")


def scene_text(path: Path, up: str, frames: int) -> str:
    """The scene of one mesh: dropped onto a floor at its lowest point, with a skin."""
    points = np.asarray(meshio.read(path).points, dtype=float)
    axis = "xyz".index(up)
    extent = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    floor = [0.0, 0.0, 0.0]
    floor[axis] = float(points[:, axis].min())
    return f"""title = "{path.name} dropped on a floor, with a skin"
up = "{up}"
[mesh]
file = "{path}"
[material]
model = "neo_hookean"
E = 5.0e4
nu = 0.3
density = 100.0
[body]
dynamics = "implicit_euler"
dt = 0.005
[[body.contacts]]
obstacle = "plane"
point = {floor}
[time]
frames = {frames}
steps_per_frame = 2
[output]
render = false
[shell]
imperfection = 1e-3
[shell.subdivision]
levels = 1
[shell.skin]
E = 5.0e7
nu = 0.3
thickness = {extent / 400.0:.6g}
[shell.energy]
k_P = 1.0e3
[shell.solver]
rtol = 1e-6
max_iterations = 300
"""


def messages(stderr: str, limit: int = 3) -> list[str]:
    """The first ``limit`` error or warning lines the user saw."""
    lines = [ln.strip() for ln in stderr.splitlines()
             if ln.startswith(("error:", "warning:")) or "Warning:" in ln]
    return lines[:limit]


def run_one(path: Path, frames: int, work: Path, timeout: float) -> dict[str, Any]:
    """Write the scene of ``path``, run it, and read what the user gets."""
    up = UP.get(path.name, "z")
    row: dict[str, Any] = {"file": path.name, "up": up}
    try:
        text = scene_text(path, up, frames)
    except Exception as exc:  # noqa: BLE001  (meshio refuses the file: the CLI will say why)
        text = f'[mesh]\nfile = "{path}"\n'
        row["meshio"] = f"{type(exc).__name__}: {exc}"
    scene, out = work / f"{path.stem}.toml", work / path.stem
    scene.write_text(text)
    started = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "wrinkles", "run", str(scene), "--out",
                           str(out)], cwd=REPO, capture_output=True, text=True, timeout=timeout)
    row.update(exit=proc.returncode, wall_s=round(time.perf_counter() - started, 1),
               messages=messages(proc.stderr))
    summary = out / "summary.json"
    if summary.is_file():
        doc = json.loads(summary.read_text())
        row.update(frames=len(doc.get("frames", [])), status=doc.get("run", {}).get("status"),
                   shell_vertices=doc.get("run", {}).get("shell", {}).get("vertices"),
                   shell_iterations=sum(f.get("details", {}).get("shell_iterations", 0)
                                        for f in doc.get("frames", [])))
    return row


def main(argv: list[str] | None = None) -> int:
    """Run every mesh, print the table, write the JSON."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dir", type=Path, default=MESH_DIR)
    p.add_argument("--files", nargs="*", default=None, help="file names in --dir (default all)")
    p.add_argument("--frames", type=int, default=2)
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds per run")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    files = sorted(f for f in args.dir.iterdir() if f.suffix in SUFFIXES) if not args.files \
        else [args.dir / f for f in args.files]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for path in files:
            row = run_one(path, args.frames, Path(tmp), args.timeout)
            rows.append(row)
            print(f"{row['file']:42s} exit {row['exit']}  frames {row.get('frames', '-')}/"
                  f"{args.frames}  {row['wall_s']:7.1f} s  shell {row.get('shell_vertices', '-')}"
                  f"  {' | '.join(row['messages'])[:160]}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"frames": args.frames, "rows": rows}, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
