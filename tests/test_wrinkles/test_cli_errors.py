"""Exit-code contract of ``wrinkles.cli.main``: in process, and failures on some MPI ranks."""

from __future__ import annotations

import pytest

import wrinkles.cli as cli
from meshes.errors import InputError, SolverError


@pytest.mark.parametrize(("error", "code"), [
    (InputError("scene.toml: material.E must be > 0"), 1),
    (SolverError("body step failed\nat t=0.1"), 2),
    (ZeroDivisionError("a bug"), 2),
])
def test_main_maps_errors_to_exit_codes(monkeypatch, capsys, error, code):
    def failing(_args):
        raise error

    monkeypatch.setitem(cli.COMMANDS, "run", failing)
    assert cli.main(["run", "any.toml"]) == code
    err = capsys.readouterr().err
    if isinstance(error, InputError | SolverError):
        assert err == f"error: {' '.join(str(error).split())}\n"  # one line, no traceback
    else:
        assert "Traceback" in err and "ZeroDivisionError: a bug" in err
        assert err.rstrip().splitlines()[-1].startswith("error: unexpected ZeroDivisionError")


def test_help_exits_zero(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["run", "--help"])
    assert info.value.code == 0
    assert "--set KEY=VALUE" in capsys.readouterr().out


SCRIPT = """
import sys
import wrinkles.cli as cli
from models.backend import MPI
from meshes.errors import InputError

cli.AGREE_SECONDS = 2.0
mode = sys.argv[1]

def fake_run(args):
    comm = MPI.COMM_WORLD
    if mode == "all" or comm.rank == 1:
        raise InputError("bad input seen by rank %d" % (0 if mode == "all" else comm.rank))
    comm.barrier()  # rank 0 would wait here forever for rank 1
    return 0

cli.COMMANDS["run"] = fake_run
sys.exit(cli.main(["run", "x.toml"]))
"""


@pytest.mark.mpi
def test_error_on_all_ranks_reported_once(mpiexec):
    proc = mpiexec(["-c", SCRIPT, "all"], n=2, timeout=120)
    assert proc.returncode == 1
    assert proc.stderr == "error: bad input seen by rank 0\n"


@pytest.mark.mpi
def test_error_on_one_rank_aborts_instead_of_hanging(mpiexec):
    proc = mpiexec(["-c", SCRIPT, "one"], n=2, timeout=120)
    assert proc.returncode == 1
    assert "[rank 1] error: bad input seen by rank 1\n" in proc.stderr
    assert "Traceback" not in proc.stderr
