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


SPLIT_SHELL_FAILS = """
import sys
import wrinkles.cli as cli
from meshes.errors import SolverError
from models.backend import MPI
from solvers.decomposition.split_newton import SplitShellEnergy

cli.AGREE_SECONDS = 2.0
evaluate, calls = SplitShellEnergy.evaluate, [0]

def failing(self, x, order=2, hessian=None):
    calls[0] += 1
    if MPI.COMM_WORLD.rank == 1 and calls[0] == 3:
        raise SolverError("forced failure in the shell stencils of rank 1")
    return evaluate(self, x, order, hessian)

SplitShellEnergy.evaluate = failing
sys.exit(cli.main(sys.argv[1:]))
"""


@pytest.mark.mpi
def test_a_split_shell_failing_on_one_rank_ends_every_rank_with_exit_2(mpiexec, tmp_path):
    """``mpiexec -n 2 wrinkles run`` with the shell split over the ranks: rank 1 alone fails
    inside a shell Newton iteration (rank 0 then waits in the next reduction); the job ends
    with exit 2 and rank 1's one-line message, no hang, no traceback."""
    scene = cli.Path(__file__).resolve().parents[2] / "scenes" / "default.toml"
    proc = mpiexec(["-c", SPLIT_SHELL_FAILS, "run", str(scene), "--frames", "1",
                    "--out", str(tmp_path / "out"), "--set", "output.render=false"],
                   n=2, timeout=180)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "[rank 1] error: forced failure in the shell stencils of rank 1" in proc.stderr
    assert "Traceback" not in proc.stderr
