"""The facets a body Newton solve integrates each obstacle's penalty over.

The penalty ``int k/2 <g(X + u)>_-^2 dA`` of an obstacle (:mod:`models.contact`) is exactly
zero on a facet whose gap ``g`` is positive at all its quadrature points, and so are its
residual and Jacobian there; yet integrating it over every exterior facet at the penalty's
quadrature (:data:`models.contact.FACET_QUADRATURE`: 6 or 12 points per facet) makes up most
of the body's Jacobian on a small mesh. A solve therefore integrates each obstacle over its
*candidate* facets only (:meth:`ActiveFacets.select`), those whose gap lower bound at the
start of the solve (:meth:`models.contact.PenaltyContact.gap_lower_bounds` of the corner
positions ``X + u_0``) is below the margin

    m = 2 max_corners |u_0 - u_n| + e_max / 10,

``u_0 - u_n`` the motion of the facet corners the step's initial guess predicts (twice it:
the solve may go further) and ``e_max`` the longest exterior edge of the rest mesh (a slack
for curved P2 facets and facets about to touch). After the solve, the penalty over the facets
left out is assembled (:meth:`ActiveFacets.outside`): every term of that sum is zero where
``g >= 0``, so the sum is exactly ``0.0`` unless a facet left out is penetrated; then the
caller solves again from the same start over all facets. A solve that passes the check took
the steps of the solve over all facets (the terms left out are exact zeros in every assembled
sum), so the result is the same, bitwise where no iterate touched a facet left out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from models.backend import MPI, global_scalar, with_facet_domains
from models.contact import BoundaryTriangles, PenaltyContact

SLACK: float = 0.1
"""The margin's slack in units of the longest exterior rest edge (module docstring)."""


@dataclass
class ContactSetStats:
    """Counters of the facet selection (per body, over its life).

    Attributes:
        solves: Solves that integrated the penalties over candidate facets.
        facets: Candidate facets summed over those solves and obstacles (this rank).
        total: Exterior facets times obstacles, summed over those solves (this rank).
        retries: Solves repeated over all facets because a facet left out was penetrated.

    """

    solves: int = 0
    facets: int = 0
    total: int = 0
    retries: int = 0


class ActiveFacets:
    """Candidate facets per obstacle and the check of the facets left out.

    Args:
        mesh: The body's mesh.
        V: The displacement space (P1 or P2, block size 3).
        contacts: The obstacles; obstacle i integrates over ``ds(contacts[i].facet_id)``.
        facets: This rank's exterior facets (:func:`models.contact.exterior_facets`), the
            obstacles' full domain.
        pairs: The same facets as ``(cell, local facet)`` pairs, flattened
            (:func:`models.backend.exterior_facet_domain`, as the obstacles' forms hold them).
        penalty: The compiled sum of the obstacles' penalty energies (the check's form).

    """

    def __init__(self, mesh: Any, V: Any, contacts: list[PenaltyContact], facets: np.ndarray,
                 pairs: np.ndarray, penalty: Any) -> None:
        self.contacts, self.penalty, self.comm = contacts, penalty, mesh.comm
        self.surface = BoundaryTriangles.of(mesh, V, facets)
        self.pairs = np.asarray(pairs, dtype=np.int32).reshape(-1, 2)
        rest = self.surface.rest
        longest = (np.linalg.norm(rest - np.roll(rest, 1, axis=1), axis=2).max()
                   if rest.size else 0.0)
        self.edge = float(self.comm.allreduce(float(longest), op=MPI.MAX))
        self.stats = ContactSetStats()
        self._near: dict[int, np.ndarray] = {}

    def select(self, u0: np.ndarray, u_n: np.ndarray) -> dict[int, np.ndarray]:
        """Each obstacle's candidate facets for a solve from ``u0`` after state ``u_n``.

        Args:
            u0: The initial guess (dof array of the displacement, ghosts included).
            u_n: The state the step starts from (same layout).

        Returns:
            ``{facet_id: pairs}`` for :meth:`solvers.body_newton.EnergyNewton.set_facet_domains`.

        """
        points = self.surface.deformed(u0)
        motion = (np.linalg.norm(points - self.surface.deformed(u_n), axis=2).max()
                  if points.size else 0.0)
        motion = float(self.comm.allreduce(float(motion), op=MPI.MAX))
        self._near = self._near_facets(points, 2.0 * motion + SLACK * self.edge)
        self.stats.facets += sum(int(np.count_nonzero(near)) for near in self._near.values())
        self.stats.solves += 1
        self.stats.total += len(self.contacts) * self.pairs.shape[0]
        return self._domains(self._near)

    def outside(self) -> float:
        """Return the penalty [J] over the facets the last selection left out (collective).

        Exactly ``0.0`` iff no facet left out has a quadrature point with ``g < 0``.
        """
        return self._left_out(self._near)

    def at(self, u: np.ndarray) -> dict[int, np.ndarray] | None:
        """Each obstacle's facets that carry its penalty at the state ``u`` (collective).

        The facets whose gap lower bound at ``u`` is below ``SLACK`` times the longest
        exterior rest edge, checked as :meth:`outside` checks a solve's: ``None`` (integrate
        over all facets) when a facet left out has a quadrature point with ``g < 0``. Any
        form whose exterior-facet integrands carry the factor ``H(-g)`` of the penalty (its
        energy, force, Jacobian, the sphere's centre stiffness) then sums to the same value
        over these facets as over all of them: the terms left out are exact zeros.

        Args:
            u: The displacement's dof array (ghosts included).

        Returns:
            ``{facet_id: pairs}`` (:func:`models.backend.with_facet_domains`), or None.

        """
        near = self._near_facets(self.surface.deformed(u), SLACK * self.edge)
        return self._domains(near) if self._left_out(near) == 0.0 else None

    def _near_facets(self, points: np.ndarray, margin: float) -> dict[int, np.ndarray]:
        """Per obstacle id, the mask of the facets whose gap lower bound is below ``margin``."""
        return {contact.facet_id: contact.gap_lower_bounds(points) < margin
                for contact in self.contacts}

    def _domains(self, near: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Return the ``(cell, local facet)`` pairs of the masked facets, per obstacle id."""
        return {i: np.ascontiguousarray(self.pairs[mask].ravel()) for i, mask in near.items()}

    def _left_out(self, near: dict[int, np.ndarray]) -> float:
        """Return the obstacles' penalty [J] over the facets outside ``near`` (collective)."""
        rest = {i: np.ascontiguousarray(self.pairs[~mask].ravel()) for i, mask in near.items()}
        return global_scalar(with_facet_domains(self.penalty, rest))
