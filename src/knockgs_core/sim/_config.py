"""Data that configures a simulation: boundary conditions, probes, solver settings.

Everything here is plain frozen data; the kernels in :mod:`knockgs_core.sim._kernels`
interpret it. Units: lengths in the normalized domain [m], times [s], forces [N].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, Union

from ._protocol import Effect

__all__ = [
    "Box",
    "DomainWalls",
    "FixedCuboid",
    "ParticleTranslation",
    "BoundaryCondition",
    "is_still_sticky",
    "Probe",
    "ExportSchedule",
    "Material",
    "SimParams",
    "TRANSFERS",
]

TRANSFERS = ("apic", "affine_flip")
"""The particle-grid transfers :class:`SimParams` accepts."""

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class Box:
    """Axis-aligned box: ``center`` [m], ``half_size`` [m] (both length-3)."""

    center: Vec3
    half_size: Vec3

    def contains(self, points):
        """Boolean mask of ``points`` (shape (n, 3)) inside the closed box."""
        import numpy as np

        c = np.asarray(self.center, dtype=np.float64)
        h = np.asarray(self.half_size, dtype=np.float64)
        return np.all(np.abs(np.asarray(points, dtype=np.float64) - c) <= h, axis=1)


@dataclass(frozen=True)
class DomainWalls:
    """Walls at the domain boundary: grid nodes within ``padding`` cells of a face.

    ``mode='sticky'`` zeroes the node velocity, ``'slip'`` zeroes only the normal
    component pointing out of the domain.
    """

    padding: int = 3
    mode: Literal["sticky", "slip"] = "slip"


@dataclass(frozen=True)
class FixedCuboid:
    """A support held on the grid: nodes inside ``box`` take ``velocity`` [m/s]
    while ``start_time <= t < end_time`` (PhysGaussian's cuboid boundary condition).

    ``friction=None`` keeps the support sticky; a number ``mu >= 0`` [-] makes it a Coulomb
    contact instead: approaching nodes lose their normal velocity (relative to the support,
    normal of the nearest box face) and their tangential speed drops by ``mu`` times the
    removed normal speed, separating nodes are free (``mu = 0``: frictionless slip)."""

    box: Box
    velocity: Vec3 = (0.0, 0.0, 0.0)
    start_time: float = 0.0
    end_time: float = math.inf
    friction: float | None = None

    def __post_init__(self):
        if self.friction is not None and not (math.isfinite(self.friction) and self.friction >= 0.0):
            raise ValueError(f"FixedCuboid.friction must be None (sticky) or a finite number >= 0, got {self.friction!r}")

    @property
    def friction_coefficient(self) -> float:
        """The kernel's friction argument: ``-1`` for sticky, else ``friction``."""
        return -1.0 if self.friction is None else float(self.friction)


@dataclass(frozen=True)
class ParticleTranslation:
    """Particles inside ``box`` at t = 0 move with ``velocity`` [m/s] while
    ``start_time <= t < end_time`` (PhysGaussian's enforce_particle_translation)."""

    box: Box
    velocity: Vec3 = (0.0, 0.0, 0.0)
    start_time: float = 0.0
    end_time: float = math.inf


BoundaryCondition = Union[DomainWalls, FixedCuboid, ParticleTranslation]


def is_still_sticky(bc: BoundaryCondition) -> bool:
    """Whether ``bc`` is a *still, sticky support*: a :class:`FixedCuboid` without friction
    that does not move and holds for the whole rollout (from t <= 0 on, never released).
    Such supports are what :class:`~knockgs_core.sim.SupportSlip` takes over and what the
    discrepancy catalogue's support terms need."""
    return (isinstance(bc, FixedCuboid) and bc.friction is None and not any(bc.velocity)
            and bc.start_time <= 0.0 and math.isinf(bc.end_time))


@dataclass(frozen=True)
class ExportSchedule:
    """Export times ``k * frame_dt`` for ``k = 0 .. n_frames - 1`` [s]."""

    frame_dt: float
    n_frames: int

    @property
    def times(self) -> list[float]:
        return [k * self.frame_dt for k in range(self.n_frames)]

    @property
    def horizon(self) -> float:
        return (self.n_frames - 1) * self.frame_dt


@dataclass(frozen=True)
class Probe:
    """A known force, applied per selected particle before P2G: ``v += f / m_p * dt``.

    ``force`` is the force on each selected particle [N], held for ``n_steps`` steps of
    ``dt_ref`` [s] starting at ``start_time`` [s]; the impulse ``force * n_steps * dt_ref``
    is what the probe delivers at any solver dt. ``box=None`` selects every particle,
    otherwise the particles inside the box at t = 0 (selection made once).
    """

    name: str
    force: Vec3
    box: Box | None = None
    start_time: float = 0.0
    n_steps: int = 1
    dt_ref: float = 1e-4
    export: ExportSchedule = field(default_factory=lambda: ExportSchedule(0.02, 31))

    @property
    def duration(self) -> float:
        return self.n_steps * self.dt_ref

    def schedule(self, dt: float) -> tuple[int, int, tuple[float, float, float]]:
        """(first step, number of steps, per-step force) at solver step ``dt``.

        The impulse ``force * duration`` is preserved exactly: the number of steps is
        ``max(1, round(duration / dt))`` and the per-step force is rescaled to match.
        """
        first = int(round(self.start_time / dt))
        steps = max(1, int(round(self.duration / dt)))
        scale = self.duration / (steps * dt)
        return first, steps, tuple(float(f) * scale for f in self.force)


@dataclass(frozen=True)
class Material:
    """Fixed-corotated ("jelly") elastic material: Young's modulus ``E`` [Pa],
    Poisson ratio ``nu`` [-], density ``rho`` [kg/m^3]."""

    E: float
    nu: float
    rho: float

    def lame(self) -> tuple[float, float]:
        """(mu, lambda) [Pa]."""
        mu = self.E / (2.0 * (1.0 + self.nu))
        lam = self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))
        return mu, lam

    def p_wave_speed(self) -> float:
        """Dilatational wave speed sqrt((lambda + 2 mu) / rho) [m/s]."""
        mu, lam = self.lame()
        return math.sqrt((lam + 2.0 * mu) / self.rho)


