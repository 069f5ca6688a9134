"""The effect protocol: what an extra physics term may do to a simulation, and when.

After Newton's split of a static ``Model`` from a time-varying ``State`` and its explicit
scratch objects: an effect is frozen data (a dataclass deriving from :class:`Effect`); what
it must remember while a rollout runs (a particle selection, an accumulated plastic strain)
is a *scratch* object that its :meth:`Effect.setup` returns for one model and that the
solver holds and hands back to every hook. Every hook has a no-op default, so an effect
overrides only the stages it acts at:

* :meth:`Effect.configure` ``(params) -> params``: static configuration, applied by
  :func:`~knockgs_core.sim.with_effects` (default: append the effect to ``params.effects``);
* :meth:`Effect.materials` ``(positions, E, nu, rho) -> (E, nu, rho)``: once, in
  :func:`~knockgs_core.sim.build_model` (per-particle arrays, theta already applied);
* :meth:`Effect.setup` ``(model) -> scratch``: once per solver, before the first substep;
* :meth:`Effect.apply_grid` ``(model, state, scratch, lo, dims, t)``: each substep, after
  the grid update and the boundary conditions (``state.grid_mv`` then holds node
  velocities [m/s]); the kernels run over the active box ``lo`` (``wp.vec3i``) of size
  ``dims`` (cells per axis);
* :meth:`Effect.apply_particles` ``(model, state, scratch, t)``: each substep, after the
  grid-to-particle transfer;
* :meth:`Effect.viscous_retardation` ``(model) -> beta``: once per solver, the retardation
  time [s] of a Kelvin-Voigt viscous stress (``beta`` times the elastic tangent applied to
  the rate of deformation), added to the stress of every particle-to-grid transfer.

``t`` is the time at the start of the substep [s]. Each effect has one scalar *strength*
parameter, named by the class attribute ``parameter``, whose value ``off`` makes the
effect a no-op.

This module is the bottom of the simulator: the configuration (``_config``: ``SimParams``
holds effects) and the model (``_model``: ``Model``, ``State``) import it, so it imports
neither; the hooks' ``params``, ``model`` and ``state`` are a
:class:`~knockgs_core.sim.SimParams`, a :class:`~knockgs_core.sim.Model` and a
:class:`~knockgs_core.sim.State`, named in words here rather than by import.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, ClassVar

if TYPE_CHECKING:  # for annotations only
    import numpy as np
    import warp as wp

__all__ = ["Effect"]


class Effect:
    """Common interface of the effects (a mixin of frozen dataclasses), with no-op hooks."""

    #: catalogue key
    name: ClassVar[str] = ""
    #: field holding the strength parameter, its unit and its "switched off" value
    parameter: ClassVar[str] = ""
    unit: ClassVar[str] = ""
    off: ClassVar[float] = 0.0

    # -- the strength parameter ---------------------------------------------------------
    @property
    def value(self) -> float:
        return float(getattr(self, self.parameter))

    def with_value(self, value: float):
        """A copy with the strength parameter set to ``value``."""
        return dataclasses.replace(self, **{self.parameter: float(value)})

    @property
    def is_off(self) -> bool:
        return self.value == self.off

    def describe(self) -> str:
        return f"{self.name}: {self.parameter} = {self.value:.4g} {self.unit}".rstrip()

    # -- hooks (no-op defaults) ---------------------------------------------------------
    def configure(self, params: Any) -> Any:
        """``params`` (a :class:`~knockgs_core.sim.SimParams`) with this effect switched on: by
        default appended to ``params.effects``. An effect that rewrites static configuration (a
        support's friction) overrides it."""
        return dataclasses.replace(params, effects=tuple(params.effects) + (self,))

    def materials(self, positions: np.ndarray, E: np.ndarray, nu: np.ndarray, rho: np.ndarray):
        """Per-particle (E [Pa], nu [-], rho [kg/m^3]), each shape (particle_count,), for
        particles at ``positions`` [m] (particle_count, 3); default: unchanged."""
        return E, nu, rho

    def setup(self, model: Any) -> Any:
        """The scratch object this effect needs while ``model`` (a :class:`~knockgs_core.sim.Model`)
        runs (None: none)."""
        return None

    def apply_grid(self, model: Any, state: Any, scratch: Any, lo: wp.vec3i, dims: tuple[int, int, int], t: float) -> None:
        """Act on the grid velocities ``state.grid_mv`` of the active box; default: nothing."""

    def apply_particles(self, model: Any, state: Any, scratch: Any, t: float) -> None:
        """Act on the particle state after the grid-to-particle transfer; default: nothing."""

    def viscous_retardation(self, model: Any) -> float:
        """The retardation time beta [s] of a Kelvin-Voigt viscous stress this effect adds to
        the elastic stress of ``model`` (stiffness-proportional damping, read once per solver;
        the solver sums the effects'); default 0."""
        return 0.0
