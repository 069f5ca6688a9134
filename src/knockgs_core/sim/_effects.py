"""Extra physics terms ("effects") the simulator can switch on; every one is off by default.

An effect is a frozen dataclass deriving from :class:`~knockgs_core.sim.Effect` (the
protocol, :mod:`knockgs_core.sim._protocol`), placed in :attr:`SimParams.effects` by
:func:`with_effects`: ``with_effects(params, e1, e2)`` is the one way to switch effects on.
It overrides the hooks of the stages it acts at (materials when the model is built, the
grid after the boundary conditions, the particles after the grid-to-particle transfer);
what it keeps while a rollout runs is a scratch object returned by its ``setup(model)``
and held by the solver.

Each effect has one scalar *strength* parameter, named by its class attribute
``parameter``, whose value ``off`` (also a class attribute) makes the effect a no-op;
``effect.value`` reads it and ``effect.with_value(v)`` returns a copy with a new value.
Units are in each docstring; lengths are in the normalized domain [m], times [s].

Catalogue (the terms a discrepancy analysis may add): :class:`VelocityDamping`,
:class:`Gravity`, :class:`VonMisesPlasticity`, :class:`PoissonShift`,
:class:`StiffnessGradient`, :class:`MaterialViscosity`, :class:`SupportSlip`,
:class:`SupportFriction`. Two further terms,
:class:`BodyForcePulse` (a time-varying external force) and :class:`HiddenMass`
(extra mass in a region), model disturbances outside that catalogue.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import warp as wp

from ..errors import InputError
from . import _kernels as K
from ._config import Box, FixedCuboid, SimParams, is_still_sticky
from ._protocol import Effect

__all__ = [
    "Effect",
    "ParticleSelection",
    "PlasticStrain",
    "VelocityDamping",
    "Gravity",
    "VonMisesPlasticity",
    "PoissonShift",
    "StiffnessGradient",
    "MaterialViscosity",
    "viscous_stability_limit",
    "SupportFriction",
    "SupportSlip",
    "BodyForcePulse",
    "HiddenMass",
    "with_effects",
    "effect_examples",
]

Vec3 = tuple[float, float, float]


# --------------------------------------------------------------------------------------
# kernels
# --------------------------------------------------------------------------------------
@wp.kernel
def grid_scale_velocity(
    lo: wp.vec3i,
    factor: float,
    grid_m: wp.array3d(dtype=float),
    grid_v: wp.array3d(dtype=wp.vec3),
):
    """Multiply the velocity of every node with mass by ``factor``; in place."""
    i, j, k = wp.tid()
    gi = i + lo[0]
    gj = j + lo[1]
    gk = k + lo[2]
    if grid_m[gi, gj, gk] > 1.0e-15:
        grid_v[gi, gj, gk] = grid_v[gi, gj, gk] * factor


@wp.kernel
def particle_add_velocity(
    mask: wp.array(dtype=wp.int32),
    dv: wp.vec3,
    v: wp.array(dtype=wp.vec3),
):
    """``v += dv`` for the particles with ``mask != 0``; in place."""
    p = wp.tid()
    if mask[p] != 0:
        v[p] = v[p] + dv


@wp.kernel
def grid_support_slip(
    lo: wp.vec3i,
    dx: float,
    center: wp.vec3,
    half_size: wp.vec3,
    factor: float,
    grid_m: wp.array3d(dtype=float),
    grid_v: wp.array3d(dtype=wp.vec3),
):
    """A still support with viscous slip: nodes with mass inside the box lose the velocity
    component along the outward normal of the nearest box face (no penetration, no
    separation) and keep ``factor`` of their tangential velocity; in place."""
    i, j, k = wp.tid()
    gi = i + lo[0]
    gj = j + lo[1]
    gk = k + lo[2]
    if grid_m[gi, gj, gk] <= 1.0e-15:
        return
    p = wp.vec3(float(gi), float(gj), float(gk)) * dx - center
    if K.node_in_box(p, half_size, dx):
        n = K.nearest_face_normal(p, half_size)
        v = grid_v[gi, gj, gk]
        grid_v[gi, gj, gk] = (v - wp.dot(v, n) * n) * factor


@wp.func
def _log_strain(s: float) -> float:
    return wp.log(wp.max(s, 1.0e-6))


@wp.kernel
def von_mises_return(
    mu: wp.array(dtype=float),
    yield_stress: float,
    F: Any,
    plastic: wp.array(dtype=float),
):
    """Von Mises return mapping on the elastic deformation gradient (PhysGaussian's).

    With ``F = U diag(s) V^T`` and the Hencky strain ``e = log s``, the deviatoric Kirchhoff
    stress of the fixed-corotated model is about ``2 mu dev(e)``; where its norm exceeds
    ``yield_stress`` the deviatoric strain is projected back onto the yield surface,
    ``dev(e) <- dev(e) * yield_stress / (2 mu |dev(e)|)``, keeping the volumetric part.
    ``plastic`` accumulates the plastic strain increment ``|dev(e)| - yield_stress / (2 mu)``.
    """
    p = wp.tid()
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(K.mat33_to_f32(K.mat33d_at(F, p)), U, s, V)
    e = wp.vec3(_log_strain(s[0]), _log_strain(s[1]), _log_strain(s[2]))
    mean = (e[0] + e[1] + e[2]) / 3.0
    dev = e - wp.vec3(mean)
    norm = wp.length(dev)
    limit = yield_stress / (2.0 * mu[p])
    if norm > limit:
        e = wp.vec3(mean) + dev * (limit / norm)
        S = wp.mat33(wp.exp(e[0]), 0.0, 0.0, 0.0, wp.exp(e[1]), 0.0, 0.0, 0.0, wp.exp(e[2]))
        K.mat33d_put(F, p, K.mat33_to_f64(U * S * wp.transpose(V)))
        plastic[p] = plastic[p] + (norm - limit)


K.overload_per_layout(von_mises_return, f64=("F",))


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------
@dataclass
class ParticleSelection:
    """Scratch of an effect acting on a set of particles selected once, at t = 0 (from the
    model's rest positions): ``mask`` int32, shape (particle_count,), 1 = selected."""

    mask: wp.array


@dataclass
class PlasticStrain:
    """Scratch of :class:`VonMisesPlasticity`: accumulated plastic strain increments [-],
    float, shape (particle_count,)."""

    plastic_strain: wp.array


def _launch(model, kernel, dim, inputs, outputs) -> None:
    """Launch an effect's kernel on the model's device."""
    wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=model.device)


def _add_velocity(model, state, mask, dv) -> None:
    """``v += dv`` on the particles selected by ``mask`` (int32, one per particle)."""
    _launch(model, particle_add_velocity, model.particle_count, [mask, wp.vec3(*dv)], [state.particle_v])


def _finite(name: str, field: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise InputError(name, field, f"must be finite, got {value!r}")
    return value


def _unit(name: str, direction) -> np.ndarray:
    d = np.asarray(direction, dtype=np.float64)
    if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
        raise InputError(name, "direction", f"must be a non-zero 3-vector, got {direction!r}")
    return d / np.linalg.norm(d)


def _reapply_moving_supports(model, state, lo, dims, t) -> None:
    """Re-impose sticky supports that move (a velocity scaling would otherwise change them)."""
    p = model.params
    for bc in p.boundaries:
        if isinstance(bc, FixedCuboid) and bc.friction is None and any(bc.velocity) and bc.start_time <= t < bc.end_time:
            _launch(model, K.grid_bc_cuboid, dims,
                    [lo, p.dx, wp.vec3(*bc.box.center), wp.vec3(*bc.box.half_size), wp.vec3(*bc.velocity), -1.0], [state.grid_mv])


# --------------------------------------------------------------------------------------
# the catalogue
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class VelocityDamping(Effect):
    """Viscous velocity damping: every substep, node velocities (nodes with mass) are
    multiplied by ``exp(-rate * dt)``, so free motion decays as ``exp(-rate t)``.

    ``rate`` [1/s] >= 0; 0 is off. (PhysGaussian's ``grid_v_damping_scale`` ``s`` per step
    is ``rate = -log(s) / dt``.)"""

    rate: float = 0.0
    name: ClassVar[str] = "damping"
    parameter: ClassVar[str] = "rate"
    unit: ClassVar[str] = "1/s"

    def __post_init__(self):
        if _finite("VelocityDamping", "rate", self.rate) < 0:
            raise InputError("VelocityDamping", "rate", f"must be >= 0, got {self.rate!r}")

    def apply_grid(self, model, state, scratch, lo, dims, t):
        if self.rate == 0.0:
            return
        factor = math.exp(-self.rate * model.params.dt)
        _launch(model, grid_scale_velocity, dims, [lo, factor, state.grid_m], [state.grid_mv])
        _reapply_moving_supports(model, state, lo, dims, t)


@dataclass(frozen=True)
class Gravity(Effect):
    """Extra uniform body acceleration ``g * direction`` [m/s^2] (self-weight: the object
    sags onto its support). Added to particle velocities after each grid-to-particle
    transfer, so the next transfer carries it to the grid before the boundary conditions
    act (supports hold it). Adds to any gravity the contract already has.

    ``g`` [m/s^2], any sign (negative reverses ``direction``); 0 is off. ``direction``:
    unit vector, default ``(0, 0, -1)``."""

    g: float = 0.0
    direction: Vec3 = (0.0, 0.0, -1.0)
    name: ClassVar[str] = "gravity"
    parameter: ClassVar[str] = "g"
    unit: ClassVar[str] = "m/s^2"

    def __post_init__(self):
        _finite("Gravity", "g", self.g)
        _unit("Gravity", self.direction)

    def setup(self, model):
        if self.g == 0.0:
            return None
        return ParticleSelection(wp.ones(model.particle_count, dtype=wp.int32, device=model.device))

    def apply_particles(self, model, state, scratch, t):
        if self.g == 0.0:
            return
        _add_velocity(model, state, scratch.mask, _unit("Gravity", self.direction) * (self.g * model.params.dt))


@dataclass(frozen=True)
class VonMisesPlasticity(Effect):
    """Von Mises plasticity (permanent set): the deviatoric Kirchhoff stress norm is capped at
    ``yield_stress`` [Pa] by a return mapping on the elastic deformation gradient after each
    grid-to-particle transfer (PhysGaussian's von Mises model on top of fixed-corotated).
    ``inf`` is off. (The discrepancy catalogue varies ``2 mu_0 / yield_stress``, the inverse
    yield strain of the base shear modulus ``mu_0``, which is 0 when the effect is off.)"""

    yield_stress: float = math.inf
    name: ClassVar[str] = "plasticity"
    parameter: ClassVar[str] = "yield_stress"
    unit: ClassVar[str] = "Pa"
    off: ClassVar[float] = math.inf

    def __post_init__(self):
        if not (self.yield_stress > 0):
            raise InputError("VonMisesPlasticity", "yield_stress", f"must be > 0 (inf = off), got {self.yield_stress!r}")

    def setup(self, model):
        if math.isinf(self.yield_stress):
            return None
        return PlasticStrain(wp.zeros(model.particle_count, dtype=float, device=model.device))

    def apply_particles(self, model, state, scratch, t):
        if math.isinf(self.yield_stress):
            return
        _launch(model, von_mises_return, model.particle_count, [model.particle_mu, float(self.yield_stress)],
                [state.particle_F, scratch.plastic_strain])


@dataclass(frozen=True)
class PoissonShift(Effect):
    """A shifted Poisson ratio: ``nu <- nu + delta_nu`` on every particle [-] (changes the
    bulk-to-shear stiffness ratio, hence lateral bulging and the mode shapes). 0 is off;
    the result must stay in (-1, 0.5)."""

    delta_nu: float = 0.0
    name: ClassVar[str] = "poisson"
    parameter: ClassVar[str] = "delta_nu"
    unit: ClassVar[str] = ""

    def __post_init__(self):
        _finite("PoissonShift", "delta_nu", self.delta_nu)

    def materials(self, positions, E, nu, rho):
        nu = np.asarray(nu, dtype=np.float64) + self.delta_nu
        if np.any(nu <= -1.0) or np.any(nu >= 0.5):
            raise InputError("PoissonShift", "delta_nu",
                             f"nu + {self.delta_nu:g} leaves (-1, 0.5): range {nu.min():.4g}..{nu.max():.4g}")
        return E, nu, rho


@dataclass(frozen=True)
class StiffnessGradient(Effect):
    """Young's modulus varying along an axis: ``E <- E * exp(slope * s)`` with
    ``s = (x_axis - mid) / extent`` in [-1/2, 1/2] over the particles' extent along
    ``axis`` (0, 1, 2 = x, y, z), so the modulus ratio top/bottom is ``exp(slope)`` and
    the mid-plane keeps its modulus. ``slope`` [-], 0 is off; positive = stiffer towards
    larger coordinates."""

    slope: float = 0.0
    axis: int = 2
    name: ClassVar[str] = "stiffness_gradient"
    parameter: ClassVar[str] = "slope"
    unit: ClassVar[str] = ""

    def __post_init__(self):
        _finite("StiffnessGradient", "slope", self.slope)
        if self.axis not in (0, 1, 2):
            raise InputError("StiffnessGradient", "axis", f"must be 0, 1 or 2, got {self.axis!r}")

    def factor(self, c, lo: float, hi: float) -> np.ndarray:
        """The modulus factor ``exp(slope * s)`` at coordinates ``c`` (any shape, m) along
        ``axis``, ``s = (c - mid) / extent`` over the extent ``[lo, hi]`` [m] (the particles')."""
        s = (np.asarray(c, dtype=np.float64) - 0.5 * (lo + hi)) / max(hi - lo, 1e-12)
        return np.exp(self.slope * s)

    def materials(self, positions, E, nu, rho):
        c = np.asarray(positions, dtype=np.float64)[:, self.axis]
        return np.asarray(E, dtype=np.float64) * self.factor(c, c.min(), c.max()), nu, rho


@dataclass(frozen=True)
class MaterialViscosity(Effect):
    """Material (Kelvin-Voigt) viscosity proportional to the stiffness: the stress gains
    ``beta`` times the elastic tangent applied to the rate of deformation D (the symmetric
    part of the velocity gradient the transfer carries), ``tau_v = J beta (2 mu D + lam tr(D) I)``
    [Pa]. This is the stiffness-proportional half of Rayleigh damping: a vibration mode of
    angular frequency omega decays with damping ratio ``beta omega / 2``, so higher modes
    decay faster (unlike :class:`VelocityDamping`, which damps every mode at one rate).

    ``retardation_time`` beta [s] >= 0; 0 is off. The viscous stress is explicit: beta must
    stay below ``dx^2 / (6 c_p^2 dt)`` of the model (c_p its fastest p-wave speed), checked
    when a solver is made."""

    retardation_time: float = 0.0
    name: ClassVar[str] = "viscosity"
    parameter: ClassVar[str] = "retardation_time"
    unit: ClassVar[str] = "s"

    def __post_init__(self):
        if _finite("MaterialViscosity", "retardation_time", self.retardation_time) < 0:
            raise InputError("MaterialViscosity", "retardation_time", f"must be >= 0, got {self.retardation_time!r}")

    def viscous_retardation(self, model):
        beta = self.retardation_time
        if beta > 0.0:
            limit = viscous_stability_limit(model.params.dx, model.max_wave_speed, model.params.dt)
            if beta > limit:
                raise InputError("MaterialViscosity", "retardation_time",
                                 f"{beta:.4g} s exceeds the explicit stability limit dx^2 / (6 c_p^2 dt) = {limit:.4g} s "
                                 "of this model (refine dt or lower it)")
        return beta


def viscous_stability_limit(dx: float, wave_speed: float, dt: float) -> float:
    """The largest stable Kelvin-Voigt retardation time [s] of an explicit step ``dt`` [s] on
    cells ``dx`` [m] with p-wave speed ``wave_speed`` [m/s]: ``dx^2 / (6 c^2 dt)`` (the
    forward-Euler diffusion bound of a 3-D grid for the viscosity ``beta c^2``)."""
    return float(dx * dx / (6.0 * max(wave_speed, 1e-30) ** 2 * dt))


@dataclass(frozen=True)
class SupportFriction(Effect):
    """The contract's sticky supports become Coulomb contacts with friction coefficient
    ``mu`` [-] (the object can slide on its support; see :class:`FixedCuboid`). ``inf`` is
    off (sticky). Static configuration: switch it on with :func:`with_effects`, which sets
    ``friction = mu`` on every :class:`FixedCuboid` that is sticky in the contract."""

    mu: float = math.inf
    name: ClassVar[str] = "support_friction"
    parameter: ClassVar[str] = "mu"
    unit: ClassVar[str] = ""
    off: ClassVar[float] = math.inf

    def __post_init__(self):
        if not (self.mu >= 0):
            raise InputError("SupportFriction", "mu", f"must be >= 0 (inf = sticky), got {self.mu!r}")

    def configure(self, params: SimParams) -> SimParams:
        if math.isinf(self.mu):
            return params
        bcs = []
        found = False  # a sticky support, moving or not
        for bc in params.boundaries:
            if isinstance(bc, FixedCuboid) and bc.friction is None:
                bc = dataclasses.replace(bc, friction=float(self.mu))
                found = True
            bcs.append(bc)
        if not found:
            raise InputError("SupportFriction", "mu", "the simulation has no sticky FixedCuboid support to make frictional")
        return dataclasses.replace(params, boundaries=tuple(bcs), effects=tuple(params.effects) + (self,))


@dataclass(frozen=True)
class SupportSlip(Effect):
    """Viscous slip at the support: the contract's still, sticky supports hold the object in
    the normal direction only (no penetration, no separation), and the tangential velocity of
    the nodes they hold relaxes towards zero with time constant ``slip_time`` [s] (each
    substep it is multiplied by ``exp(-dt / slip_time)``; a Navier-type slip law with a drag
    rate ``1 / slip_time``). 0 is off (sticky); large values approach frictionless sliding.
    Unlike Coulomb friction (:class:`SupportFriction`) it needs no normal load, so it also
    applies to contracts without gravity. Static configuration: switch it on with
    :func:`with_effects`, which takes over every still sticky :class:`FixedCuboid`
    (recorded in ``boxes``)."""

    slip_time: float = 0.0
    boxes: tuple[Box, ...] = ()
    name: ClassVar[str] = "support_slip"
    parameter: ClassVar[str] = "slip_time"
    unit: ClassVar[str] = "s"

    def __post_init__(self):
        if _finite("SupportSlip", "slip_time", self.slip_time) < 0:
            raise InputError("SupportSlip", "slip_time", f"must be >= 0, got {self.slip_time!r}")

    def configure(self, params: SimParams) -> SimParams:
        if self.slip_time == 0.0:
            return params
        held = tuple(bc.box for bc in params.boundaries if is_still_sticky(bc))
        if not held:
            raise InputError("SupportSlip", "slip_time", "the simulation has no still sticky FixedCuboid support")
        bcs = tuple(bc for bc in params.boundaries if not is_still_sticky(bc))
        me = dataclasses.replace(self, boxes=held)
        return dataclasses.replace(params, boundaries=bcs, effects=tuple(params.effects) + (me,))

    def apply_grid(self, model, state, scratch, lo, dims, t):
        if self.slip_time == 0.0:
            return
        if not self.boxes:
            raise InputError("SupportSlip", "boxes", "switch the effect on with with_effects(params, effect)")
        p = model.params
        factor = math.exp(-p.dt / self.slip_time)
        for box in self.boxes:
            _launch(model, grid_support_slip, dims,
                    [lo, p.dx, wp.vec3(*box.center), wp.vec3(*box.half_size), factor, state.grid_m], [state.grid_mv])


# --------------------------------------------------------------------------------------
# outside the catalogue (disturbances used to test that they are not mis-attributed)
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BodyForcePulse(Effect):
    """A time-varying external push: particles inside ``box`` at t = 0 (all when ``box`` is
    None) get the acceleration ``accel * sin(pi (t - start) / (end - start)) * direction``
    [m/s^2] while ``start <= t < end`` [s] (a half-sine gust). 0 is off."""

    accel: float = 0.0
    direction: Vec3 = (0.0, 1.0, 0.0)
    box: Box | None = None
    start: float = 0.1
    end: float = 0.3
    name: ClassVar[str] = "force_pulse"
    parameter: ClassVar[str] = "accel"
    unit: ClassVar[str] = "m/s^2"

    def __post_init__(self):
        _finite("BodyForcePulse", "accel", self.accel)
        _unit("BodyForcePulse", self.direction)
        if not (0 <= self.start < self.end):
            raise InputError("BodyForcePulse", "start/end", f"need 0 <= start < end, got {self.start!r}, {self.end!r}")

    def setup(self, model):
        """The particles inside ``box`` at t = 0 (the model's rest positions)."""
        if self.accel == 0.0:
            return None
        if self.box is None:
            return ParticleSelection(wp.ones(model.particle_count, dtype=wp.int32, device=model.device))
        inside = self.box.contains(model.particle_x0_host).astype(np.int32)
        return ParticleSelection(wp.array(inside, dtype=wp.int32, device=model.device))

    def apply_particles(self, model, state, scratch, t):
        if self.accel == 0.0 or not (self.start <= t < self.end):
            return
        a = self.accel * math.sin(math.pi * (t - self.start) / (self.end - self.start))
        _add_velocity(model, state, scratch.mask, _unit("BodyForcePulse", self.direction) * (a * model.params.dt))


@dataclass(frozen=True)
class HiddenMass(Effect):
    """Extra mass in a region: density inside ``box`` multiplied by ``1 + fraction`` [-]
    (a hidden insert). 0 is off."""

    fraction: float = 0.0
    box: Box = Box((1.0, 1.0, 1.0), (0.1, 0.1, 0.1))
    name: ClassVar[str] = "hidden_mass"
    parameter: ClassVar[str] = "fraction"
    unit: ClassVar[str] = ""

    def __post_init__(self):
        if not (_finite("HiddenMass", "fraction", self.fraction) > -1.0):
            raise InputError("HiddenMass", "fraction", f"must be > -1, got {self.fraction!r}")

    def materials(self, positions, E, nu, rho):
        inside = self.box.contains(positions)
        rho = np.asarray(rho, dtype=np.float64) * np.where(inside, 1.0 + self.fraction, 1.0)
        return E, nu, rho


def with_effects(params: SimParams, *effects: Effect) -> SimParams:
    """``params`` with ``effects`` switched on, in order, each by its
    :meth:`~knockgs_core.sim.Effect.configure` (by default: appended to ``params.effects``;
    an effect that rewrites static configuration also records itself there)."""
    for effect in effects:
        if not isinstance(effect, Effect):
            raise InputError("SimParams", "effects", f"expected an Effect, got {type(effect).__name__}")
        params = effect.configure(params)
    return params


def effect_examples(*, centre: Vec3 = (1.0, 1.0, 1.0)) -> list[Effect]:
    """One instance of every effect of this module, for checks that each effect passes through
    a solver path (the tests; ``benchmarks/gpu_parity.py --effects``), so that they share one
    list and a new effect joins both. The strengths move the response of an object some 0.4 m
    across, knocked on a support for 30 substeps of 5e-4 s, by 2e-3 to 0.2 of its RMS
    displacement. ``BodyForcePulse`` acts within 1 m of ``centre`` [m] (half sizes),
    ``HiddenMass`` within 0.05 m."""
    return [VelocityDamping(rate=2.0), Gravity(g=9.8), VonMisesPlasticity(yield_stress=30.0),
            MaterialViscosity(retardation_time=1e-3), SupportFriction(mu=0.3), SupportSlip(slip_time=0.01),
            StiffnessGradient(slope=0.5), PoissonShift(delta_nu=0.05),
            BodyForcePulse(accel=0.6, direction=(0.0, 0.0, -1.0), box=Box(centre, (1.0, 1.0, 1.0)), start=0.0, end=0.01),
            HiddenMass(fraction=1.0, box=Box(centre, (0.05, 0.05, 0.05)))]
