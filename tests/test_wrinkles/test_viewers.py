"""Every XDMF series of a run opens in the libxml2-based readers (ParaView's legacy XDMF reader).

``vtkXdmfReader`` (Xdmf2, the reader behind ParaView's "XDMF Reader" and pyvista) expands only
the XInclude namespace ``http://www.w3.org/2001/XInclude``; with dolfinx 0.11's
``https://...`` spelling the time-step grids have no mesh and the reader crashes. Each reader
runs in a subprocess, so a segfault fails the test instead of killing pytest.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from support import REPO, wrinkles

READ = """
import json, sys
import vtk
reader = vtk.vtkXdmfReader()
reader.SetFileName(sys.argv[1])
reader.UpdateInformation()
info = reader.GetOutputInformation(0)
key = vtk.vtkStreamingDemandDrivenPipeline.TIME_STEPS()
times = list(info.Get(key)) if info.Has(key) else []
points, names = [], []
for t in times or [None]:
    if t is not None:
        reader.UpdateTimeStep(t)
    else:
        reader.Update()
    data = reader.GetOutputDataObject(0)
    blocks = ([data.GetBlock(k) for k in range(data.GetNumberOfBlocks())]
              if data.IsA("vtkMultiBlockDataSet") else [data])
    data = max(blocks, key=lambda b: b.GetPointData().GetNumberOfArrays())  # the fields grid
    points.append(data.GetNumberOfPoints())
    pd = data.GetPointData()
    names = sorted(pd.GetArrayName(k) for k in range(pd.GetNumberOfArrays()))
print(json.dumps({"times": times, "points": points, "fields": names}))
"""

PYVISTA = """
import json, sys
import pyvista as pv
mesh = pv.read(sys.argv[1])
blocks = list(mesh) if isinstance(mesh, pv.MultiBlock) else [mesh]
block = max(blocks, key=lambda b: len(b.point_data))
print(json.dumps({"points": int(block.n_points), "fields": sorted(block.point_data.keys())}))
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("viewers") / "out"
    proc = wrinkles("run", str(REPO / "scenes" / "default.toml"), "--out", str(out),
                    "--frames", "2", "--set", "shell.subdivision.levels=0",
                    "--set", "output.render=false")
    assert proc.returncode == 0, proc.stderr
    return out


def read(script: str, path: Path) -> dict:
    proc = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True,
                          text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 0, f"reader exited {proc.returncode}: {proc.stderr[-2000:]}"
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize(("name", "fields"), [
    ("body.xdmf", ["displacement", "velocity"]),
    ("shell.xdmf", ["bending_energy_density", "cluster_id", "displacement", "self_intersecting"]),
])
def test_legacy_vtk_xdmf_reader_reads_every_step(run, name, fields):
    got = read(READ, run / name)
    print(name, got)
    assert got["times"] == pytest.approx([0.0, 0.25, 0.5])
    assert len(set(got["points"])) == 1 and got["points"][0] > 0
    assert got["fields"] == fields


@pytest.mark.parametrize("name", ["body.xdmf", "shell.xdmf"])
def test_pyvista_reads_the_series(run, name):
    got = read(PYVISTA, run / name)
    assert got["points"] > 0 and "displacement" in got["fields"]


def test_files_spell_the_xinclude_namespace_libxml2_expands(run):
    for name in ("body.xdmf", "shell.xdmf"):
        text = (run / name).read_text()
        assert "https://www.w3.org/2001/XInclude" not in text
        assert 'xmlns:xi="http://www.w3.org/2001/XInclude"' in text


def test_shell_steps_list_the_bending_energy_density_first(run):
    """ParaView colours a dataset by its first point scalar: the wrinkles, not cluster ids."""
    import xml.etree.ElementTree as ET

    grids = [g for g in ET.parse(run / "shell.xdmf").getroot().iter("Grid")
             if g.get("GridType") == "Uniform"]
    assert grids and all(g.find("Attribute").get("Name") == "bending_energy_density"
                         for g in grids)
