"""Physical material -> discrete shell stiffnesses k_L, k_A, k_B (with derivations and limits).

Membrane (linearised, small in-plane strain ``eps``). An edge spring of rest length ``a`` and
direction ``t`` stores ``k_L (l - a)^2 / a ~ k_L a (t . eps t)^2``. The equilateral lattice
of edge ``a`` has ``2 / (sqrt 3 a^2)`` edges per unit area in each of its three directions,
and for three directions 60 degrees apart ``sum_t (t.eps t)^2 = 3/8 ((tr eps)^2 + 2 |eps|^2)``,
so the edge energy per unit area is

    psi_L = sqrt(3) k_L / (4 a) ((tr eps)^2 + 2 |eps|^2).

Plane-stress linear elasticity stores ``psi = h (mu |eps|^2 + lambda*/2 (tr eps)^2)`` with
``mu = E / (2 (1 + nu))`` and ``lambda* = E nu / (1 - nu^2)``. Edge springs therefore give
``mu h = sqrt(3) k_L / (2 a)`` and ``lambda* = mu``: **edge springs always have Poisson ratio
1/3** (the Cauchy relation). The area term ``k_A (A - A0)^2 / A0`` stores
``k_A (tr eps)^2`` per unit area (``A / A0 - 1 ~ tr eps``), i.e. pure bulk stiffness.

Two mappings (:func:`membrane_stiffness`):

* "equibiaxial" (the default, no area term): match the equibiaxial energy
  ``E h eps^2 / (1 - nu)`` (``eps_ij = eps delta_ij`` gives ``psi_L = 2 sqrt(3) k_L eps^2 / a``):
  ``k_L = E h a / (2 sqrt(3) (1 - nu))``, ``k_A = 0``. Exact for every nu under equibiaxial
  strain and exact for all strains when nu = 1/3; for nu != 1/3 the discrete shear modulus
  is ``mu_L / mu = (1 + nu) / (2 (1 - nu))`` times the continuum one
  (:func:`shear_modulus_ratio`; e.g. 1.5 at nu = 0.5, 0.5 at nu = 0).
* "isotropic" (nu >= 1/3): edges carry the shear modulus, the area term the missing bulk
  modulus: ``k_L = E h a / (sqrt(3) (1 + nu))``, ``k_A = E h (3 nu - 1) / (4 (1 - nu^2))``.
  Exact linearised plane-stress response on the equilateral lattice for any strain.

Bending: ``k_B = D / 2 = E h^3 / (24 (1 - nu^2))`` (plate stiffness ``D = E h^3 / (12 (1 -
nu^2))``), calibration "sphere". The hinge sum ``sum_h 3 |e|^2 / (A1 + A2) theta^2`` tends to
the mean-curvature integral ``int (k1 + k2)^2 dA`` for a sphere (16 pi), so
``k_B W_B ~ D/2 int (2H)^2 dA`` there. On equilateral lattices a cylindrical bend (k2 = 0: the
shape of a wrinkle) costs 3x the plate energy with ``D / 2`` (docs/notes/hinge-bending-limit.md),
so calibration "cylinder" uses ``k_B = D / 6``: single-curvature bending is exact in the limit on
equilateral-type meshes, a sphere then gets 1/3 of the plate value. No single k_B matches both.

ARCSim's bending weight differs from ``D/2`` by a factor; :func:`bending_stiffness_from_arcsim`
converts explicitly (see its docstring for the convention assumed).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from meshes.errors import InputError

MembraneMapping = Literal["equibiaxial", "isotropic"]
BendingCalibration = Literal["sphere", "cylinder"]

BENDING_CALIBRATION: dict[str, float] = {"sphere": 0.5, "cylinder": 1.0 / 6.0}
"""k_B / D per calibration (module docstring): "sphere" D/2, "cylinder" D/6."""

ARCSIM_BENDING_FACTOR: float = 1.0 / 24.0
"""Assumed ratio of ARCSim's bending weight to ``k_B = E h^3 / (24 (1 - nu^2))`` (MISSION.md
section 4: "ARCSim's is 1/24 of this form"); not verified against ARCSim's source here."""


@dataclass(frozen=True)
class ShellMaterial:
    """Physical thin-sheet parameters.

    Attributes:
        E: Young's modulus (Pa, > 0).
        nu: Poisson ratio (-1 < nu < 1/2 for an isotropic solid; here -1 < nu < 1).
        thickness: Sheet thickness h (m, > 0).
        edge_length: Mean rest edge length a of the shell mesh (m, > 0).

    """

    E: float = 1e6
    nu: float = 1.0 / 3.0
    thickness: float = 1e-3
    edge_length: float = 1e-2

    def __post_init__(self) -> None:
        """Validate ranges, naming the field."""
        for name in ("E", "thickness", "edge_length"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"{name}: must be a finite number > 0, got {value!r}")
        if not -1.0 < self.nu < 1.0:
            raise InputError(f"nu: must lie in (-1, 1), got {self.nu!r}")


