"""MLS-MPM solver: a static :class:`Model`, a time-varying :class:`State`, and
:class:`MPMSolver` whose :meth:`~MPMSolver.step` advances one substep.

The grid kernels run only over the *active box*, the part of the grid that the particles'
stencils can reach before the next guard check, so grid work scales with the occupied
region rather than with ``n_grid^3``.
"""

from __future__ import annotations

import contextlib
import inspect
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Callable

import numpy as np
import warp as wp

from .._warp import warp_device
from ..errors import InputError, SimulationError
from . import _kernels as K
from ._config import DomainWalls, FixedCuboid, ParticleTranslation, Probe, SimParams
from ._protocol import Effect

__all__ = ["Model", "State", "MPMSolver", "SimResult", "build_model", "particle_volumes", "cell_crowding", "default_device",
           "simulate", "simulate_many"]

def default_device() -> str:
    """The Warp device used when none is given: ``$KNOCKGS_DEVICE`` or ``"cpu"``."""
    return os.environ.get("KNOCKGS_DEVICE", "cpu")


def _sharing(cells: np.ndarray) -> np.ndarray:
    """For integer cells [N, 3]: how many of the rows share each row's cell, (N,) int64."""
    cells = cells - cells.min(axis=0)
    span = cells.max(axis=0) + 1
    key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]  # the cell's index in the particles' box
    if int(np.prod(span)) <= max(8 * len(key), 1 << 22):
        return np.bincount(key)[key]
    # a sparse box (particles far apart): count the occupied cells only
    _, inverse, per_cell = np.unique(key, return_inverse=True, return_counts=True)
    return per_cell[inverse]


def particle_volumes(positions: np.ndarray, dx: float) -> np.ndarray:
    """Particle volume [m^3] from initial particles per grid cell (PhysGaussian):
    each particle gets ``dx^3 / (particles in its cell)``. Shape (particle_count,)."""
    cells = np.floor(np.asarray(positions, dtype=np.float64) / dx).astype(np.int64)
    if len(cells) == 0:
        return np.zeros(0, dtype=np.float32)
    return (dx**3 / _sharing(cells)).astype(np.float32)


def cell_crowding(positions: np.ndarray, dx: float) -> float:
    """How crowded the particles' stencil base cells (``floor(x / dx - 0.5)``) are: the number
    of particles that share a particle's base cell, averaged over the particles [-]. A thin
    shell of many particles in few cells counts for its particles, not its cells: 8 for a block
    at 8 particles per cell, ~100 for the paper-scale Pillow's shell. ``positions`` [N, 3] m."""
    if len(positions) == 0:
        return 0.0
    cells = np.floor(np.asarray(positions, dtype=np.float64) / dx - 0.5).astype(np.int64)
    return float(np.mean(_sharing(cells)))


@dataclass
class Model:
    """Static description of one simulation (Warp arrays live on ``device``).

    particle_mass [kg], particle_vol [m^3], particle_mu / particle_lam [Pa]: shape
    (particle_count,). ``probe_mask`` marks the particles the probe acts on (selected once
    at t = 0); ``probe_force`` is the per-step force on each of them [N] for steps
    ``probe_first <= step < probe_first + probe_steps``. ``translations`` pairs each
    :class:`ParticleTranslation` with its particle mask (at most one is active at a time).
    Host copies: ``mass_host`` particle masses [kg] (particle_count,) float32 and
    ``particle_x0_host`` rest positions [m] (particle_count, 3) float32, from which regions
    are selected at t = 0 (effects' ``setup``). ``matrix_layout``: how the states and scratch
    made for this model store the per-particle matrices (:func:`matrix_array`; a storage
    choice, the same values). ``deformation_storage``: how they store the deformation gradients
    (:func:`deformation_array`: F in float64, or its displacement gradient F - I in float32;
    the same F to within F - I's float32 rounding).
    """

    params: SimParams
    device: str
    particle_count: int
    particle_mass: wp.array
    particle_vol: wp.array
    particle_mu: wp.array
    particle_lam: wp.array
    probe_mask: wp.array
    probe_force: tuple[float, float, float] = (0.0, 0.0, 0.0)
    probe_first: int = 0
    probe_steps: int = 0
    probe_count: int = 0
    translations: list[tuple[ParticleTranslation, wp.array]] = field(default_factory=list)
    mass_host: np.ndarray | None = None
    max_wave_speed: float = 0.0
    particle_x0_host: np.ndarray | None = None
    matrix_layout: str = "auto"
    deformation_storage: str = "auto"

    @property
    def total_probe_force(self) -> tuple[float, float, float]:
        """Per-step force times the number of selected particles [N]."""
        return tuple(f * self.probe_count for f in self.probe_force)

    @property
    def probe_impulse(self) -> tuple[float, float, float]:
        """Total impulse the probe delivers [N s]."""
        return tuple(f * self.probe_steps * self.params.dt for f in self.total_probe_force)


@dataclass
class State:
    """Time-varying simulation state.

    particle_x0 rest positions [m] (particle_count, 3) and particle_u displacements [m]
    (positions are x0 + u: small displacements keep their float32 precision); particle_v
    [m/s]; particle_F deformation gradient in float64, or on a GPU as its displacement gradient
    F - I in float32 (:func:`deformation_array`; it accumulates ``I + dt C`` every substep: a
    float32 F would round a strain of ~1e-3 at 1's precision, a random walk into a floor on the
    dt convergence); particle_C APIC affine velocity [1/s]; both laid out as the model says
    (:func:`matrix_array`: records on the CPU, components on a GPU;
    :meth:`deformation_gradients`, :meth:`affine_velocities` give them as (particle_count, 3,
    3) in either); particle_rot
    warm-start rotation of F's polar decomposition (quaternion xyzw); grid_mv grid momentum
    [kg m/s], then velocity [m/s] (n_grid, n_grid, n_grid) of vec3; grid_m grid mass [kg]
    (n_grid, n_grid, n_grid); grid_mv_old (affine-FLIP transfer only) the grid momentum
    without this substep's stress [kg m/s], then the old node velocity ``u_old`` [m/s]
    (n_grid, n_grid, n_grid) of vec3, whose difference to grid_mv is what G2P adds to the
    particles; a (1, 1, 1) placeholder under APIC. ``step`` counts substeps taken.
    """

    particle_x0: wp.array
    particle_u: wp.array
    particle_v: wp.array
    particle_F: wp.array
    particle_C: wp.array
    particle_rot: wp.array
    grid_mv: wp.array
    grid_m: wp.array
    grid_mv_old: wp.array
    step: int = 0

    def positions(self) -> np.ndarray:
        """Current particle positions x0 + u [m], (particle_count, 3) float64."""
        return self.particle_x0.numpy().astype(np.float64) + self.particle_u.numpy().astype(np.float64)

    def deformation_gradients(self) -> np.ndarray:
        """The particles' deformation gradients, (particle_count, 3, 3) float64."""
        return matrices(self.particle_F, len(self.particle_x0))

    def affine_velocities(self) -> np.ndarray:
        """The particles' affine velocity matrices C [1/s], (particle_count, 3, 3) float32."""
        return matrices(self.particle_C, len(self.particle_x0))