@dataclass(frozen=True)
class SimParams:
    """Solver settings shared by every rollout of one contract and profile.

    ``n_grid`` cells per axis over ``[0, grid_lim]^3``; substep ``dt`` [s]; ``gravity``
    [m/s^2]; ``grid_v_damping_scale`` multiplies grid velocities each substep of length
    ``damping_dt_ref`` when < 1 (PhysGaussian semantics at the paper's 1e-4 s substep); at
    another dt the per-substep factor is ``scale ** (dt / damping_dt_ref)``, so the damping
    per unit time, a property of the contract, does not change with the resolution profile;
    ``boundaries`` are applied in order after the grid update.
    ``transfer`` is the particle-grid transfer: ``"apic"`` (the paper's; it replaces particle
    velocities by the grid's at every substep, a numerical damping per substep that grows as
    dt shrinks) or ``"affine_flip"`` (particle velocity and affine matrix take the grid
    increment, relaxed towards APIC with time constant ``pic_relaxation_time`` [s]; ``inf``
    is pure affine FLIP: no transfer damping, first order in dt). The relaxation time is in
    seconds, not in cells or substeps, so the contract's physics does not change with the
    resolution profile (see :mod:`knockgs_core.sim._kernels`).
    ``cfl_limit`` bounds ``max|v| dt / dx`` (the guard stops the run above it);
    ``elastic_cfl_limit`` bounds ``c_p dt / dx`` with the fastest dilatational wave speed
    ``c_p`` of the materials (checked before the first substep: above it explicit MPM is
    unstable whatever the velocities).
    """

    n_grid: int = 100
    grid_lim: float = 2.0
    dt: float = 1e-4
    gravity: Vec3 = (0.0, 0.0, 0.0)
    grid_v_damping_scale: float = 1.0
    damping_dt_ref: float = 1e-4
    boundaries: tuple[BoundaryCondition, ...] = (DomainWalls(),)
    cfl_limit: float = 1.0
    elastic_cfl_limit: float = 1.0
    guard_every: int = 50
    transfer: Literal["apic", "affine_flip"] = "affine_flip"
    pic_relaxation_time: float = math.inf
    effects: tuple[Effect, ...] = ()
    """Optional extra physics, in the order their hooks run: :class:`~knockgs_core.sim.Effect`
    instances (the protocol is in :mod:`knockgs_core.sim._protocol`), switched on with
    :func:`~knockgs_core.sim.with_effects`."""

    def __post_init__(self):
        if self.transfer not in TRANSFERS:
            raise ValueError(f"SimParams.transfer must be one of {', '.join(TRANSFERS)}, got {self.transfer!r}")
        if not (self.pic_relaxation_time > 0):  # also rejects NaN
            raise ValueError(f"SimParams.pic_relaxation_time must be > 0 [s] (inf: pure affine FLIP), "
                             f"got {self.pic_relaxation_time!r}")

    @property
    def dx(self) -> float:
        return self.grid_lim / self.n_grid

    @property
    def flip_weight(self) -> float:
        """Weight ``exp(-dt / pic_relaxation_time)`` of the affine-FLIP increment per substep
        (0 under APIC)."""
        if self.transfer == "apic":
            return 0.0
        return math.exp(-self.dt / self.pic_relaxation_time)
