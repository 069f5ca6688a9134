"""The simulator's data: a static :class:`Model` (particles, materials, boundary conditions,
probe) and a time-varying :class:`State`, built by :func:`build_model` and :func:`make_state`,
and how their per-particle matrices and deformation gradients are stored on a device
(:func:`matrix_array`, :func:`deformation_array`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np
import warp as wp

from .._warp import warp_device
from ..errors import InputError
from . import _kernels as K
from ._config import ParticleTranslation, Probe, SimParams, probe_weights
from ._protocol import Effect

__all__ = ["Model", "State", "build_model", "make_state", "particle_volumes", "cell_crowding", "default_device",
           "device_storage", "GPU_STORAGE", "matrix_array", "deformation_array", "matrices"]


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


def body_volume(particles, dx: float) -> float:
    """The volume [m^3] the simulator gives ``particles`` on a grid of cell ``dx`` [m]: their
    own rest volumes, or ``dx^3 / (particles in the cell)`` each (occupied cells x dx^3)."""
    vol = particles.volumes if particles.volumes is not None else particle_volumes(particles.positions, dx)
    return float(np.sum(vol, dtype=np.float64))


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
    (particle_count,). ``probe_weight`` [-] (particle_count,) float32 is each particle's share
    of the probe (0 outside its box, selected once at t = 0; mean 1 over the selected
    particles, :func:`probe_weights`); ``probe_force`` is the per-step force on a particle of
    weight 1 [N] for steps ``probe_first <= step < probe_first + probe_steps``. ``translations`` pairs each
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
    probe_weight: wp.array
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
    each of its 9 rows starts 128-byte aligned on the GPU (unaligned rows stream slower:
    benchmarks/results/2026-11-27-window-sums-and-reference.md)."""
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
    component of 32 particles from one stretch of memory (the faster layout on a GPU);
    ``"records"``, shape (n,) of ``mat33``/``mat33d``: each particle's matrix in one piece (the
    faster on the CPU); ``"auto"``: components on a GPU, records on the CPU (measured in
    benchmarks/results/2026-11-27-layout-and-instructions.md). The values, and on the CPU the
    bits, are the same in both.
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


#: how a CUDA device stores a model's per-particle matrices and F (:func:`build_model`'s
#: keywords): :func:`device_storage` for a CUDA device
GPU_STORAGE: Mapping = MappingProxyType(device_storage(True))


def _as_particle_array(value, n: int, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise InputError("material", name, f"expected a scalar or shape ({n},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError("material", name, "non-finite value")
    return arr


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
    probe_by_mass: bool = False,
    device: str | None = None,
    matrix_layout: str = "auto",
    deformation_storage: str = "auto",
) -> Model:
    """Build the static model for particles at ``positions`` [m] (N, 3).

    ``E`` [Pa], ``nu`` [-], ``rho`` [kg/m^3]: scalars or per-particle arrays (theta already
    applied), then passed through each effect's ``materials`` hook. ``volumes`` [m^3]
    default to initial particles per cell. The probe's per-particle force is multiplied by
    ``probe_force_scale`` and rescaled so its impulse is kept at ``params.dt``; its contact
    box selects particles once, here, and shares the force among them by :func:`probe_weights`
    (equally, or by mass with ``probe_by_mass``: particles that carry their own volumes).
    ``params.effects`` must be :class:`Effect` instances and at most one
    :class:`ParticleTranslation` may be active at any time.
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

    weight = np.zeros(n, dtype=np.float32)
    force = (0.0, 0.0, 0.0)
    first = steps = count = 0
    if probe is not None:
        sel = np.ones(n, dtype=bool) if probe.box is None else probe.box.contains(x)
        count = int(sel.sum())
        if count == 0:
            raise InputError(f"probe {probe.name}", "box", "the contact box selects no particles")
        weight = probe_weights(sel, mass if probe_by_mass else None)
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
        probe_weight=wp.array(weight, dtype=float, device=device),
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