def matrix_pitch(n: int) -> int:
    """Columns of a per-particle matrix array for ``n`` particles: ``n`` rounded up to 32, so
    each of its 9 rows starts 128-byte aligned on the GPU (unaligned rows measured 1.5x slower
    to stream on an H100: benchmarks/results/2026-11-27-window-sums-and-reference.md)."""
    return max(32, -(-n // 32) * 32)


def device_storage(cuda: bool) -> dict:
    """What :func:`build_model`'s ``"auto"`` storage chooses on a CUDA device (``cuda``) or the
    CPU: ``matrix_layout`` (:func:`matrix_array`) and ``deformation_storage``
    (:func:`deformation_array`). The one place these choices are made; :data:`GPU_STORAGE` is
    its answer for a GPU."""
    return dict(matrix_layout="components" if cuda else "records",
                deformation_storage="displacement" if cuda else "float64")


def _matrix_layout(layout: str, dev) -> str:
    """The matrix layout ``layout`` means on device ``dev`` (see :func:`matrix_array`), checked."""
    if layout == "auto":
        layout = device_storage(dev.is_cuda)["matrix_layout"]
    if layout not in K.MATRIX_ARRAYS:
        raise InputError("Model", "matrix_layout", f"must be 'auto' or one of {sorted(K.MATRIX_ARRAYS)}, got {layout!r}")
    return layout


def matrix_array(n: int, dtype, device, *, layout: str = "auto") -> wp.array:
    """A zeroed per-particle 3x3 matrix array for ``n`` particles, of float32 (``dtype=float``)
    or float64 (``wp.float64``) components (the kernels read and write it through
    :func:`_kernels.mat33_at` and its kin, overloaded per layout).

    ``layout``: ``"components"``, component by component, shape (9, :func:`matrix_pitch`) with
    particle p's component ``3 i + j`` at ``[3 i + j, p]``: a GPU warp's threads read one
    component of 32 particles from one stretch of memory (on an H100 the Pillow's substep 1.06x
    faster than records); ``"records"``, shape (n,) of ``mat33``/``mat33d``: each particle's
    matrix in one piece (on the 2-core CPU 5-12 % faster than components); ``"auto"``:
    components on a GPU, records on the CPU (benchmarks/results/2026-11-27-layout-and-instructions.md).
    The values, and on the CPU the bits, are the same in both.
    """
    dev = wp.get_device(device)
    kind = K.MATRIX_ARRAYS[_matrix_layout(layout, dev)][dtype is wp.float64]  # the array type the kernels take
    shape = max(n, 1) if kind.ndim == 1 else (9, matrix_pitch(n))
    return wp.zeros(shape, dtype=kind.dtype, device=dev)


DEFORMATION_STORAGES = ("float64", "displacement")


def deformation_array(n: int, device, *, storage: str = "auto", layout: str = "auto") -> wp.array:
    """A zeroed deformation-gradient array for ``n`` particles (set F = I with
    :func:`_kernels.state_rest`; the kernels read and write it through
    :func:`_kernels.mat33d_at` and :func:`_kernels.mat33d_put`, overloaded per array type).

    ``storage``: ``"float64"``, F in float64 in the matrices' ``layout``
    (:func:`matrix_array`); ``"displacement"``, its displacement gradient H = F - I in float32,
    shape (3, 3, :func:`matrix_pitch`) with component (i, j) of particle p at [i, j, p] (the
    kernels compute in float64 and round F - I: a strain's increment rounds at H's precision,
    as a displacement u does in x0 + u; half the bytes a substep, beside matrices laid out
    component by component only); ``"auto"``: displacement on a GPU, float64 on the CPU, whose
    bits stay those of F in float64 (benchmarks/results/2026-11-28-f-minus-i-and-arena.md).
    """
    dev = wp.get_device(device)
    if _deformation_storage(storage, layout, dev) == "float64":
        return matrix_array(n, wp.float64, dev, layout=layout)
    return wp.zeros((3, 3, matrix_pitch(n)), dtype=float, device=dev)


def _deformation_storage(storage: str, layout: str, dev) -> str:
    """The deformation storage ``storage`` means on device ``dev`` beside the matrix layout
    ``layout`` (see :func:`deformation_array`), both checked."""
    if storage == "auto":
        storage = device_storage(dev.is_cuda)["deformation_storage"]
    if storage not in DEFORMATION_STORAGES:
        raise InputError("Model", "deformation_storage",
                         f"must be 'auto' or one of {list(DEFORMATION_STORAGES)}, got {storage!r}")
    if _matrix_layout(layout, dev) != "components" and storage == "displacement":
        raise InputError("Model", "deformation_storage",
                         "'displacement' is stored component by component: it needs matrix_layout 'components' "
                         f"(or 'auto' on a GPU), got {layout!r}")
    return storage


def matrices(a: wp.array, n: int) -> np.ndarray:
    """A per-particle matrix array of :func:`matrix_array` (either layout) as (n, 3, 3) on the
    host; a displacement-gradient array (:func:`deformation_array`) as the deformation
    gradients I + H in float64."""
    if a.ndim == 1:
        return a.numpy()[:n].copy()
    if a.ndim == 3:
        return np.moveaxis(a.numpy()[:, :, :n], 2, 0).astype(np.float64) + np.eye(3)
    return np.ascontiguousarray(a.numpy()[:, :n].T.reshape(n, 3, 3))


@dataclass
class SimResult:
    """Exported frames: ``times`` [s] (T,), ``positions`` [m] (T, N, 3) float32, and the
    deformation gradient ``F`` (T, n_F, 3, 3) float32 of the first ``n_F`` particles when
    asked for. ``stats`` holds guard statistics (max CFL number, min det F, steps).
    ``reproducible_sums``: how the solver made a deterministic run's P2G sums reproducible
    (:attr:`MPMSolver.reproducible_sums`); None for a run that was not."""

    times: np.ndarray
    positions: np.ndarray
    F: np.ndarray | None
    stats: dict
    reproducible_sums: str | None = None


def _as_particle_array(value, n: int, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise InputError("material", name, f"expected a scalar or shape ({n},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError("material", name, "non-finite value")
    return arr


def _flag(where: str, field: str, value) -> bool:
    """``value`` as a bool, where only True or False (or NumPy's) is accepted."""
    if value not in (True, False):
        raise InputError(where, field, f"must be True or False, got {value!r}")
    return bool(value)


def _check_params(params: SimParams) -> None:
    """What the solver supports beyond the dataclasses' own checks: effects following the
    :class:`Effect` protocol, and particle translations active one at a time (the
    grid-to-particle pass moves one selection per substep)."""
    for i, effect in enumerate(params.effects):
        if not isinstance(effect, Effect):
            raise InputError("SimParams", f"effects[{i}]", f"expected an Effect (knockgs_core.sim), got {type(effect).__name__}")
    spans = [(i, bc.start_time, bc.end_time) for i, bc in enumerate(params.boundaries) if isinstance(bc, ParticleTranslation)]
    for k, (i, s0, e0) in enumerate(spans):
        for j, s1, e1 in spans[k + 1:]:
            if s0 < e1 and s1 < e0:
                raise InputError("SimParams", f"boundaries[{j}]",
                                 f"particle translation active over [{s1:g}, {e1:g}) s overlaps boundaries[{i}] over "
                                 f"[{s0:g}, {e0:g}) s; at most one particle translation may be active at a time")


def build_model(
    positions: np.ndarray,
    *,
    E,
    nu,
    rho,
    params: SimParams,
    volumes: np.ndarray | None = None,
    probe: Probe | None = None,
    probe_force_scale: float = 1.0,
    device: str | None = None,
    matrix_layout: str = "auto",
    deformation_storage: str = "auto",
) -> Model:
    """Build the static model for particles at ``positions`` [m] (N, 3).

    ``E`` [Pa], ``nu`` [-], ``rho`` [kg/m^3]: scalars or per-particle arrays (theta already
    applied), then passed through each effect's ``materials`` hook. ``volumes`` [m^3]
    default to initial particles per cell. The probe's per-particle force is multiplied by
    ``probe_force_scale`` and rescaled so its impulse is kept at ``params.dt``; its contact
    box selects particles once, here. ``params.effects`` must be :class:`Effect` instances
    and at most one :class:`ParticleTranslation` may be active at any time.
    ``matrix_layout`` and ``deformation_storage``: how states made for the model store the
    per-particle matrices and F (:class:`Model`; ``"auto"``: the device's choice,
    :data:`GPU_STORAGE` on a GPU).
    """
    _check_params(params)
    # starts Warp (quiet on a CPU run); one line naming an unavailable device; "cuda" is the
    # card this process claimed (knockgs_core._warp.resolve_device)
    device = warp_device(device or default_device()).alias
    _deformation_storage(deformation_storage, matrix_layout, wp.get_device(device))  # one line naming a bad choice
    x = np.ascontiguousarray(positions, dtype=np.float32)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] == 0:
        raise InputError("positions", "shape", f"expected (N, 3) with N > 0, got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise InputError("positions", "x", "non-finite particle position")
    n = x.shape[0]
    dx = params.dx
    lo_ok = 3 * dx
    hi_ok = params.grid_lim - 3 * dx
    if x.min() < lo_ok or x.max() > hi_ok:
        raise InputError("positions", "x", f"particles must lie in [{lo_ok:g}, {hi_ok:g}]^3 (3 cells inside the domain)")
    E = _as_particle_array(E, n, "E")
    nu = _as_particle_array(nu, n, "nu")
    rho = _as_particle_array(rho, n, "rho")
    for effect in params.effects:
        E, nu, rho = (np.asarray(a, dtype=np.float64) for a in effect.materials(x, E, nu, rho))
    if np.any(E <= 0) or np.any(rho <= 0) or np.any(nu <= -1) or np.any(nu >= 0.5):
        raise InputError("material", "E/nu/rho", "need E > 0, rho > 0, -1 < nu < 0.5")
    vol = particle_volumes(x, dx) if volumes is None else np.asarray(volumes, dtype=np.float32)
    if vol.shape != (n,) or np.any(~np.isfinite(vol)) or np.any(vol <= 0):
        raise InputError("volumes", "volume", "need positive finite per-particle volumes")
    mass = (rho * vol).astype(np.float32)
    mu = (E / (2.0 * (1.0 + nu))).astype(np.float32)
    lam = (E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))).astype(np.float32)
    wave = float(np.max(np.sqrt((lam.astype(np.float64) + 2.0 * mu) / rho)))

    mask = np.zeros(n, dtype=np.int32)
    force = (0.0, 0.0, 0.0)
    first = steps = count = 0
    if probe is not None:
        sel = np.ones(n, dtype=bool) if probe.box is None else probe.box.contains(x)
        count = int(sel.sum())
        if count == 0:
            raise InputError(f"probe {probe.name}", "box", "the contact box selects no particles")
        mask[sel] = 1
        first, steps, f = probe.schedule(params.dt)
        force = tuple(float(c) * probe_force_scale for c in f)

    translations = []
    for bc in params.boundaries:
        if isinstance(bc, ParticleTranslation):
            sel = bc.box.contains(x).astype(np.int32)
            translations.append((bc, wp.array(sel, dtype=wp.int32, device=device)))

    return Model(
        params=params,
        device=device,
        particle_count=n,
        particle_mass=wp.array(mass, dtype=float, device=device),
        particle_vol=wp.array(vol, dtype=float, device=device),
        particle_mu=wp.array(mu, dtype=float, device=device),
        particle_lam=wp.array(lam, dtype=float, device=device),
        probe_mask=wp.array(mask, dtype=wp.int32, device=device),
        probe_force=force,
        probe_first=first,
        probe_steps=steps,
        probe_count=count,
        translations=translations,
        mass_host=mass,
        max_wave_speed=wave,
        particle_x0_host=x,
        matrix_layout=matrix_layout,
        deformation_storage=deformation_storage,
    )


def make_state(model: Model, positions: np.ndarray, velocities: np.ndarray | None = None) -> State:
    """Initial state: given positions [m] (N, 3), velocities [m/s] (default 0), F = I, C = 0."""
    n, dev, g = model.particle_count, model.device, model.params.n_grid
    g_old = g if model.params.transfer == "affine_flip" else 1
    x = np.ascontiguousarray(positions, dtype=np.float32)
    if velocities is None:
        v = wp.zeros(n, dtype=wp.vec3, device=dev)
    else:
        v = wp.array(np.ascontiguousarray(velocities, dtype=np.float32), dtype=wp.vec3, device=dev)
    F = deformation_array(n, dev, storage=model.deformation_storage, layout=model.matrix_layout)
    rot = wp.empty(n, dtype=wp.quat, device=dev)
    wp.launch(K.state_rest, dim=n, outputs=[F, rot], device=dev)  # F = I, rotations the identity
    return State(
        particle_x0=wp.array(x, dtype=wp.vec3, device=dev),
        particle_u=wp.zeros(n, dtype=wp.vec3, device=dev),
        particle_v=v,
        particle_F=F,
        particle_C=matrix_array(n, float, dev, layout=model.matrix_layout),
        particle_rot=rot,
        grid_mv=wp.zeros((g, g, g), dtype=wp.vec3, device=dev),
        grid_m=wp.zeros((g, g, g), dtype=float, device=dev),
        grid_mv_old=wp.zeros((g_old, g_old, g_old), dtype=wp.vec3, device=dev),
    )


@dataclass
class _CellScratch:
    """Scratch of the P2G by cells (``MPMSolver(p2g="cells")``): per particle, in the
    particles' order, the position in its base cell ``fx`` [cells], the affine matrix of stress
    and APIC terms ``affine`` (:func:`matrix_array`, laid out as the model says; the momentum and
    mass and affine FLIP's APIC term alone ``m C`` are formed from the state's ``v`` and ``C``
    where they are summed) and the base cell's ``keys``;
    the radix sort's ``sort_keys`` and ``order`` (twice the particle count, as the sort needs;
    ``order[:n]`` is a permutation at all times: the identity until the first sort), ``none_key``
    (a key above every cell's) and ``end_bit`` (the bits the sort looks at)."""

    fx: wp.array
    affine: wp.array
    keys: wp.array
    sort_keys: wp.array
    order: wp.array
    none_key: int
    end_bit: int

    @classmethod
    def make(cls, model: Model) -> _CellScratch:
        """The scratch for ``model``."""
        n, dev, g = model.particle_count, model.device, model.params.n_grid
        none_key = g * g * g
        order = wp.array(np.arange(2 * n, dtype=np.int32), dtype=wp.int32, device=dev)
        return cls(fx=wp.zeros(n, dtype=wp.vec3, device=dev), affine=matrix_array(n, float, dev, layout=model.matrix_layout),
                   keys=wp.zeros(n, dtype=wp.int32, device=dev), sort_keys=wp.zeros(2 * n, dtype=wp.int32, device=dev),
                   order=order, none_key=none_key, end_bit=max(1, int(none_key).bit_length()))


class _FixedScratch:
    """Scratch of the fixed-point reproducible P2G (``MPMSolver(deterministic=True)``): the
    int64 node sums ``q`` [7, n_grid^3] (momentum, mass, stress-free momentum), their scales
    ``scale_m``, ``scale_p`` (powers of two: the object's mass ``M`` [kg] and the momentum bound
    ``bound_p = M 64 dx / dt`` [kg m/s] at 2^61 units) and units ``unit_m``, ``unit_p`` (their
    inverses, float64), and ``overflow`` [1], set where a run sum reached 2^61 units."""

    def __init__(self, model: Model):
        p = model.params
        dev = model.device
        mass = float(np.asarray(model.mass_host, dtype=np.float64).sum())
        self.bound_p = mass * 64.0 * p.dx / p.dt
        if not (mass > 0.0 and math.isfinite(self.bound_p) and self.bound_p > 0.0):
            raise InputError("MPMSolver", "deterministic", f"fixed-point sums need a positive total mass and "
                             f"momentum bound, got {mass!r} kg and {self.bound_p!r} kg m/s")
        e_m = 61 - math.ceil(math.log2(mass))
        e_p = 61 - math.ceil(math.log2(self.bound_p))
        if max(abs(e_m), abs(e_p)) > 120:  # the scales are float32 kernel arguments
            raise InputError("MPMSolver", "deterministic", f"fixed-point scales 2^{e_m} and 2^{e_p} leave float32's "
                             f"range (total mass {mass:.3g} kg, momentum bound {self.bound_p:.3g} kg m/s)")
        self.scale_m, self.scale_p = math.ldexp(1.0, e_m), math.ldexp(1.0, e_p)
        self.unit_m, self.unit_p = wp.float64(math.ldexp(1.0, -e_m)), wp.float64(math.ldexp(1.0, -e_p))
        self.q = wp.zeros((7, p.n_grid ** 3), dtype=wp.int64, device=dev)
        self.overflow = wp.zeros(1, dtype=wp.int32, device=dev)

    @classmethod
    def placeholder(cls, device) -> _FixedScratch:
        """Stand-in arguments for the float window sums, which ignore them."""
        f = cls.__new__(cls)
        f.scale_m = f.scale_p = 1.0
        f.q = wp.zeros((7, 1), dtype=wp.int64, device=device)
        f.overflow = wp.zeros(1, dtype=wp.int32, device=device)
        return f


class _RecordScratch:
    """Scratch of the window sums by vector atomics (``MPMSolver(window_atomics="vector")``):
    the node records ``sums_mvm`` (momentum [kg m/s] and mass [kg]) and, under affine FLIP,
    ``sums_old`` (stress-free momentum [kg m/s], its fourth component unused), flat over the
    ``n_grid``^3 nodes, 16 bytes a node each; zero between substeps (the grid update reads and
    zeroes them)."""

    def __init__(self, model: Model):
        n = model.params.n_grid ** 3
        flip = model.params.transfer == "affine_flip"
        self.sums_mvm = wp.zeros(n, dtype=wp.vec4, device=model.device)
        self.sums_old = wp.zeros(n if flip else 1, dtype=wp.vec4, device=model.device)

    @classmethod
    def placeholder(cls, device) -> _RecordScratch:
        """Stand-in arguments for the window sums into the grid's arrays, which ignore them."""
        r = cls.__new__(cls)
        r.sums_mvm = wp.zeros(1, dtype=wp.vec4, device=device)
        r.sums_old = wp.zeros(1, dtype=wp.vec4, device=device)
        return r


class MPMSolver:
    """Advances a :class:`State` of a :class:`Model` by substeps of ``params.dt``.

    A guard runs every ``params.guard_every`` substeps (and on demand): non-finite values,
    a CFL number ``max|v| dt / dx`` above ``params.cfl_limit``, or particles leaving the
    domain stop the run with a :class:`~knockgs_core.errors.SimulationError`. The guard also
    sizes the active grid box for the next substeps. ``effect_scratch`` holds the scratch
    object of each of ``params.effects`` (same order), made by its ``setup`` here.

    ``p2g``: ``"scatter"`` (one float atomic per particle and stencil node; the CPU's),
    ``"cells"`` (particles sorted by base cell every :attr:`resort_every` substeps, summed by
    windows of :attr:`cell_chunk` sorted particles with one atomic per run of one base cell and
    stencil node: :func:`~knockgs_core.sim._kernels.p2g_windows`) or ``"auto"``: by cells on a
    CUDA device where the particles crowd their cells (:func:`cell_crowding` at least
    :attr:`CELLS_CROWDING`; counted on every device and recorded in ``crowding``), else the
    scatter.

    ``graph``: replay each substep as a captured graph (one per probe state and set of active
    supports, captured again when the guard moves the active box), which skips the host's
    launch overhead: a CUDA graph on a GPU; on the CPU (on request only) Warp replays the
    recorded launches, bit for bit the same substeps. ``"auto"``: on a CUDA device, for models
    without effects and particle translations (whose host-side hooks run every substep). The
    same kernels, in the same order, with the same arguments.

    ``fuse``: with the P2G by cells, end each substep with G2P fused with the next substep's
    per-particle P2G half (:func:`~knockgs_core.sim._kernels.g2p_prepare`, a kernel per
    transfer): one pass over the particles instead of two, the same bits. The next substep's probe impulse and rotation are
    then already in the state between substeps, so the solver must step that one state on
    (another state, or a state whose step count was changed, is refused), and nothing else may
    change it between substeps. ``"auto"``: where substeps are graphs and P2G is by cells.

    ``resort_every``, ``cell_chunk``, ``window_atomics``: the P2G by cells' settings (the class
    attributes of the same names document them); they set speed only.

    ``deterministic``: a GPU rollout the same bit for bit on every run. Float atomics add a
    node's contributions in the order the GPU schedules its threads, so the last bits of a GPU
    rollout vary between runs. Deterministic, the P2G is by cells (chosen whatever the
    crowding) and the windows' run sums, each summed in a fixed order, are added to the nodes
    as int64 fixed-point sums (:attr:`reproducible_sums`;
    :func:`~knockgs_core.sim._kernels.window_sums_fixed`), whose integer atomics give one sum in
    any order: no float atomics reach the grid. The same sums as the other variants, in another
    order and rounded to the fixed point's units (the CPU's scatter stays the default there).

    ``polar_step`` and ``polar_update``: the polar iterations' step near convergence and how it
    is taken, and ``g2p_sums``: how G2P sums its stencil (the class attributes of the same names
    document them). ``crowding``: the model's :func:`cell_crowding` where the caller
    has it (runs of one particle set share it: :func:`simulate_many` counts it once);
    computed from the model's rest positions otherwise.
    """

    #: cap on the warm-started polar iterations per particle and substep (they stop when the
    #: correction angle is below 1e-7 rad). Not a discretization knob: the stress needs the
    #: converged rotation. The Ficus's thin, fast-rotating parts need up to 8 iterations; a cap of
    #: 4 (the former value) moved its Probe-A response by 9 % and its dt sensitivity from 1.8 % to
    #: 6.5 % per halving (docs/assets.md). tests/test_sim_physics.py checks that it never binds.
    polar_iters = 32
    #: the polar iterations' step near convergence, a multiple of Mueller et al.'s
    #: (:func:`~knockgs_core.sim._kernels.polar_rotation`): 1.0 (theirs) or up to 1.9; 1.5
    #: takes ~3 iterations a particle where 1.0 takes ~8, to the same rotation (within its 1e-7
    #: rad). ``"auto"``: 1.5 on a GPU, 1.0 on the CPU (whose rollouts, and the tables made from
    #: them, keep their bits)
    polar_step: float | str = "auto"
    #: how the polar iterations rotate by a correction below 0.1 rad
    #: (:func:`~knockgs_core.sim._kernels.polar_rotation`): ``"axis_angle"`` (the axis and the
    #: angle's sine and cosine, Mueller et al.'s) or ``"rational"`` (the quaternion ``(h, 1)``
    #: normalized: no sine, cosine or square root, one division; the same converged rotation).
    #: ``"auto"``: rational on a GPU, axis and angle on the CPU (whose rollouts, and the tables
    #: made from them, keep their bits)
    polar_update: str = "auto"
    #: how G2P sums the node velocities into the particle's velocity and affine matrix:
    #: ``"nodes"`` (an outer product a node, :func:`~knockgs_core.sim._kernels.gather_by_nodes`)
    #: or ``"lines"`` (factored along the stencil's lines, ~300 multiply-adds a particle and field
    #: instead of ~700: :func:`~knockgs_core.sim._kernels.gather_by_lines`; the same sums in
    #: another order). ``"auto"``: lines on a GPU, nodes on the CPU (whose rollouts, and the
    #: tables made from them, keep their bits)
    g2p_sums: str = "auto"
    #: ``p2g="auto"`` on a CUDA device sums by cells from this :func:`cell_crowding` on (particles
    #: sharing a particle's base cell, on average), and scatters below it: where particles crowd
    #: their cells the scatter's atomics serialize on the shared nodes (measured on blocks at 1
    #: and 8 particles a cell: benchmarks/results/2026-11-26-graphs-crowding-cell-sums.md)
    CELLS_CROWDING = 4.0
    #: the P2G by cells sorts the particles by base cell every this many substeps; between sorts
    #: the windows follow the last order, their runs cut where a particle has changed cells since
    #: (the sums are right in any order: the interval sets speed only;
    #: benchmarks/results/2026-11-26-graphs-crowding-cell-sums.md)
    resort_every: int = 10
    #: sorted particles a window of the P2G by cells takes (a block's threads and its staged
    #: terms in shared memory: at most 256); a run of one base cell is cut at a window's ends
    cell_chunk: int = 32
    #: how the P2G by cells sums: by windows (:func:`~knockgs_core.sim._kernels.p2g_windows`),
    #: as benchmark reports record
    cell_sums: str = "windows"
    #: how the bitwise-reproducible P2G (``deterministic=True``) sums, as rollout metadata
    #: records: the windows' run sums added as int64 sums in units of a power of two (the
    #: object's mass, and its mass times 64 dx / dt, at 2^61 units or less, so a unit is 4e-19 to
    #: 9e-19 of each: of the momenta, 3e-17 to 6e-17 of the mass times dx / dt); integer atomics,
    #: so the sums and the rollout are the same in any order the GPU runs them; the grid update
    #: reads and zeroes them; a run sum added at or above 2^61 units stops the rollout at the next
    #: guard check (:meth:`check`); they hold 56 bytes a grid node. Their cost on a GPU:
    #: benchmarks/results/2026-11-28-fixed-point-sums.md
    reproducible_sums: str = "fixed_point"
    #: how the float window sums reach the nodes: ``"scalar"`` (one float atomic a component
    #: into the grid's momentum, mass and stress-free momentum arrays, zeroed before P2G) or
    #: ``"vector"`` (into vec4 node records of momentum and mass, and of the stress-free
    #: momentum, one 16-byte atomic each on a device of compute capability 9.0 or later; the
    #: grid update reads and zeroes them: :func:`~knockgs_core.sim._kernels.grid_update_records`).
    #: The same sums, added to each node in the same order wherever the atomics arrive in order
    #: (the CPU: the same bits). ``"auto"``: vector on a GPU where P2G sums by cells, scalar
    #: elsewhere. The bitwise-reproducible sums (``deterministic=True``) add no floats to the
    #: nodes, so the option does not apply there. Measured in
    #: benchmarks/results/2026-11-29-vector-atomics.md
    window_atomics: str = "auto"

    @classmethod
    def auto_p2g(cls, cuda: bool, crowding: float | None) -> str:
        """``p2g="auto"``'s choice: by cells on a CUDA device where the particles crowd their
        cells (atomics on shared nodes serialize there), the scatter elsewhere and always on
        the CPU."""
        return "cells" if cuda and crowding is not None and crowding >= cls.CELLS_CROWDING else "scatter"

    @staticmethod
    def auto_fuse(graph: bool, p2g: str) -> bool:
        """``fuse="auto"``'s choice: where substeps are graphs and P2G is by cells."""
        return bool(graph) and p2g == "cells"

    @classmethod
    def auto_options(cls, cuda: bool, *, crowding: float | None = math.inf, hooks: bool = False,
                     deterministic: bool = False) -> dict:
        """What the device-dependent options' ``"auto"`` chooses on a CUDA device (``cuda``) or
        the CPU: ``p2g``, ``graph``, ``fuse``, ``polar_step``, ``polar_update`` and
        ``g2p_sums``, for particles crowding their cells by ``crowding`` (:func:`cell_crowding`),
        a model with host-side hooks (``hooks``: effects or particle translations) or not, and
        the bitwise-reproducible P2G or not, and ``window_atomics``. The one place these choices
        are made (the constructor asks it); :data:`GPU_SOLVER_OPTIONS` is its answer for a GPU."""
        p2g = "cells" if deterministic else cls.auto_p2g(cuda, crowding)
        graph = bool(cuda) and not hooks
        return dict(p2g=p2g, graph=graph, fuse=cls.auto_fuse(graph, p2g), polar_step=1.5 if cuda else 1.0,
                    polar_update="rational" if cuda else "axis_angle", g2p_sums="lines" if cuda else "nodes",
                    window_atomics="vector" if cuda and p2g == "cells" and not deterministic else "scalar")

    def __init__(self, model: Model, *, p2g: str = "auto", graph: bool | str = "auto", fuse: bool | str = "auto",
                 resort_every: int | None = None, cell_chunk: int | None = None, deterministic: bool = False,
                 polar_step: float | str | None = None, polar_update: str | None = None, g2p_sums: str | None = None,
                 crowding: float | None = None, window_atomics: str | None = None):
        self.model = model
        self.deterministic = _flag("MPMSolver", "deterministic", deterministic)
        if resort_every is not None:
            self.resort_every = resort_every
        if cell_chunk is not None:
            self.cell_chunk = cell_chunk
        p = model.params
        cuda = wp.get_device(model.device).is_cuda
        hooks = bool(p.effects or model.translations)
        self.crowding = None
        if p2g == "auto" and not self.deterministic:  # the crowding is counted only where it chooses
            x0 = model.particle_x0_host
            if crowding is None:
                crowding = cell_crowding(x0, p.dx) if x0 is not None else math.inf
            self.crowding = float(crowding)
        auto = self.auto_options(cuda, crowding=math.inf if self.crowding is None else self.crowding, hooks=hooks,
                                 deterministic=self.deterministic)
        if polar_step is not None:
            self.polar_step = polar_step
        if self.polar_step == "auto":
            self.polar_step = auto["polar_step"]
        if isinstance(self.polar_step, bool) or not isinstance(self.polar_step, (int, float)) \
                or not 1.0 <= self.polar_step <= 1.9:
            raise InputError("MPMSolver", "polar_step", f"must be 'auto' or a number in [1, 1.9], got {self.polar_step!r}")
        self.polar_step = float(self.polar_step)
        if polar_update is not None:
            self.polar_update = polar_update
        if self.polar_update == "auto":
            self.polar_update = auto["polar_update"]
        if self.polar_update not in ("axis_angle", "rational"):
            raise InputError("MPMSolver", "polar_update",
                             f"must be 'auto', 'axis_angle' or 'rational', got {self.polar_update!r}")
        self._polar_rational = int(self.polar_update == "rational")
        if g2p_sums is not None:
            self.g2p_sums = g2p_sums
        if self.g2p_sums == "auto":
            self.g2p_sums = auto["g2p_sums"]
        if self.g2p_sums not in ("nodes", "lines"):
            raise InputError("MPMSolver", "g2p_sums", f"must be 'auto', 'nodes' or 'lines', got {self.g2p_sums!r}")
        self._g2p_lines = int(self.g2p_sums == "lines")
        if graph == "auto":
            graph = auto["graph"]
        if graph not in (True, False):
            raise InputError("MPMSolver", "graph", f"must be 'auto', True or False, got {graph!r}")
        if graph and hooks:
            raise InputError("MPMSolver", "graph", "substep graphs take models without effects and particle translations")
        self.graph = bool(graph)
        self._graphs: dict = {}
        if p2g == "auto":
            p2g = auto["p2g"]
        if p2g not in ("scatter", "cells"):
            raise InputError("MPMSolver", "p2g", f"must be 'auto', 'scatter' or 'cells', got {p2g!r}")
        self.p2g = p2g
        if self.deterministic and p2g != "cells":
            raise InputError("MPMSolver", "deterministic", "the bitwise-reproducible P2G sums by cells (p2g='cells' or 'auto')")
        if fuse == "auto":
            fuse = self.auto_fuse(self.graph, p2g)
        if fuse not in (True, False):
            raise InputError("MPMSolver", "fuse", f"must be 'auto', True or False, got {fuse!r}")
        if fuse and (p2g != "cells" or hooks):
            raise InputError("MPMSolver", "fuse", "fused substeps take the P2G by cells and models without effects "
                             "and particle translations")
        self.fuse = bool(fuse)
        self._prepared: tuple[int, int] | None = None  # (state, step) whose P2G terms the last G2P computed
        self._cells = _CellScratch.make(model) if p2g == "cells" else None
        self._fixed = _FixedScratch(model) if self.deterministic else None
        if window_atomics is not None:
            self.window_atomics = window_atomics
        if self.window_atomics not in ("auto", "scalar", "vector"):
            raise InputError("MPMSolver", "window_atomics",
                             f"must be 'auto', 'scalar' or 'vector', got {self.window_atomics!r}")
        # the bitwise-reproducible sums add no floats to the nodes: the option does not apply there
        float_windows = p2g == "cells" and not self.deterministic
        if self.window_atomics == "vector" and p2g != "cells":
            raise InputError("MPMSolver", "window_atomics", f"vector atomics add the window sums of p2g='cells', not {p2g!r}")
        if self.window_atomics == "auto":
            self.window_atomics = auto["window_atomics"] if float_windows else "scalar"
        self._records = _RecordScratch(model) if self.window_atomics == "vector" and float_windows else None
        # the window kernel's arguments that its variant ignores: stand-ins
        self._window_records = self._records
        if self._records is None and p2g == "cells":
            self._window_records = _RecordScratch.placeholder(model.device)
        self._window_fixed = self._fixed
        if self._fixed is None and p2g == "cells":
            self._window_fixed = _FixedScratch.placeholder(model.device)
        self._sorted_at: int | None = None  # the step of the last sort by cells
        self._inv_dx = 1.0 / p.dx
        self._lo = (0, 0, 0)
        self._hi = (p.n_grid, p.n_grid, p.n_grid)
        dev = model.device
        self._stats_f = wp.zeros(2, dtype=float, device=dev)
        self._stats_i = wp.zeros(9, dtype=wp.int32, device=dev)
        self._overrun = wp.zeros(1, dtype=wp.int32, device=dev)
        self._stats_zero = wp.zeros(1, dtype=wp.int32, device=dev)  # no reproducible P2G: no overflow
        self._zero_mask = wp.zeros(model.particle_count, dtype=wp.int32, device=dev)
        self.max_cfl = 0.0
        self.min_det_F = 1.0
        self.effect_scratch = tuple(effect.setup(model) for effect in p.effects)
        # the effects' Kelvin-Voigt viscous stress (stiffness-proportional damping), summed [s]
        self.retardation = float(sum(effect.viscous_retardation(model) for effect in p.effects))

    # -- guard -----------------------------------------------------------------------
    def check(self, state: State) -> dict:
        """Run the guard; resize the active box. Returns the statistics."""
        m, p = self.model, self.model.params
        wp.launch(K.guard_reset, dim=1, outputs=[self._stats_f, self._stats_i], device=m.device)
        per = K.STATS_PER_BLOCK
        overflow = self._stats_zero if self._fixed is None else self._fixed.overflow  # no reproducible P2G: no overflow
        wp.launch_tiled(K.particle_stats, dim=[max(1, -(-m.particle_count // per))],
                        inputs=[state.particle_x0, state.particle_u, state.particle_v, state.particle_F, self._inv_dx,
                                m.particle_count, per, self._overrun, overflow],
                        outputs=[self._stats_f, self._stats_i], block_dim=K.STATS_BLOCK_DIM, device=m.device)
        sf = self._stats_f.numpy()
        si = self._stats_i.numpy()  # with the overrun flag and the reproducible P2G's overflow (one read-back)
        overrun = int(si[7])
        if int(si[8]):
            raise SimulationError(f"the fixed-point P2G's sums overflowed by step {state.step}: a node's momentum "
                                  f"passed {self._fixed.bound_p:.4g} kg m/s (the object's mass times 64 dx / dt); "
                                  f"the motion is far beyond the CFL limit: reduce dt, or rerun with deterministic=False")
        t = state.step * p.dt
        where = f"at step {state.step} (t = {t:.6g} s)"
        elastic = m.max_wave_speed * p.dt / p.dx
        if elastic > p.elastic_cfl_limit:
            raise SimulationError(
                f"elastic CFL violation {where}: c_p dt / dx = {elastic:.3g} > {p.elastic_cfl_limit:g} "
                f"(fastest p-wave speed {m.max_wave_speed:.4g} m/s, dt = {p.dt:g} s, dx = {p.dx:.4g} m). "
                f"Likely cause: dt too large for the stiffest, lightest material; "
                f"use dt <= {p.elastic_cfl_limit * p.dx / m.max_wave_speed:.3g} s."
            )
        if si[0] > 0:
            raise SimulationError(
                f"simulation blew up {where}: {int(si[0])} particles have non-finite state. "
                f"Likely cause: substep dt = {p.dt:g} s too large for the stiffest material "
                f"(p-wave speed {m.max_wave_speed:.4g} m/s needs dt <~ {p.dx / max(m.max_wave_speed, 1e-12):.3g} s "
                f"at dx = {p.dx:.4g} m), or a probe force too strong."
            )
        vmax = math.sqrt(max(float(sf[0]), 0.0))
        cfl = vmax * p.dt / p.dx
        self.max_cfl = max(self.max_cfl, cfl)
        self.min_det_F = min(self.min_det_F, float(sf[1]))
        if cfl > p.cfl_limit:
            raise SimulationError(
                f"CFL violation {where}: max|v| dt / dx = {cfl:.3g} > {p.cfl_limit:g} "
                f"(max|v| = {vmax:.4g} m/s, dt = {p.dt:g} s, dx = {p.dx:.4g} m). "
                f"Likely cause: dt too large for this material or probe; reduce dt."
            )
        if overrun:
            raise SimulationError(
                f"particles outran the active grid region {where} (max|v| dt / dx = {cfl:.3g} now): "
                f"the motion accelerated between guard checks; likely cause: dt = {p.dt:g} s too large "
                f"for this material (unstable), or lower guard_every"
            )
        cmin, cmax = si[1:4], si[4:7]
        if cmin.min() < 2 or cmax.max() > p.n_grid - 3:
            raise SimulationError(
                f"particles left the simulation domain {where} (cells {cmin.tolist()}..{cmax.tolist()} of {p.n_grid})")
        # margin for the motion until the next check, in cells
        pad = 2 + int(math.ceil(2.0 * vmax * p.guard_every * p.dt / p.dx))
        self._lo = tuple(int(max(0, c - 1 - pad)) for c in cmin)
        self._hi = tuple(int(min(p.n_grid, c + 3 + pad)) for c in cmax)
        return {"cfl": cfl, "vmax": vmax, "min_det_F": float(sf[1])}

    # -- one substep -----------------------------------------------------------------
    def _record(self, state: State) -> None:
        """Record this substep's kernel launches for the current active box and state.

        Replaying a recorded launch skips Warp's per-call argument packing (~70 us a launch
        on the CPU), which otherwise dominates substeps of small models. Re-recorded when
        the guard moves the active box or another state is stepped."""
        m, p = self.model, self.model.params
        dt, dev = p.dt, m.device
        lo = wp.vec3i(*self._lo)
        hi = wp.vec3i(*self._hi)
        dims = tuple(h - low for low, h in zip(self._lo, self._hi))
        rec = dict(device=dev, record_cmd=True)
        flip = int(p.transfer == "affine_flip")
        cmds = {}
        cmds["zero"] = wp.launch(K.grid_zero, dim=dims, inputs=[lo, flip],
                                 outputs=[state.grid_mv, state.grid_m, state.grid_mv_old], **rec)
        # the particle inputs of both P2G variants (``probe_on`` is set per substep)
        particle_args = [state.particle_x0, state.particle_u, state.particle_C, state.particle_F,
                         m.particle_mass, m.particle_vol, m.particle_mu, m.particle_lam,
                         m.probe_mask, wp.vec3(*m.probe_force), 0, self._inv_dx, dt, self.polar_iters, self.polar_step,
                         self._polar_rational, self.retardation, lo, hi]
        if self._cells is not None:
            c = self._cells
            for name in ("resort_every", "cell_chunk"):
                value = getattr(self, name)
                if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                    raise InputError("MPMSolver", name, f"must be an integer >= 1, got {value!r}")
            if self.cell_chunk > 256:
                raise InputError("MPMSolver", "cell_chunk", f"a window takes at most 256 particles (a block's threads "
                                 f"and shared memory), got {self.cell_chunk}")
            cmds["p2g"] = wp.launch(
                K.p2g_prepare,
                dim=m.particle_count,
                inputs=[*particle_args, p.n_grid, c.none_key],
                outputs=[state.particle_v, state.particle_rot, c.fx, c.affine, c.keys, self._overrun],
                **rec,
            )
            cmds["p2g_sort_keys"] = wp.launch(K.p2g_sort_keys, dim=m.particle_count, inputs=[c.keys],
                                              outputs=[c.sort_keys, c.order], **rec)
            w = self.cell_chunk
            f, r = self._window_fixed, self._window_records
            fixed_args = [r.sums_mvm, r.sums_old, f.q, f.scale_m, f.scale_p, f.overflow]
            cmds["p2g_windows"] = wp.launch_tiled(
                K.p2g_windows(w, flip, self._fixed is not None, self._records is not None),
                dim=-(-m.particle_count // w),
                block_dim=w,
                inputs=[c.order, c.keys, c.none_key, m.particle_count, p.n_grid, self._inv_dx, c.fx,
                        state.particle_v, m.particle_mass, c.affine, state.particle_C],
                outputs=[state.grid_mv.flatten(), state.grid_m.flatten(), state.grid_mv_old.flatten(), *fixed_args],
                **rec,
            )
        else:  # one float atomic per particle and stencil node
            cmds["p2g"] = wp.launch(
                K.p2g,
                dim=m.particle_count,
                inputs=[*particle_args, flip],
                outputs=[state.particle_v, state.particle_rot, state.grid_mv, state.grid_m, state.grid_mv_old, self._overrun],
                **rec,
            )
        damping = p.grid_v_damping_scale ** (dt / p.damping_dt_ref) if p.grid_v_damping_scale < 1.0 else 1.0
        # domain walls listed first are applied in the update pass (same order, one pass less)
        fused = p.boundaries[0] if p.boundaries and isinstance(p.boundaries[0], DomainWalls) else None
        wall_args = [1, p.n_grid, fused.padding, int(fused.mode == "sticky")] if fused else [0, p.n_grid, 0, 0]
        update_args = [lo, dt, wp.vec3(*p.gravity), damping, *wall_args, flip, state.grid_m]
        if self._fixed is not None:  # from the fixed-point sums, zeroed there
            f = self._fixed
            cmds["update"] = wp.launch(K.grid_update_fixed, dim=dims,
                                       inputs=[*update_args[:-1], f.unit_m, f.unit_p, f.q],
                                       outputs=[state.grid_m, state.grid_mv, state.grid_mv_old], **rec)
        elif self._records is not None:  # from the node records, zeroed there
            r = self._records
            cmds["update"] = wp.launch(K.grid_update_records, dim=dims, inputs=[*update_args[:-1], r.sums_mvm, r.sums_old],
                                       outputs=[state.grid_m, state.grid_mv, state.grid_mv_old], **rec)
        else:
            cmds["update"] = wp.launch(K.grid_update, dim=dims, inputs=update_args,
                                       outputs=[state.grid_mv, state.grid_mv_old], **rec)
        bcs = []
        for bc in p.boundaries:
            if bc is fused:
                continue
            if isinstance(bc, DomainWalls):
                bcs.append((bc, wp.launch(K.grid_bc_walls, dim=dims, inputs=[lo, p.n_grid, bc.padding, int(bc.mode == "sticky")],
                                          outputs=[state.grid_mv], **rec)))
            elif isinstance(bc, FixedCuboid):
                box_args = [wp.vec3(*bc.box.center), wp.vec3(*bc.box.half_size), wp.vec3(*bc.velocity), bc.friction_coefficient]
                cmd = wp.launch(K.grid_bc_cuboid, dim=dims, inputs=[lo, p.dx, *box_args], outputs=[state.grid_mv], **rec)
                bcs.append((bc, cmd))
        cmds["bcs"] = bcs
        cmds["g2p"] = wp.launch(
            K.g2p,
            dim=m.particle_count,
            inputs=[state.grid_mv.flatten(), p.n_grid, self._inv_dx, dt, self._zero_mask, wp.vec3(0.0), 0, lo, hi,
                    state.particle_x0, flip, p.flip_weight, state.grid_mv_old.flatten(), self._g2p_lines],
            outputs=[state.particle_u, state.particle_v, state.particle_C, state.particle_F, self._overrun],
            **rec,
        )
        if self.fuse:
            c = self._cells
            cmds["g2p_prepare"] = wp.launch(
                K.g2p_prepare(flip),
                dim=m.particle_count,
                inputs=[state.grid_mv.flatten(), self._inv_dx, dt, self._zero_mask, wp.vec3(0.0), 0, lo, hi,
                        state.particle_x0, p.flip_weight, state.grid_mv_old.flatten(), self._g2p_lines,
                        m.particle_mass,
                        m.particle_vol, m.particle_mu, m.particle_lam, m.probe_mask, wp.vec3(*m.probe_force), 0,
                        self.polar_iters, self.polar_step, self._polar_rational, self.retardation, p.n_grid, c.none_key],
                outputs=[state.particle_u, state.particle_v, state.particle_C, state.particle_F, state.particle_rot,
                         c.fx, c.affine, c.keys, self._overrun],
                **rec,
            )
        self._cmds = cmds
        self._cmds_key = (id(state), self._lo, self._hi)
        self._graphs = {}  # graphs of the launches recorded before
        self._box = (lo, dims)  # the active box as the effects' grid hooks take it

    def step(self, state: State) -> None:
        """Advance ``state`` by one substep: P2G (probe force included), grid update, boundary
        conditions, effects on the grid, G2P (particle translation included), effects on the
        particles."""
        m, p = self.model, self.model.params
        prepared = self._prepared is not None
        if prepared and self._prepared != (id(state), state.step):
            raise InputError("MPMSolver", "fuse", "a solver with fused substeps steps one state on, substep by substep "
                             "(its next P2G terms are computed); use a solver per state, or fuse=False")
        if getattr(self, "_cmds_key", None) != (id(state), self._lo, self._hi):
            self._record(state)
        t = state.step * p.dt
        probe_on = self._probe_on(state.step)
        active = tuple(isinstance(bc, DomainWalls) or bc.start_time <= t < bc.end_time for bc, _ in self._cmds["bcs"])
        sort = self._cells is not None and (self._sorted_at is None or not 0 <= state.step - self._sorted_at < self.resort_every)
        if sort:
            self._sorted_at = state.step
        # fused: this substep's P2G terms came with the last G2P; this G2P computes the next's
        probe_next = self._probe_on(state.step + 1) if self.fuse else None
        if self.graph:
            key = (None if prepared else probe_on, probe_next, active, sort)
            graph = self._graphs.get(key)
            if graph is None:
                with wp.ScopedCapture(device=m.device) as capture:
                    self._launch(state, t, probe_on, active, sort, prepared=prepared, probe_next=probe_next)
                graph = self._graphs[key] = capture.graph
            wp.capture_launch(graph)
        else:
            self._launch(state, t, probe_on, active, sort, prepared=prepared, probe_next=probe_next)
        for effect, scratch in zip(p.effects, self.effect_scratch):
            effect.apply_particles(m, state, scratch, t)
        state.step += 1
        if self.fuse:
            self._prepared = (id(state), state.step)

    def _probe_on(self, step: int) -> int:
        """1 where the probe pushes during substep ``step``, else 0."""
        m = self.model
        return int(m.probe_steps > 0 and m.probe_first <= step < m.probe_first + m.probe_steps)

    def _launch(self, state: State, t: float, probe_on: int, active: tuple[bool, ...], sort: bool = False, *,
                prepared: bool = False, probe_next: int | None = None) -> None:
        """The substep's launches at time ``t`` [s] up to G2P: P2G with the probe ``probe_on``
        (by cells: sorted by base cell first where ``sort``; its per-particle half skipped where
        ``prepared`` by the last G2P),
        the grid update, the supports flagged ``active``, the effects on the grid, G2P with the
        particle translation active at ``t`` (:meth:`step` adds the effects on the particles),
        fused with the next substep's per-particle P2G half (its probe ``probe_next``) unless
        that is None."""
        m, p = self.model, self.model.params
        cmds = self._cmds
        if self._fixed is None and self._records is None:  # these write every node of the box
            cmds["zero"].launch()
        if not prepared:
            cmds["p2g"].set_param_by_name("probe_on", probe_on)
            cmds["p2g"].launch()
        if self._cells is not None:  # (sort by base cell,) then sum by windows
            c = self._cells
            if sort:
                cmds["p2g_sort_keys"].launch()
                wp.utils.radix_sort_pairs(c.sort_keys, c.order, m.particle_count, end_bit=c.end_bit)
            cmds["p2g_windows"].launch()
        cmds["update"].launch()
        for (_, cmd), on in zip(cmds["bcs"], active):
            if on:
                cmd.launch()
        for effect, scratch in zip(p.effects, self.effect_scratch):
            effect.apply_grid(m, state, scratch, *self._box, t)
        if probe_next is not None:
            cmds["g2p_prepare"].set_param_by_name("probe_on", probe_next)
            cmds["g2p_prepare"].launch()
            return
        if m.translations:
            self._set_translation(cmds["g2p"], t)
        cmds["g2p"].launch()

    def _set_translation(self, g2p, t: float) -> None:
        """Point the recorded G2P launch at the particle translation active at ``t``, if any
        (:func:`build_model` allows at most one at a time)."""
        mask, velocity, on = self._zero_mask, wp.vec3(0.0), 0
        for bc, selection in self.model.translations:
            if bc.start_time <= t < bc.end_time:
                mask, velocity, on = selection, wp.vec3(*bc.velocity), 1
        g2p.set_param_by_name("trans_mask", mask)
        g2p.set_param_by_name("trans_velocity", velocity)
        g2p.set_param_by_name("trans_on", on)

    def momentum(self, state: State) -> np.ndarray:
        """Total particle momentum [kg m/s], accumulated in float64 on the host."""
        v = state.particle_v.numpy().astype(np.float64)
        return (self.model.mass_host.astype(np.float64)[:, None] * v).sum(axis=0)


# the windows' kernels of the default size (both transfers), made with the module (as the
# overloads: a kernel first made when a solver records its launches would make Warp build the
# module again)
for _flip in (0, 1):
    for _fixed, _records in ((False, False), (True, False), (False, True)):
        K.p2g_windows(MPMSolver.cell_chunk, _flip, _fixed, _records)


#: the substep a CUDA device runs where the CPU runs another, as :class:`MPMSolver`'s options:
#: :meth:`MPMSolver.auto_options` for a CUDA device and a model without effects whose particles
#: crowd their cells, as the paper's objects and the verification block are. Given to
#: :func:`simulate_many` on the CPU (``solver_options=GPU_SOLVER_OPTIONS``, the model built with
#: :data:`GPU_STORAGE`), they replay a GPU's substep there: the same sums, in the order the CPU
#: adds them. The paper profile adds ``deterministic=True``.
GPU_SOLVER_OPTIONS: Mapping = MappingProxyType(MPMSolver.auto_options(True))
#: how a CUDA device stores a model's per-particle matrices and F (:func:`build_model`'s
#: keywords): :func:`device_storage` for a CUDA device
GPU_STORAGE: Mapping = MappingProxyType(device_storage(True))


def _solver_options(options: Mapping | None) -> dict:
    """``options`` checked as :class:`MPMSolver` keywords that :func:`simulate_many` passes on
    (``deterministic`` and ``crowding`` it sets itself)."""
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise InputError("simulation", "solver_options", f"must be a mapping of MPMSolver options, got {type(options).__name__}")
    known = [k for k in inspect.signature(MPMSolver.__init__).parameters if k not in ("self", "model", "crowding")]
    for key in options:
        if key == "deterministic":
            raise InputError("simulation", "solver_options", "pass deterministic= to the simulation, not as a solver option")
        if key not in known:
            raise InputError("simulation", "solver_options",
                             f"unknown option {key!r}; MPMSolver takes {', '.join(k for k in known if k != 'deterministic')}")
    return dict(options)


def simulate(
    model: Model,
    state: State,
    *,
    frame_dt: float,
    n_frames: int,
    export_F: int = 0,
    progress: Callable[[int, int, dict], None] | None = None,
    deterministic: bool = False,
    solver_options: Mapping | None = None,
) -> SimResult:
    """Run from ``state`` (at step 0) and export ``n_frames`` frames every ``frame_dt`` [s],
    the first at t = 0. ``export_F`` > 0 also exports the deformation gradient of the first
    ``export_F`` particles (the Gaussian-associated ones). ``progress(frame, n_frames, stats)``
    is called after each exported frame. ``deterministic`` and ``solver_options``: as in
    :func:`simulate_many`."""
    report = None if progress is None else (lambda run, frame, n, stats: progress(frame, n, stats))
    return simulate_many([(model, state)], frame_dt=frame_dt, n_frames=n_frames, export_F=export_F, progress=report,
                         deterministic=deterministic, solver_options=solver_options)[0]


class _Exporter:
    """Writes a state's positions (and the first ``n_F`` deformation gradients) into frame
    arrays: on the host as the state holds them, or, with ``index``, gathered on the device
    in that order (row i is particle ``index[i]``).

    A frame is staged (:meth:`stage`) and then taken into the arrays (:meth:`take`). With
    ``index`` on a GPU, staging gathers the rows and copies them into pinned host memory in
    the current stream's order without waiting (``pending``); taking waits for those copies.
    So the caller can enqueue the next substeps between the two and the GPU keeps working
    while the frame comes back. Elsewhere staging copies the frame at once."""

    def __init__(self, model: Model, n_F: int, index: np.ndarray | None):
        self.n_F = n_F
        self.index = None
        self.pending = None  # the event after a staged frame's copies on a GPU
        self._staged: tuple[np.ndarray, np.ndarray | None] | None = None  # a frame staged on the host
        if index is not None:
            index = np.asarray(index)
            n = model.particle_count
            if index.shape != (n,) or (n and (index.min() < 0 or index.max() >= n)):
                raise InputError("simulation", "export_index", f"must be {n} particle indices, got shape {index.shape}")
            dev = model.device
            self.cuda = wp.get_device(dev).is_cuda
            self.index = wp.array(index.astype(np.int32), dtype=wp.int32, device=dev)
            self.x = wp.empty(n, dtype=wp.vec3, device=dev)
            self.F = wp.empty(n_F, dtype=wp.mat33, device=dev) if n_F else None
            if self.cuda:  # the frames' way back: pinned host copies, filled in the stream's order
                self.x_host = wp.empty(n, dtype=wp.vec3, device="cpu", pinned=True)
                self.F_host = wp.empty(n_F, dtype=wp.mat33, device="cpu", pinned=True) if n_F else None
                self.event = wp.Event(dev)

    def stage(self, state: State) -> None:
        """Start exporting ``state``'s frame (see the class); at most one frame is staged."""
        if self.index is None:
            self._staged = (state.positions(),
                            state.deformation_gradients()[: self.n_F].astype(np.float32) if self.n_F else None)
            return
        dev = self.x.device
        wp.launch(K.gather_positions, dim=len(self.x), inputs=[state.particle_x0, state.particle_u, self.index],
                  outputs=[self.x], device=dev)
        if self.n_F:
            wp.launch(K.gather_F, dim=self.n_F, inputs=[state.particle_F, self.index], outputs=[self.F], device=dev)
        if not self.cuda:
            self._staged = (self.x.numpy().copy(), self.F.numpy().copy() if self.n_F else None)
            return
        stream = wp.get_stream(dev)  # the gathers' stream: the device's current one
        wp.copy(self.x_host, self.x, stream=stream)
        if self.n_F:
            wp.copy(self.F_host, self.F, stream=stream)
        self.pending = stream.record_event(self.event)

    def take(self, X: np.ndarray, F: np.ndarray | None, frame: int) -> None:
        """Write the staged frame into row ``frame`` of ``X`` (and of ``F`` where given)."""
        if self.pending is not None:  # the copies into the pinned host arrays, then the arrays
            wp.synchronize_event(self.pending)
            self.pending = None
            self._staged = (self.x_host.numpy(), self.F_host.numpy() if self.n_F else None)
        staged, self._staged = self._staged, None
        X[frame] = staged[0]
        if F is not None:
            F[frame] = staged[1]

    def export(self, state: State, X: np.ndarray, F: np.ndarray | None, frame: int) -> None:
        """Stage and take ``state``'s frame at once."""
        self.stage(state)
        self.take(X, F, frame)


def simulate_many(
    runs: list[tuple[Model, State]],
    *,
    frame_dt: float,
    n_frames: int,
    export_F: int = 0,
    progress: Callable[[int, int, int, dict], None] | None = None,
    concurrent: bool = False,
    export_index: np.ndarray | None = None,
    on_frame: Callable[[int, int, np.ndarray, np.ndarray | None], None] | None = None,
    deterministic: bool = False,
    solver_options: Mapping | None = None,
) -> list[SimResult]:
    """Run several independent simulations (``runs``: (model, state) pairs, all with the same
    time step) in lockstep and export the same frames from each, as :func:`simulate` does.

    Every substep steps each run in turn, then runs the guard checks that are due, so each run
    sees exactly the operations it would see alone: on the CPU the results equal those of
    separate :func:`simulate` calls bit for bit. With ``concurrent`` on a CUDA device each run
    gets its own stream, so the GPU overlaps the runs' kernels (P2G's atomics on different
    grids do not wait for each other); a guard check waits only for its own run's stream.
    ``progress(run, frame, n_frames, stats)`` is called after each exported frame of each
    run. ``export_index`` [particle_count] int: exported row i is particle ``export_index[i]``
    (gathered on the device: a model simulated in another order, e.g. by grid cell, exports in
    its particle set's order); the first ``export_F`` rows of it give the deformation gradients.
    ``on_frame(run, frame, positions, F)`` is called once each frame of each run is exported,
    frame 0 included, in frame order (before ``progress``; with ``export_index`` on a GPU the
    frame comes back behind the next substeps and is handed over before the host's next wait
    on the device, else right away): ``positions`` [particle_count, 3]
    float32 [m] and ``F`` [export_F, 3, 3] float32 (None without ``export_F``) are that
    frame's rows of the result's arrays, final once handed over (a consumer may keep them
    without a copy, and must not write to them), e.g. to write the frame while the next one
    is simulated. ``deterministic``: each run's solver with the bitwise-reproducible P2G
    (:class:`MPMSolver`'s option: a GPU rollout the same bit for bit on every run; True or
    False only, refused otherwise). ``solver_options``:
    further keywords of each run's :class:`MPMSolver` (e.g. :data:`GPU_SOLVER_OPTIONS`; None:
    the device's choices); an unknown key is refused by name. Returns one :class:`SimResult`
    per run, in order."""
    options = _solver_options(solver_options)
    deterministic = _flag("simulation", "deterministic", deterministic)
    if not runs:
        return []
    dts = {m.params.dt for m, _ in runs}
    if len(dts) != 1:
        raise InputError("simulation", "dt", f"runs simulated together must share one time step, got {sorted(dts)}")
    p0 = runs[0][0].params
    ratio = frame_dt / p0.dt
    steps_per_frame = int(round(ratio))
    if steps_per_frame < 1 or abs(ratio - steps_per_frame) > 1e-6 * max(1.0, ratio):
        raise InputError("simulation", "frame_dt", f"frame_dt = {frame_dt:g} s must be a whole multiple of dt = {p0.dt:g} s")
    streams = None
    if concurrent and len(runs) > 1 and wp.get_device(runs[0][0].device).is_cuda:
        device = runs[0][0].device
        wp.synchronize_device(device)  # the models' arrays are ready before other streams read them
        streams = [wp.Stream(device) for _ in runs]

    def on(i):
        return wp.ScopedStream(streams[i]) if streams else contextlib.nullcontext()

    exporters = [_Exporter(model, export_F, export_index) for model, _ in runs]
    solvers, positions, Fs, stats = [], [], [], []
    crowding: dict[tuple, float | None] = {}  # runs of one particle set and grid count their cells once
    for i, (model, state) in enumerate(runs):
        with on(i):
            shared = (id(model.particle_x0_host), model.params.dx)
            solver = MPMSolver(model, deterministic=deterministic, crowding=crowding.get(shared), **options)
            crowding[shared] = solver.crowding
            n = model.particle_count
            X = np.empty((n_frames, n, 3), dtype=np.float32)
            F = np.empty((n_frames, export_F, 3, 3), dtype=np.float32) if export_F else None
            stats.append(solver.check(state))
            exporters[i].export(state, X, F, 0)
        if on_frame is not None:
            on_frame(i, 0, X[0], None if F is None else F[0])
        solvers.append(solver)
        positions.append(X)
        Fs.append(F)
    # (run, frame, its statistics) staged and not yet taken: on a GPU a frame's copies run
    # behind the next substeps, and the frame is handed over before the host waits on anything
    # else (the next guard check or frame)
    staged: list[tuple[int, int, dict]] = []

    def hand_over() -> None:
        for i, f, st in staged:
            exporters[i].take(positions[i], Fs[i], f)
            if on_frame is not None:
                on_frame(i, f, positions[i][f], None if Fs[i] is None else Fs[i][f])
            if progress is not None:
                progress(i, f, n_frames, st)
        staged.clear()

    for frame in range(1, n_frames):
        for s in range(steps_per_frame):
            for i, (model, state) in enumerate(runs):
                with on(i):
                    solvers[i].step(state)
            for i, (model, state) in enumerate(runs):
                # the guard runs every guard_every substeps and right after the probe's first
                # substep (velocities jump there, and the active box must follow)
                if state.step % model.params.guard_every == 0 or (model.probe_steps and state.step == model.probe_first + 1):
                    hand_over()
                    with on(i):
                        stats[i] = solvers[i].check(state)
        hand_over()
        for i, (model, state) in enumerate(runs):
            with on(i):
                stats[i] = solvers[i].check(state)
                exporters[i].stage(state)
            staged.append((i, frame, stats[i]))
        if not any(e.pending is not None for e in exporters):
            hand_over()  # staged on the host: handed over at once, as each frame is exported
    hand_over()
    times = np.arange(n_frames, dtype=np.float64) * frame_dt
    return [
        SimResult(times=times.copy(), positions=positions[i], F=Fs[i],
                  stats={"max_cfl": solver.max_cfl, "min_det_F": solver.min_det_F, "steps": state.step,
                         "steps_per_frame": steps_per_frame},
                  reproducible_sums=solver.reproducible_sums if solver.deterministic else None)
        for i, (solver, (_, state)) in enumerate(zip(solvers, runs))
    ]
