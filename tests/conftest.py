"""Shared test fixtures."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from wrinkles.launch import mpiexec_path

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded random generator, so failures reproduce."""
    return np.random.default_rng(20261122)


def _mpiexec_path() -> str:
    found = mpiexec_path()
    if found is None:
        pytest.skip("mpiexec not found next to the interpreter or on PATH")
    return found


@pytest.fixture
def mpiexec():
    """Run ``mpiexec -n N python ARGS`` with a timeout; return the CompletedProcess.

    Usage: ``mpiexec(["-m", "wrinkles.cli", "run", ...], n=2, timeout=300)``.
    """

    def run(args: list[str], n: int = 2, timeout: float = 600, cwd: Path | None = None,
            check: bool = False) -> subprocess.CompletedProcess[str]:
        cmd = [_mpiexec_path(), "-n", str(n), sys.executable, *args]
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout,
                              cwd=cwd or REPO, env=env)
        if check and proc.returncode != 0:
            raise AssertionError(f"{cmd} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
        return proc

    return run
