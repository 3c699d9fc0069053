"""Ball on sofa from the CLI (issue 5, item 1): scenes/ball_sofa_coarse.toml, two-way rigid ball.

The coarse sofa (h = 0.2 m) rests on a frictionless ground contact, its bottom held in x and y
by pins; a 5 kg ball (r = 0.15 m)
starts 3 cm above the seat at 1 m/s down, hits it in frame 3 (dt = 5 ms, 2 steps per frame)
and rebounds by frame 7. The shell is kept at one subdivision level and not rendered here
(test time).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest
from support import FAST, REPO, SCENE, wrinkles

G, DT, C0, W0 = 9.81, 0.005, 0.63, -1.0


def frames_of(out: Path) -> list[dict]:
    return json.loads((out / "summary.json").read_text())["frames"]


@pytest.fixture(scope="module")
def ten_frames(tmp_path_factory) -> tuple[subprocess.CompletedProcess[str], Path]:
    out = tmp_path_factory.mktemp("ball") / "out"
    proc = wrinkles("run", str(SCENE), "--frames", "10", "--out", str(out), *FAST)
    assert proc.returncode == 0, proc.stderr
    return proc, out


def test_the_demo_as_shipped_sets_up_without_a_warning(tmp_path):
    """``make demo`` prints no warning: at the scene's own two subdivision levels its skin's
    wrinkle wavelength spans 4.5 shell edges (the set-up warns below 4, as it did for the 3 mm
    skin's 3.0; docs/notes/scenes.md)."""
    proc = wrinkles("run", str(SCENE), "--frames", "1", "--out", str(tmp_path / "out"),
                    "--set", "output.render=false")
    assert proc.returncode == 0, proc.stderr
    assert "warning" not in proc.stderr.lower(), proc.stderr
    thin = wrinkles("run", str(SCENE), "--frames", "1", "--out", str(tmp_path / "thin"),
                    "--set", "output.render=false", "--set", "shell.skin.thickness=3e-3")
    assert "spans only 3.0 shell edges" in thin.stderr, thin.stderr


def ball(frame: dict) -> dict:
    return frame["details"]["balls"][0]


def test_free_flight_before_contact_is_exact(ten_frames):
    """Frames 1-2: no contact force, one body solve per step, and the implicit Euler free fall
    c_n = c_0 + w_0 t + (-g) h^2 n (n+1)/2, w_n = w_0 - g t exactly."""
    frames = frames_of(ten_frames[1])
    for f in frames[:2]:
        n = round(f["time"] / DT)
        b = ball(f)
        assert b["contact_force"] == [0.0, 0.0, 0.0]
        assert f["details"]["rigid_iterations"] == [1, 1]
        assert b["center"][2] == pytest.approx(C0 + W0 * f["time"] - G * DT**2 * n * (n + 1) / 2,
                                               abs=1e-12)
        assert b["velocity"][2] == pytest.approx(W0 - G * f["time"], abs=1e-12)


def test_ball_decelerates_on_contact_and_rebounds(ten_frames):
    frames = frames_of(ten_frames[1])
    vz = np.array([ball(f)["velocity"][2] for f in frames])
    fz = np.array([ball(f)["contact_force"][2] for f in frames])
    hit = int(np.argmax(fz > 0.0))  # first frame with a contact force
    assert hit == 2  # frame 3 (measured)
    impact = vz[hit - 1] - G * 2 * DT  # free-fall speed it would have at the end of frame 3
    assert vz[hit] > impact  # decelerated within the contact frame (measured -1.250 > -1.294)
    assert np.all(np.diff(vz[hit:9]) > 0.0)  # pushed up while in contact (frames 3-9)
    assert np.all(fz[hit:9] > 10.0)  # measured 44 .. 303 N, 70 N in frame 9
    assert 0.3 * abs(impact) < vz.max() < abs(impact)  # rebound slower than impact (0.80)
    assert np.all(np.abs([ball(f)["center"][:2] for f in frames] - np.array([1.0, 0.35]))
                  < 2e-3)  # near-vertical (the sofa is not symmetric in y): measured 8e-4


def test_penetration_stays_below_two_percent_of_the_radius(ten_frames):
    """Penetration = max over the deformed boundary triangles of r - dist(c, T), / r."""
    pen = np.array([ball(f)["penetration"] for f in frames_of(ten_frames[1])])
    assert pen[:2].max() == 0.0
    assert 0.005 < pen.max() < 0.02  # measured 0.0137 (penalty at 6th-degree facet points)


def test_momentum_balance_impulse_on_ball_equals_sofa_plus_ground(ten_frames):
    """Summed over all steps: the ball's momentum change minus gravity (impulse on the ball)
    is minus the sofa's momentum change minus its gravity and the ground's impulse (floor
    contact + pin reactions), to 1e-6 relative, in all three components; both equal the
    bookkept contact impulse sum h R."""
    frames = frames_of(ten_frames[1])
    scale = max(np.abs(f["details"]["momentum"]["ball_impulse"]).max() for f in frames)
    assert scale > 10.0  # measured 13.5 N s (the ball's momentum turned from -6.3 to +3.6)
    for f in frames:
        m = {k: np.array(v) for k, v in f["details"]["momentum"].items()}
        np.testing.assert_allclose(m["ball_impulse"] + m["body_impulse"], 0.0, rtol=0,
                                   atol=1e-9 * scale)  # measured < 3e-10 N s (issue: 1e-6)
        np.testing.assert_allclose(m["body_impulse"], m["contact_impulse"], rtol=0,
                                   atol=1e-9 * scale)
    ground = np.array(frames[-1]["details"]["momentum"]["ground_impulse"])
    assert ground[2] > 1.0  # the floor carries the sofa (and the ball): measured 64.5 N s
    assert np.abs(ground[:2]).max() > 0.05  # the pins hold it sideways: measured 0.18 N s


@pytest.fixture(scope="module")
def two_way_frames(tmp_path_factory) -> Path:
    """The ten frames with the shell coupled two-way (monolithic: the shell is in every
    body solve of the rigid coupling), the coupled solves to rtol 1e-8."""
    out = tmp_path_factory.mktemp("ball_two_way") / "out"
    proc = wrinkles("run", str(SCENE), "--frames", "10", "--out", str(out), *FAST,
                    "--set", 'shell.coupling.mode="two_way"', "--set", "shell.solver.rtol=1e-8")
    assert proc.returncode == 0, proc.stderr
    return out


def test_two_way_shell_keeps_the_impulse_ledger(two_way_frames):
    """With the shell coupled two-way the run reaches frame 10 with every coupled solve
    converged, and the ledger closes: ball + body impulse = 0 and body = contact impulse to
    1e-7 of the 13 N s exchanged, all components (measured 7.1e-12 N s at frame 10). The
    massless shell passes on a net force of the size of the coupled solve's final gradient:
    with the scene's rtol 1e-6 a solve that stops at a third of its tolerance left 2.9e-6 N s,
    hence rtol 1e-8 here; without the pins' share of the shell force in their reaction
    (:meth:`solvers.body.Body.set_interface_force`) it was 0.4 N s."""
    frames = frames_of(two_way_frames)
    assert len(frames) == 10
    assert all(f["details"]["coupling_converged"] for f in frames)
    scale = max(np.abs(f["details"]["momentum"]["ball_impulse"]).max() for f in frames)
    assert scale > 10.0
    for f in frames:
        m = {k: np.array(v) for k, v in f["details"]["momentum"].items()}
        print(f["frame"], m["ball_impulse"] + m["body_impulse"],
              m["body_impulse"] - m["contact_impulse"])
        np.testing.assert_allclose(m["ball_impulse"] + m["body_impulse"], 0.0, rtol=0,
                                   atol=1e-7 * scale)
        np.testing.assert_allclose(m["body_impulse"], m["contact_impulse"], rtol=0,
                                   atol=1e-7 * scale)


def test_coupling_iterates_only_in_contact(ten_frames):
    frames = frames_of(ten_frames[1])
    its = [f["details"]["rigid_iterations"] for f in frames]
    assert all(k == 1 for step in its[:2] for k in step)
    assert all(2 <= k <= 5 for step in its[3:] for k in step)  # measured 3-4 body solves
    tol = 1e-8 * 0.15
    assert all(f["details"]["rigid_mismatch"] <= tol for f in frames)


def test_body_solves_integrate_the_contacts_on_a_few_facets(ten_frames):
    """The summary's contact facet selection: measured 18 % of the facets, no repeat."""
    run = json.loads((ten_frames[1] / "summary.json").read_text())["run"]
    contact = run["contact_facets"]
    print(f"contact facets: {contact}")
    assert contact["solves"] >= 20  # two steps per frame, several body solves per step
    assert 0.05 < contact["share"] < 0.4
    assert contact["retries"] == 0


def test_checkpoint_holds_the_ball_and_resume_continues_it(ten_frames, tmp_path):
    """Stop after 5 frames, resume to 8: the ball's state in frames 6-8 equals the
    uninterrupted run's (same arithmetic: to 1e-12), the shell's energies to 1e-9."""
    ref = frames_of(ten_frames[1])
    out = tmp_path / "out"
    first = wrinkles("run", str(SCENE), "--frames", "5", "--out", str(out), *FAST)
    assert first.returncode == 0, first.stderr
    with h5py.File(out / "checkpoint.h5", "r") as h5:
        np.testing.assert_allclose(h5["stages/rigid/center"][...][0], ball(ref[4])["center"],
                                   rtol=0, atol=1e-14)
    second = wrinkles("run", str(SCENE), "--frames", "8", "--out", str(out), "--resume", *FAST)
    assert second.returncode == 0, second.stderr
    got = frames_of(out)
    assert len(got) == 8
    for f, r in zip(got[5:], ref[5:8], strict=True):
        for key in ("center", "velocity", "contact_force"):
            np.testing.assert_allclose(ball(f)[key], ball(r)[key], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(f["details"]["momentum"]["ball_impulse"],
                                   r["details"]["momentum"]["ball_impulse"], atol=1e-10)
        # the shell's first resumed frame factorises afresh where the straight run reused
        # frame 5's factorisation (docs/notes/factor-reuse.md): the same shells to tolerance
        assert f["details"]["shell_converged"]
        assert f["details"]["shell_energy"] == pytest.approx(r["details"]["shell_energy"],
                                                             rel=1e-9)


@pytest.mark.slow
def test_full_scene_comes_to_rest(tmp_path):
    """scenes/ball_sofa.toml (h = 0.1 m sofa, guided ball dropped from 30 cm, 75 frames of
    20 ms) with the shell reduced to the coarse surface: the ball is at rest (|v| < 5 mm/s)
    from frame 59 on and its contact force carries its weight (measured: 4 min 51 s wall on
    the contended machine without the shell)."""
    out = tmp_path / "out"
    proc = wrinkles("run", str(REPO / "scenes" / "ball_sofa.toml"), "--out", str(out),
                    "--set", "shell.subdivision.levels=0", "--set", "output.render=false",
                    "--set", "output.xdmf=false", timeout=1800)
    assert proc.returncode == 0, proc.stderr
    frames = frames_of(out)
    assert len(frames) == 75
    speed = np.array([np.linalg.norm(ball(f)["velocity"]) for f in frames])
    assert speed[:12].max() > 2.0  # measured 2.35 m/s just before the hit
    assert speed[58:].max() < 5e-3  # measured: at rest from frame 59 (< 1 mm/s from 68)
    weight = 5.0 * G
    assert ball(frames[-1])["contact_force"][2] == pytest.approx(weight, rel=5e-3)  # 0.1 %
    assert max(ball(f)["penetration"] for f in frames) < 0.025  # measured 0.0185
    m = frames[-1]["details"]["momentum"]
    scale = np.abs(m["ball_impulse"]).max()  # 73.6 N s
    np.testing.assert_allclose(np.add(m["ball_impulse"], m["body_impulse"]), 0.0, rtol=0,
                               atol=1e-6 * scale)


def test_the_shell_reuses_its_factorisation_by_default_and_reaches_the_same_shells(ten_frames,
                                                                                  tmp_path):
    """A dynamic scene's shell Newton reuses its factorisation across iterations and frames
    (solvers.solver_choice.choose_factor_reuse; docs/notes/factor-reuse.md): against the same
    10 frames with the reuse turned off by its expert key, fewer factorisations in all and the
    same shell in every frame (energies to 1e-9, both solves converged to the scene's
    tolerance)."""
    out = tmp_path / "newton"
    proc = wrinkles("run", str(SCENE), "--frames", "10", "--out", str(out), *FAST, "--set",
                    "shell.solver.options={'newton.modified.enabled' = false}")
    assert proc.returncode == 0, proc.stderr
    reused, newton = frames_of(ten_frames[1]), frames_of(out)
    run = json.loads((ten_frames[1] / "summary.json").read_text())["run"]
    assert run["shell"]["solver"]["factor_reuse"] is True
    facts = [sum(f["details"]["shell_factorizations"] for f in fr) for fr in (reused, newton)]
    print("factorisations with / without reuse", facts)
    assert facts[0] < 0.8 * facts[1]
    for a, b in zip(reused, newton, strict=True):
        assert a["details"]["shell_converged"] and b["details"]["shell_converged"]
        assert a["details"]["shell_energy"] == pytest.approx(b["details"]["shell_energy"],
                                                             rel=1e-9)
