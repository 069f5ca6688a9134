"""Data that configures a simulation: boundary conditions, probes, the physics' settings
(:class:`SimParams`) and how the solver steps (:class:`SolverConfig`).

Everything here is plain frozen data; the kernels in :mod:`knockgs_core.sim._kernels`
interpret it. Units: lengths in the normalized domain [m], times [s], forces [N].
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import ClassVar, Literal, Union

from ..errors import InputError
from ._protocol import Effect

__all__ = [
    "Box",
    "DomainWalls",
    "FixedCuboid",
    "ParticleTranslation",
    "BoundaryCondition",
    "is_still_sticky",
    "Probe",
    "probe_weights",
    "ExportSchedule",
    "Material",
    "SimParams",
    "SolverConfig",
    "GPU_SOLVER_OPTIONS",
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


def probe_weights(selected, mass=None):
    """Each particle's share [-] (N,) float32 of a probe that selects ``selected`` [N] bool: 0
    outside, mean 1 inside, so the probe's total force is the per-particle force times the
    count either way. Without ``mass`` every selected particle gets 1 (PhysGaussian's force per
    particle: particles of one grid cell share its volume equally). With ``mass`` [kg] (N,),
    for particles that carry their own volumes (``fill.volumes``: ``enclosed``, ``wall``), the
    share is the particle's mass over the selection's mean: the force accelerates the knocked
    region uniformly, the load a body force, however the region is sampled. (Equal forces on
    particles of unequal mass would push a light particle at the surface, a sliver of a cell,
    hundreds of times harder than the body around it, and the load would change with the
    fill.)"""
    import numpy as np

    sel = np.asarray(selected, dtype=bool)
    out = np.zeros(len(sel), dtype=np.float64)
    if mass is None:
        out[sel] = 1.0
    elif sel.any():
        m = np.asarray(mass, dtype=np.float64)[sel]
        out[sel] = m / m.mean()
    return out.astype(np.float32)


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


def as_flag(where: str, field: str, value) -> bool:
    """``value`` as a bool, where only True or False (or NumPy's) is accepted."""
    if value not in (True, False):
        raise InputError(where, field, f"must be True or False, got {value!r}")
    return bool(value)


@dataclass(frozen=True)
class SolverConfig:
    """How :class:`~knockgs_core.sim.MPMSolver` steps: the P2G variant, substep graphs, fused
    substeps, the reproducible sums, the polar iterations, G2P's sums and the P2G by cells'
    settings. None of them changes the physics: the same sums, in another order or rounding.

    An option ``"auto"`` is the device's choice; :meth:`resolve` makes every such choice for a
    device and a model (the one place they are made) and checks every option.
    :data:`GPU_SOLVER_OPTIONS` is its answer for a GPU. ``MPMSolver(model, config)`` resolves
    the config it is given (a resolved one stays as it is); ``MPMSolver(model, **options)``
    takes the same fields as keywords.
    """

    p2g: str = "auto"
    """``"scatter"`` (one float atomic per particle and stencil node; the CPU's), ``"cells"``
    (particles sorted by base cell every :attr:`resort_every` substeps, summed by windows of
    :attr:`cell_chunk` sorted particles with one atomic per run of one base cell and stencil
    node: :func:`~knockgs_core.sim._kernels.p2g_windows`) or ``"auto"``: by cells on a CUDA
    device where the particles crowd their cells (:func:`~knockgs_core.sim.cell_crowding` at
    least :attr:`CELLS_CROWDING`), else the scatter."""
    graph: bool | str = "auto"
    """Replay each substep as a captured graph (one per probe state and set of active supports,
    captured again when the guard moves the active box), which skips the host's launch overhead:
    a CUDA graph on a GPU; on the CPU (on request only) Warp replays the recorded launches, bit
    for bit the same substeps. ``"auto"``: on a CUDA device, for models without effects and
    particle translations (whose host-side hooks run every substep)."""
    fuse: bool | str = "auto"
    """With the P2G by cells, end each substep with G2P fused with the next substep's
    per-particle P2G half (:func:`~knockgs_core.sim._kernels.g2p_prepare`): one pass over the
    particles instead of two, the same bits. The next substep's probe impulse and rotation are
    then already in the state between substeps, so the solver must step that one state on, and
    nothing else may change it between substeps. ``"auto"``: where substeps are graphs and P2G
    is by cells."""
    resort_every: int = 10
    """The P2G by cells sorts the particles by base cell every this many substeps; between sorts
    the windows follow the last order, their runs cut where a particle has changed cells since
    (the sums are right in any order: the interval sets speed only;
    benchmarks/results/2026-11-26-graphs-crowding-cell-sums.md)."""
    cell_chunk: int = 32
    """Sorted particles a window of the P2G by cells takes (a block's threads and its staged
    terms in shared memory: at most 256); a run of one base cell is cut at a window's ends."""
    deterministic: bool = False
    """A GPU rollout the same bit for bit on every run. Float atomics add a node's contributions
    in the order the GPU schedules its threads, so the last bits of a GPU rollout vary between
    runs. Deterministic, the P2G is by cells (chosen whatever the crowding) and the windows' run
    sums, each summed in a fixed order, are added to the nodes as int64 fixed-point sums
    (:attr:`~knockgs_core.sim.MPMSolver.reproducible_sums`;
    :func:`~knockgs_core.sim._kernels.window_sums_fixed`), whose integer atomics give one sum in
    any order: no float atomics reach the grid. True or False only."""
    polar_step: float | str = "auto"
    """The polar iterations' step near convergence, a multiple of Mueller et al.'s
    (:func:`~knockgs_core.sim._kernels.polar_rotation`): 1.0 (theirs) up to 1.9; 1.5 takes about
    a third of the iterations of 1.0 to the same rotation (within its 1e-7 rad). ``"auto"``: 1.5
    on a GPU, 1.0 on the CPU (whose rollouts, and the tables made from them, keep their bits)."""
    polar_update: str = "auto"
    """How the polar iterations rotate by a correction below 0.1 rad
    (:func:`~knockgs_core.sim._kernels.polar_rotation`): ``"axis_angle"`` (the axis and the
    angle's sine and cosine, Mueller et al.'s) or ``"rational"`` (the quaternion ``(h, 1)``
    normalized: no sine, cosine or square root, one division; the same converged rotation).
    ``"auto"``: rational on a GPU, axis and angle on the CPU."""
    g2p_sums: str = "auto"
    """How G2P sums the node velocities into the particle's velocity and affine matrix:
    ``"nodes"`` (an outer product a node, :func:`~knockgs_core.sim._kernels.gather_by_nodes`) or
    ``"lines"`` (factored along the stencil's lines, ~300 multiply-adds a particle and field
    instead of ~700: :func:`~knockgs_core.sim._kernels.gather_by_lines`; the same sums in another
    order). ``"auto"``: lines on a GPU, nodes on the CPU."""
    window_atomics: str = "auto"
    """How the float window sums reach the nodes: ``"scalar"`` (one float atomic a component into
    the grid's momentum, mass and stress-free momentum arrays, zeroed before P2G) or ``"vector"``
    (into vec4 node records of momentum and mass, and of the stress-free momentum, one 16-byte
    atomic each on a device of compute capability 9.0 or later; the grid update reads and zeroes
    them: :func:`~knockgs_core.sim._kernels.grid_update_records`). The same sums, added to each
    node in the same order wherever the atomics arrive in order (the CPU: the same bits).
    ``"auto"``: vector on a GPU where P2G sums by cells, scalar elsewhere. The reproducible sums
    (``deterministic``) add no floats to the nodes, so the option does not apply there. Measured
    in benchmarks/results/2026-11-29-vector-atomics.md."""

    #: ``p2g="auto"`` on a CUDA device sums by cells from this crowding on (particles sharing a
    #: particle's base cell, on average), and scatters below it: where particles crowd their cells
    #: the scatter's atomics serialize on the shared nodes (measured on blocks at 1 and 8
    #: particles a cell: benchmarks/results/2026-11-26-graphs-crowding-cell-sums.md)
    CELLS_CROWDING: ClassVar[float] = 4.0
    #: the options whose ``"auto"`` depends on the device (:meth:`device_options`)
    DEVICE_OPTIONS: ClassVar[tuple[str, ...]] = ("p2g", "graph", "fuse", "polar_step", "polar_update", "g2p_sums",
                                                 "window_atomics")
    #: the options for which MPMSolver's keyword None keeps the field as it is
    NONE_KEEPS: ClassVar[tuple[str, ...]] = ("resort_every", "cell_chunk", "polar_step", "polar_update", "g2p_sums",
                                             "window_atomics")

    def with_options(self, **options) -> SolverConfig:
        """This config with the fields given as :class:`~knockgs_core.sim.MPMSolver`'s keyword
        options (None keeps the field of the options in :attr:`NONE_KEEPS`); an unknown
        keyword is a TypeError naming it."""
        if not options:
            return self
        return dataclasses.replace(self, **{key: value for key, value in options.items()
                                            if value is not None or key not in self.NONE_KEEPS})

    @property
    def counts_crowding(self) -> bool:
        """Whether :meth:`resolve` needs the particles' crowding: only ``p2g="auto"`` of a solver
        that is not deterministic chooses by it."""
        return self.p2g == "auto" and not self.deterministic

    def device_options(self) -> dict:
        """The options whose ``"auto"`` depends on the device (:attr:`DEVICE_OPTIONS`), by name."""
        return {name: getattr(self, name) for name in self.DEVICE_OPTIONS}

    def resolve(self, *, cuda: bool, crowding: float | None = math.inf, hooks: bool = False) -> SolverConfig:
        """This config with every ``"auto"`` chosen for a CUDA device (``cuda``) or the CPU, for
        particles crowding their cells by ``crowding`` (:func:`~knockgs_core.sim.cell_crowding`;
        inf: as crowded as can be) and a model with host-side hooks (``hooks``: effects or particle
        translations) or not, and every option checked (an :class:`~knockgs_core.errors.InputError`
        naming it). Resolving a resolved config for the same device and model changes nothing."""
        def bad(option: str, message: str) -> InputError:
            return InputError("MPMSolver", option, message)

        deterministic = as_flag("MPMSolver", "deterministic", self.deterministic)
        polar_step = (1.5 if cuda else 1.0) if self.polar_step == "auto" else self.polar_step
        if isinstance(polar_step, bool) or not isinstance(polar_step, (int, float)) or not 1.0 <= polar_step <= 1.9:
            raise bad("polar_step", f"must be 'auto' or a number in [1, 1.9], got {polar_step!r}")
        polar_update = ("rational" if cuda else "axis_angle") if self.polar_update == "auto" else self.polar_update
        if polar_update not in ("axis_angle", "rational"):
            raise bad("polar_update", f"must be 'auto', 'axis_angle' or 'rational', got {polar_update!r}")
        g2p_sums = ("lines" if cuda else "nodes") if self.g2p_sums == "auto" else self.g2p_sums
        if g2p_sums not in ("nodes", "lines"):
            raise bad("g2p_sums", f"must be 'auto', 'nodes' or 'lines', got {g2p_sums!r}")
        graph = (bool(cuda) and not hooks) if self.graph == "auto" else self.graph
        if graph not in (True, False):
            raise bad("graph", f"must be 'auto', True or False, got {graph!r}")
        if graph and hooks:
            raise bad("graph", "substep graphs take models without effects and particle translations")
        p2g = self.p2g
        if p2g == "auto":  # by cells where the scatter's atomics would serialize on crowded nodes
            crowded = cuda and crowding is not None and crowding >= self.CELLS_CROWDING
            p2g = "cells" if deterministic or crowded else "scatter"
        if p2g not in ("scatter", "cells"):
            raise bad("p2g", f"must be 'auto', 'scatter' or 'cells', got {p2g!r}")
        if deterministic and p2g != "cells":
            raise bad("deterministic", "the bitwise-reproducible P2G sums by cells (p2g='cells' or 'auto')")
        fuse = (bool(graph) and p2g == "cells") if self.fuse == "auto" else self.fuse
        if fuse not in (True, False):
            raise bad("fuse", f"must be 'auto', True or False, got {fuse!r}")
        if fuse and (p2g != "cells" or hooks):
            raise bad("fuse", "fused substeps take the P2G by cells and models without effects and particle translations")
        window_atomics = self.window_atomics
        if window_atomics not in ("auto", "scalar", "vector"):
            raise bad("window_atomics", f"must be 'auto', 'scalar' or 'vector', got {window_atomics!r}")
        if window_atomics == "vector" and p2g != "cells":
            raise bad("window_atomics", f"vector atomics add the window sums of p2g='cells', not {p2g!r}")
        if window_atomics == "auto":  # the reproducible sums add no floats to the nodes
            window_atomics = "vector" if cuda and p2g == "cells" and not deterministic else "scalar"
        return dataclasses.replace(self, p2g=p2g, graph=bool(graph), fuse=bool(fuse), deterministic=deterministic,
                                   polar_step=float(polar_step), polar_update=polar_update, g2p_sums=g2p_sums,
                                   window_atomics=window_atomics)


#: the substep a CUDA device runs where the CPU runs another, as :class:`SolverConfig`'s device
#: options: :meth:`SolverConfig.resolve` for a CUDA device and a model without effects whose
#: particles crowd their cells, as the paper's objects and the verification block are. Given to
#: :func:`~knockgs_core.sim.simulate_many` on the CPU (``solver_options=GPU_SOLVER_OPTIONS``, the
#: model built with :data:`~knockgs_core.sim.GPU_STORAGE`), they replay a GPU's substep there:
#: the same sums, in the order the CPU adds them. The paper profile adds ``deterministic=True``.
GPU_SOLVER_OPTIONS: Mapping = MappingProxyType(SolverConfig().resolve(cuda=True).device_options())
