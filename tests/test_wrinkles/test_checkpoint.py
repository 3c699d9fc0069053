"""``Body.set_state`` and the checkpoint file: a restored run continues like the straight one.

Newmark (beta 1/4, gamma 1/2) carries the acceleration from step to step; restoring it with
``Body.set_state`` marks it valid so the restarted run takes the very same steps (no
recomputed ``a_0``). The checkpoint also carries named arrays of other stages.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from meshes.errors import InputError
from meshes.structured import structured_box
from models.backend import MPI, mesh_from_arrays
from models.body import BodyOptions, PinSpec
from models.materials import Material
from solvers.body import Body
from solvers.body_newton import NewtonOptions
from wrinkles.checkpoint import gather_state, read_state, scatter_state, with_arrays, write_state

STEPS = 6


def swinging_block(dynamics: str) -> Body:
    """A 0.1 m soft block clamped at x = 0, swinging down under gravity (large rotations)."""
    tet = structured_box((4, 2, 2), (0.1, 0.05, 0.05))
    mesh = mesh_from_arrays(MPI.COMM_WORLD, tet.points, tet.tets)
    pins = (PinSpec(point=(0.0, 0.0, 0.0), normal=(1.0, 0.0, 0.0), tol=1e-9),)
    options = BodyOptions(degree=1, dynamics=dynamics, dt=0.02, gravity=(0.0, 0.0, -9.81),
                          pins=pins)
    return Body(mesh, Material(E=2e3, nu=0.3, density=1000.0), options,
                NewtonOptions(rtol=1e-10, atol=1e-12))


@pytest.mark.parametrize("dynamics", ["newmark", "implicit_euler", "static"])
def test_checkpointed_run_continues_like_the_straight_run(tmp_path, dynamics):
    straight = swinging_block(dynamics)
    reports = [straight.step() for _ in range(STEPS)]
    first = swinging_block(dynamics)
    for _ in range(STEPS // 2):
        first.step()
    write_state(tmp_path / "checkpoint.h5", gather_state(first, STEPS // 2))
    second = swinging_block(dynamics)
    scatter_state(second, read_state(tmp_path / "checkpoint.h5"))
    resumed = [second.step() for _ in range(STEPS // 2)]
    scale = np.abs(straight.u.x.array).max()
    err = np.abs(second.u.x.array - straight.u.x.array).max() / scale
    print(f"{dynamics}: |u| = {scale:.3e} m, relative difference after restart {err:.2e}, "
          f"iterations straight {[r.newton_iterations for r in reports[STEPS // 2:]]} "
          f"resumed {[r.newton_iterations for r in resumed]}")
    assert scale > 1e-3  # it moved
    assert second.t == pytest.approx(straight.t, abs=1e-15)
    # dynamics: same state, same iterates (bitwise); statics: the load-step extrapolation
    # rate is not checkpointed, so the Newton start differs: equal to solver tolerance
    assert err <= (1e-14 if dynamics != "static" else 1e-8)
    if dynamics == "newmark":
        err_a = np.abs(second.a.x.array - straight.a.x.array).max()
        assert err_a <= 1e-12 * np.abs(straight.a.x.array).max()


def test_set_state_refuses_wrong_sizes_and_non_finite_values():
    body = swinging_block("newmark")
    n = body.u.x.array.size
    good = np.zeros(n)
    with pytest.raises(InputError, match="set_state: u must be"):
        body.set_state(0.0, np.zeros(n + 3), good, good)
    with pytest.raises(InputError, match="set_state: a must be"):
        body.set_state(0.0, good, good, np.full(n, np.nan))
    with pytest.raises(InputError, match="set_state: t must be finite"):
        body.set_state(np.inf, good, good, good)
    body.set_state(0.5, good + 1e-3, good, good)
    assert body.t == 0.5 and np.all(body.u.x.array == 1e-3)


def test_checkpoint_keeps_named_arrays_of_other_stages(tmp_path, rng):
    body = swinging_block("implicit_euler")
    body.step()
    positions, ids = rng.standard_normal((50, 3)), np.arange(7)
    state = with_arrays(gather_state(body, 1), "shell", {"positions": positions})
    state = with_arrays(state, "rigid", {"ids": ids})
    write_state(tmp_path / "c.h5", state)
    back = read_state(tmp_path / "c.h5")
    assert back.frame == 1 and back.time == pytest.approx(0.02, abs=1e-15)
    np.testing.assert_array_equal(back.arrays["shell"]["positions"], positions)
    np.testing.assert_array_equal(back.arrays["rigid"]["ids"], ids)
    for name, values in state.fields.items():
        np.testing.assert_array_equal(back.fields[name], values)
    with pytest.raises(InputError, match="invalid stage or array name"):
        with_arrays(state, "shell/x", {"positions": positions})


def test_format_1_checkpoint_still_reads_and_garbage_is_refused(tmp_path):
    body = swinging_block("implicit_euler")
    state = gather_state(body, 0)
    with h5py.File(tmp_path / "old.h5", "w") as h5:  # the layout before the stages group
        h5.attrs["frame"], h5.attrs["time"] = 0, 0.0
        h5["coords"] = state.coords
        for name, values in state.fields.items():
            h5[f"fields/{name}"] = values
    assert read_state(tmp_path / "old.h5").arrays == {}
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    with pytest.raises(InputError, match="bad.h5: unreadable checkpoint"):
        read_state(tmp_path / "bad.h5")
