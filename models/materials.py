"""Hyperelastic materials of the coarse body as UFL expressions.

Two compressible isotropic stored energies ``psi(F)`` per unit reference volume are offered
(Bonet & Wood, "Nonlinear Continuum Mechanics for Finite Element Analysis", 2nd ed., ch. 6):

* compressible Neo-Hookean (default)::

      psi(F) = mu/2 (I_C - 3) - mu ln J + lambda/2 (ln J)^2,   I_C = tr(F^T F), J = det F
      P(F)   = mu (F - F^{-T}) + lambda ln J F^{-T}

* St. Venant-Kirchhoff (used by Remillard & Kry's code for the body)::

      psi(F) = lambda/2 (tr E)^2 + mu E:E,   E = (F^T F - I)/2
      P(F)   = F S,   S = lambda tr(E) I + 2 mu E

Lame parameters from Young's modulus and Poisson's ratio:
``mu = E / (2 (1 + nu))``, ``lambda = E nu / ((1 + nu)(1 - 2 nu))``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from meshes.errors import InputError
from models.backend import ufl

MODELS: tuple[str, ...] = ("neo_hookean", "stvk")


@dataclass(frozen=True)
class Material:
    """An isotropic compressible hyperelastic material.

    Attributes:
        model: Stored energy, ``"neo_hookean"`` (default) or ``"stvk"``.
        E: Young's modulus [Pa], > 0.
        nu: Poisson's ratio [-], -1 < nu < 0.5 (the models are compressible).
        density: Mass density in the reference configuration [kg/m^3], > 0.

    """

    model: str = "neo_hookean"
    E: float = 1.0e5
    nu: float = 0.3
    density: float = 1000.0

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise InputError(f"material.model must be one of {MODELS}, got {self.model!r}")
        for name in ("E", "nu", "density"):
            if not math.isfinite(float(getattr(self, name))):
                raise InputError(f"material.{name} must be finite, got {getattr(self, name)}")
        if self.E <= 0.0:
            raise InputError(f"material.E must be > 0, got {self.E}")
        if self.nu >= 0.5:
            raise InputError(f"material.nu must be < 0.5 (compressible model), got {self.nu}")
        if self.nu <= -1.0:
            raise InputError(f"material.nu must be > -1, got {self.nu}")
        if self.density <= 0.0:
            raise InputError(f"material.density must be > 0, got {self.density}")

    @property
    def mu(self) -> float:
        """Shear modulus ``mu = E / (2 (1 + nu))`` [Pa]."""
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def lmbda(self) -> float:
        """First Lame parameter ``lambda = E nu / ((1 + nu)(1 - 2 nu))`` [Pa]."""
        return self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))

    def psi(self, F: Any) -> Any:
        """Return the stored energy ``psi(F)`` [J/m^3] as a UFL expression (module doc)."""
        if self.model == "stvk":
            return stvk_psi(F, self.mu, self.lmbda)
        return neo_hookean_psi(F, self.mu, self.lmbda)

    def first_piola(self, F: Any) -> Any:
        """First Piola-Kirchhoff stress ``P = d psi / d F`` [Pa] in closed form (UFL)."""
        if self.model == "stvk":
            return stvk_piola(F, self.mu, self.lmbda)
        return neo_hookean_piola(F, self.mu, self.lmbda)


def green_strain(F: Any) -> Any:
    """Green-Lagrange strain ``E = (F^T F - I) / 2``."""
    return 0.5 * (F.T * F - ufl.Identity(F.ufl_shape[0]))


def neo_hookean_psi(F: Any, mu: float, lmbda: float) -> Any:
    """Compressible Neo-Hookean ``mu/2 (I_C - 3) - mu ln J + lambda/2 (ln J)^2``."""
    J = ufl.det(F)
    return 0.5 * mu * (ufl.tr(F.T * F) - 3.0) - mu * ufl.ln(J) + 0.5 * lmbda * ufl.ln(J) ** 2


def neo_hookean_piola(F: Any, mu: float, lmbda: float) -> Any:
    """Neo-Hookean first Piola stress ``mu (F - F^{-T}) + lambda ln J F^{-T}``."""
    FinvT = ufl.inv(F).T
    return mu * (F - FinvT) + lmbda * ufl.ln(ufl.det(F)) * FinvT


def stvk_psi(F: Any, mu: float, lmbda: float) -> Any:
    """St. Venant-Kirchhoff ``lambda/2 (tr E)^2 + mu E:E``."""
    E = green_strain(F)
    return 0.5 * lmbda * ufl.tr(E) ** 2 + mu * ufl.inner(E, E)


def stvk_piola(F: Any, mu: float, lmbda: float) -> Any:
    """St. Venant-Kirchhoff first Piola stress ``F (lambda tr(E) I + 2 mu E)``."""
    E = green_strain(F)
    return F * (lmbda * ufl.tr(E) * ufl.Identity(F.ufl_shape[0]) + 2.0 * mu * E)