def membrane_stiffness(mat: ShellMaterial,
                       mapping: MembraneMapping = "equibiaxial") -> tuple[float, float]:
    """``(k_L, k_A)`` matching plane-stress elasticity (module docstring for the derivation).

    Args:
        mat: Material and mesh size.
        mapping: "equibiaxial" (``k_L = E h a / (2 sqrt 3 (1 - nu))``, ``k_A = 0``) or
            "isotropic" (``k_L = E h a / (sqrt 3 (1 + nu))``,
            ``k_A = E h (3 nu - 1) / (4 (1 - nu^2))``; needs nu >= 1/3).

    Raises:
        InputError: unknown mapping, or "isotropic" with nu < 1/3 (would need k_A < 0).

    """
    e, nu, h, a = mat.E, mat.nu, mat.thickness, mat.edge_length
    if mapping == "equibiaxial":
        return e * h * a / (2.0 * np.sqrt(3.0) * (1.0 - nu)), 0.0
    if mapping == "isotropic":
        if nu < 1.0 / 3.0 - 1e-12:
            raise InputError(f"nu: the isotropic membrane mapping needs nu >= 1/3 (edge springs "
                             f"alone have Poisson ratio 1/3), got {nu}")
        return (e * h * a / (np.sqrt(3.0) * (1.0 + nu)),
                max(e * h * (3.0 * nu - 1.0) / (4.0 * (1.0 - nu * nu)), 0.0))
    raise InputError(f"mapping: expected 'equibiaxial' or 'isotropic', got {mapping!r}")


def edge_lattice_moduli(k_L: float, k_A: float, edge_length: float) -> tuple[float, float]:
    """In-plane ``(mu h, lambda* h)`` of edge springs + area term on an equilateral lattice.

    ``psi = sqrt(3) k_L / (4 a) ((tr eps)^2 + 2 |eps|^2) + k_A (tr eps)^2``
    ``= mu h |eps|^2 + lambda* h / 2 (tr eps)^2``.
    """
    mu_h = np.sqrt(3.0) * k_L / (2.0 * edge_length)
    return mu_h, mu_h + 2.0 * k_A


def shear_modulus_ratio(mat: ShellMaterial) -> float:
    """``mu_discrete / mu`` of the "equibiaxial" mapping: ``(1 + nu) / (2 (1 - nu))``.

    1 at nu = 1/3; the error of that mapping under shear for other Poisson ratios.
    """
    k_L, k_A = membrane_stiffness(mat, "equibiaxial")
    mu_h, _ = edge_lattice_moduli(k_L, k_A, mat.edge_length)
    return float(mu_h / (mat.E * mat.thickness / (2.0 * (1.0 + mat.nu))))


def plate_bending_stiffness(mat: ShellMaterial) -> float:
    """Plate bending stiffness ``D = E h^3 / (12 (1 - nu^2))``."""
    return mat.E * mat.thickness**3 / (12.0 * (1.0 - mat.nu**2))


def bending_stiffness(mat: ShellMaterial, calibration: BendingCalibration = "sphere") -> float:
    """Hinge bending stiffness k_B from the plate stiffness D (module docstring).

    ``D / 2 = E h^3 / (24 (1 - nu^2))`` ("sphere", mean curvature) or ``D / 6`` ("cylinder":
    single-curvature bending on equilateral lattices).

    Raises:
        InputError: unknown calibration.

    """
    if calibration not in BENDING_CALIBRATION:
        raise InputError(f"calibration: expected one of {tuple(BENDING_CALIBRATION)}, "
                         f"got {calibration!r}")
    return BENDING_CALIBRATION[calibration] * plate_bending_stiffness(mat)


def bending_stiffness_from_arcsim(k_arcsim: float) -> float:
    """Convert an ARCSim-convention bending weight to this code's ``k_B``.

    Assumes ``k_arcsim = ARCSIM_BENDING_FACTOR * k_B`` (see :data:`ARCSIM_BENDING_FACTOR`).
    """
    if not k_arcsim >= 0:
        raise InputError(f"k_arcsim: must be >= 0, got {k_arcsim!r}")
    return k_arcsim / ARCSIM_BENDING_FACTOR


def shell_stiffness(mat: ShellMaterial, mapping: MembraneMapping = "equibiaxial",
                    calibration: BendingCalibration = "sphere") -> dict[str, float]:
    """``{"k_L", "k_A", "k_B"}`` for :class:`models.shell.energy.ShellParams`."""
    k_L, k_A = membrane_stiffness(mat, mapping)
    return {"k_L": k_L, "k_A": k_A, "k_B": bending_stiffness(mat, calibration)}
