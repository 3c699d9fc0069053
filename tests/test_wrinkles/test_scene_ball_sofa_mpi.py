"""Ball on sofa on 2 and 3 MPI ranks agrees with the serial run (ball state, penetration,
balance)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from support import FAST, SCENE, wrinkles

ARGS = ["run", str(SCENE), "--frames", "5", *FAST, "--set", "output.xdmf=false"]


@pytest.fixture(scope="module")
def serial(tmp_path_factory) -> Path:
    """The serial run the rank counts are compared with."""
    out = tmp_path_factory.mktemp("serial")
    proc = wrinkles(*ARGS, "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    return out


@pytest.mark.mpi
@pytest.mark.parametrize(("ranks", "layout"), [(2, "split"), (2, "overlap"), (3, "split")])
def test_ranks_agree_with_serial(serial, ranks, layout, tmp_path, mpiexec):
    """Body and ball split over 2 and 3 ranks, or stepped on one rank beside the shell
    (``"overlap"``, the 2-rank default here, tests/test_wrinkles/test_overlap.py)."""
    parallel = tmp_path / "mpi"
    proc = mpiexec(["-m", "wrinkles", *ARGS, "--out", str(parallel),
                    "--set", f"shell.solver.layout='{layout}'"], n=ranks, timeout=300)
    assert proc.returncode == 0, proc.stderr
    a, b = (json.loads((d / "summary.json").read_text())["frames"] for d in (serial, parallel))
    run = json.loads((parallel / "summary.json").read_text())["run"]
    assert (run["ranks"], run["layout"]) == (ranks, layout)
    for fa, fb in zip(a, b, strict=True):
        ba, bb = fa["details"]["balls"][0], fb["details"]["balls"][0]
        for key in ("center", "velocity"):
            np.testing.assert_allclose(bb[key], ba[key], rtol=0, atol=1e-10)  # measured 1e-16
        np.testing.assert_allclose(bb["contact_force"], ba["contact_force"], rtol=1e-8,
                                   atol=1e-8)
        assert bb["penetration"] == pytest.approx(ba["penetration"], abs=1e-12)
        m = fb["details"]["momentum"]
        assert np.abs(np.add(m["ball_impulse"], m["body_impulse"])).max() < 1e-9
    assert max(f["details"]["balls"][0]["penetration"] for f in b) > 0.005  # in contact
