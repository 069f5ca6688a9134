"""Effects (extra physics terms) and the Coulomb support, checked against analytic answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import warp as wp

from knockgs_core.errors import InputError
from knockgs_core.sim import (
    BodyForcePulse,
    Box,
    DomainWalls,
    Effect,
    FixedCuboid,
    Gravity,
    HiddenMass,
    MaterialViscosity,
    MPMSolver,
    ParticleTranslation,
    PoissonShift,
    Probe,
    SimParams,
    StiffnessGradient,
    SupportFriction,
    SupportSlip,
    VelocityDamping,
    VonMisesPlasticity,
    build_model,
    is_still_sticky,
    make_state,
    simulate,
    viscous_stability_limit,
    with_effects,
)
from knockgs_core.sim._effects import PlasticStrain, von_mises_return

N_GRID = 32
DX = 2.0 / N_GRID


def block(lo, hi, spacing=DX / 2):
    axes = [np.arange(a + spacing / 2, b, spacing) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)


def run(X, params, *, E=2e5, nu=0.3, rho=1000.0, v0=None, frame_dt=0.01, n_frames=31, probe=None):
    model = build_model(X, E=E, nu=nu, rho=rho, params=params, probe=probe)
    V = None if v0 is None else np.tile(np.asarray(v0, dtype=np.float32), (len(X), 1))
    return simulate(model, make_state(model, X, V), frame_dt=frame_dt, n_frames=n_frames)


# -------------------------------------------------------------------------------------
# Coulomb friction on a FixedCuboid support
# -------------------------------------------------------------------------------------
SLAB = Box((1.0, 1.0, 0.5), (0.9, 0.9, 0.25))  # top face at z = 0.75
SLIDER = ((0.6, 0.875, 0.75), (0.85, 1.125, 0.875))  # resting on the top face


def slide(mu, v0=0.5):
    params = SimParams(n_grid=N_GRID, dt=5e-4, gravity=(0.0, 0.0, -9.8),
                       boundaries=(DomainWalls(), FixedCuboid(SLAB, friction=mu)))
    r = run(block(*SLIDER), params, v0=(v0, 0.0, 0.0))
    c = r.positions.astype(np.float64).mean(axis=1)
    return r.times, c


def test_block_sliding_on_a_frictional_support_decelerates_at_mu_g():
    """A block launched at 0.5 m/s along a level support with friction mu decelerates at
    mu g (Coulomb): the centroid velocity falls linearly until it stops."""
    g = 9.8
    for mu in (0.2, 0.4):
        t, c = slide(mu)
        v = np.gradient(c[:, 0], t)
        t_stop = 0.5 / (mu * g)
        window = (t > 0.03) & (t < 0.8 * t_stop)
        decel = -np.polyfit(t[window], v[window], 1)[0]
        assert decel == pytest.approx(mu * g, rel=0.04), (mu, decel)
        # it stops where Coulomb says (v0^2 / (2 mu g)) and stays
        assert c[-1, 0] - c[0, 0] == pytest.approx(0.25 / (2 * mu * g), rel=0.08)
        assert abs(v[-1]) < 0.01


def test_frictionless_support_slides_freely_and_large_friction_sticks():
    t, c = slide(0.0)
    np.testing.assert_allclose(c[:, 0] - c[0, 0], 0.5 * t, atol=1e-4)
    assert np.abs(c[:, 2] - c[0, 2]).max() < 2e-3  # rests on the support, does not sink
    t, c = slide(50.0)
    # the base stops within a step; the body only rocks over its base
    assert abs(c[-1, 0] - c[0, 0]) < 0.01


def test_friction_none_is_the_sticky_support():
    X = block(*SLIDER)
    params = SimParams(n_grid=N_GRID, dt=5e-4, boundaries=(DomainWalls(), FixedCuboid(SLAB)))
    a = run(X, params, v0=(0.3, 0, 0), n_frames=6).positions
    params2 = SimParams(n_grid=N_GRID, dt=5e-4, boundaries=(DomainWalls(), FixedCuboid(SLAB, friction=None)))
    b = run(X, params2, v0=(0.3, 0, 0), n_frames=6).positions
    assert np.array_equal(a, b)
    with pytest.raises(ValueError):
        FixedCuboid(SLAB, friction=-0.1)


# -------------------------------------------------------------------------------------
# the catalogue effects
# -------------------------------------------------------------------------------------
FREE = ((0.85, 0.85, 0.85), (1.15, 1.1, 1.05))


def test_velocity_damping_decays_free_motion_exponentially():
    """A free body in uniform motion slows as exp(-rate t) (grid velocities scaled each step)."""
    rate = 3.0
    params = with_effects(SimParams(n_grid=N_GRID, dt=1e-3, boundaries=()), VelocityDamping(rate=rate))
    r = run(block(*FREE), params, v0=(0.2, 0.0, 0.0), frame_dt=0.05, n_frames=9)
    x = r.positions.astype(np.float64).mean(axis=1)[:, 0]
    expected = x[0] + 0.2 * (1 - np.exp(-rate * r.times)) / rate
    np.testing.assert_allclose(x, expected, atol=2e-4)


BAR = ((0.75, 0.875, 0.875), (1.25, 1.125, 1.125))  # a free 0.5 m bar along x


def _bar_elongation(beta, *, E=2e5, rho=1000.0):
    """The free bar's first axial mode (initial velocity 0.3 sin(pi (x - xc) / L) m/s):
    times [s] and elongation (right half's mean x minus the left's) [m] over 0.4 s."""
    X = block(*BAR)
    xc = X[:, 0].mean()
    v0 = np.zeros_like(X)
    v0[:, 0] = 0.3 * np.sin(np.pi * (X[:, 0] - xc) / 0.5)
    params = SimParams(n_grid=N_GRID, dt=5e-4)
    if beta:
        params = with_effects(params, MaterialViscosity(retardation_time=beta))
    model = build_model(X, E=E, nu=0.3, rho=rho, params=params)
    r = simulate(model, make_state(model, X, v0), frame_dt=0.0025, n_frames=161)
    P = r.positions.astype(np.float64)
    right = X[:, 0] > xc
    e = P[:, right, 0].mean(axis=1) - P[:, ~right, 0].mean(axis=1)
    return r.times, e - e[0]


def test_material_viscosity_damps_a_mode_at_beta_omega_squared_over_two():
    """Kelvin-Voigt (stiffness-proportional) viscosity: a vibration mode of angular frequency
    omega decays at the rate beta omega^2 / 2 (damping ratio beta omega / 2), on top of the
    transfer's own (small) dissipation; the frequency stays (the ratio is small)."""
    from scipy.optimize import curve_fit

    def fit(t, e):
        f = lambda t, A, lam, w, ph, c: A * np.exp(-lam * t) * np.sin(w * t + ph) + c  # noqa: E731
        return curve_fit(f, t, e, p0=(np.abs(e).max(), 1.0, 80.0, 0.0, 0.0))[0]

    _, lam0, w0, _, _ = fit(*_bar_elongation(0.0))
    assert lam0 < 0.1  # the transfer alone barely damps the mode (1/s)
    for beta in (0.001, 0.002):
        _, lam, w, _, _ = fit(*_bar_elongation(beta))
        assert w == pytest.approx(w0, rel=0.01)
        assert lam - lam0 == pytest.approx(beta * w0**2 / 2.0, rel=0.06), (beta, lam, lam0, w0)


def test_material_viscosity_leaves_rigid_rotation_undamped_and_is_off_at_zero():
    """The viscous stress acts on the rate of deformation only: a spinning free block keeps its
    angular momentum (velocity damping would slow it). Retardation time 0 is bit for bit no
    effect; one above the explicit stability limit is refused with the limit named."""
    X = block(*FREE)
    c = X.astype(np.float64).mean(axis=0)
    omega = np.array([0.0, 0.0, 2.0])
    V = np.cross(omega, X - c).astype(np.float32)

    def spin(*effects):
        params = with_effects(SimParams(n_grid=N_GRID, dt=1e-3, boundaries=()), *effects)
        model = build_model(X, E=2e5, nu=0.3, rho=1000.0, params=params)
        r = simulate(model, make_state(model, X, V), frame_dt=0.05, n_frames=9)
        P = r.positions.astype(np.float64)
        dP = (P[-1] - P[-2]) / 0.05
        return P, float(np.sum(np.cross(P[-1] - P[-1].mean(axis=0), dP)[:, 2]))

    P0, L0 = spin()
    _, L1 = spin(MaterialViscosity(retardation_time=0.002))
    _, L2 = spin(VelocityDamping(rate=3.0))
    assert L1 == pytest.approx(L0, rel=2e-3)
    assert L2 < 0.5 * L0
    np.testing.assert_array_equal(spin(MaterialViscosity(retardation_time=0.0))[0], P0)
    params = SimParams(n_grid=N_GRID, dt=1e-3, boundaries=())
    model = build_model(X, E=2e5, nu=0.3, rho=1000.0, params=params)
    limit = viscous_stability_limit(params.dx, model.max_wave_speed, params.dt)
    too_much = with_effects(params, MaterialViscosity(retardation_time=2.0 * limit))
    with pytest.raises(InputError, match="retardation_time.*stability limit"):
        MPMSolver(build_model(X, E=2e5, nu=0.3, rho=1000.0, params=too_much))


def test_gravity_effect_matches_contract_gravity_and_free_fall():
    X = block(*FREE)
    base = SimParams(n_grid=N_GRID, dt=1e-3, boundaries=())
    a = run(X, with_effects(base, Gravity(g=2.0)), frame_dt=0.05, n_frames=5)
    b = run(X, SimParams(n_grid=N_GRID, dt=1e-3, boundaries=(), gravity=(0.0, 0.0, -2.0)), frame_dt=0.05, n_frames=5)
    za = a.positions.astype(np.float64).mean(axis=1)[:, 2] - X[:, 2].mean()
    zb = b.positions.astype(np.float64).mean(axis=1)[:, 2] - X[:, 2].mean()
    # free fall -g t^2 / 2; the effect acts one substep later than contract gravity
    np.testing.assert_allclose(zb, -1.0 * a.times**2, atol=3e-4)
    np.testing.assert_allclose(za, -1.0 * a.times**2, atol=3e-4)
    assert np.all(np.abs(za - zb) <= 2.0 * 1e-3 * a.times + 1e-7)
    # a negative strength pulls the other way
    c = run(X, with_effects(base, Gravity(g=-2.0)), frame_dt=0.05, n_frames=3)
    assert c.positions[:, :, 2].mean(axis=1)[-1] > X[:, 2].mean()


def test_gravity_effect_is_held_by_a_sticky_support():
    X = block((0.8, 0.8, 0.75), (1.2, 1.2, 1.0))
    params = with_effects(SimParams(n_grid=N_GRID, dt=5e-4, boundaries=(DomainWalls(), FixedCuboid(SLAB))), Gravity(g=9.8))
    r = run(X, params, E=1e5, frame_dt=0.05, n_frames=11)
    bottom = X[:, 2] < 0.75 + DX / 2
    # the bottom layer stays put, the body sags by a bounded amount and does not creep
    assert np.abs(r.positions[-1, bottom] - X[bottom]).max() < 2e-3
    sag = X[:, 2].mean() - r.positions[:, :, 2].mean(axis=1)
    assert 0 < sag[-1] < 0.02 and abs(sag[-1] - sag[-3]) < 0.01


@pytest.mark.parametrize("layout", ["records", "components"])
def test_von_mises_return_mapping_matches_numpy(rng, layout):
    """The kernel caps the deviatoric Hencky strain at yield / (2 mu) and keeps the volume, in
    either layout of the solver's matrices (the CPU's records, the GPU's components)."""
    n = 200
    F = np.eye(3) + 0.15 * rng.standard_normal((n, 3, 3))
    F[np.linalg.det(F) < 0.2] = np.eye(3)
    mu = rng.uniform(50.0, 150.0, n)
    yield_stress = 8.0
    wp.init()
    from knockgs_core.sim._model import matrices, matrix_array

    # F is float64 in the solver
    Fw = matrix_array(n, wp.float64, "cpu", layout=layout)
    F32 = F.astype(np.float32).astype(np.float64)
    if layout == "records":
        Fw.assign(F32)
    else:
        rows = np.zeros(Fw.shape)
        rows[:, :n] = F32.reshape(n, 9).T
        Fw.assign(rows)
    plastic = wp.zeros(n, dtype=float, device="cpu")
    mu_w = wp.array(mu.astype(np.float32), dtype=float, device="cpu")
    wp.launch(von_mises_return, dim=n, inputs=[mu_w, yield_stress], outputs=[Fw, plastic], device="cpu")
    out = matrices(Fw, n)
    U, s, Vt = np.linalg.svd(F)
    e = np.log(s)
    dev = e - e.mean(1, keepdims=True)
    norm = np.linalg.norm(dev, axis=1)
    limit = yield_stress / (2 * mu)
    scale = np.where(norm > limit, limit / norm, 1.0)
    e_new = e.mean(1, keepdims=True) + dev * scale[:, None]
    ref = U @ (np.exp(e_new)[:, :, None] * Vt)
    np.testing.assert_allclose(out, ref, atol=2e-5)
    np.testing.assert_allclose(np.linalg.det(out), np.linalg.det(F), rtol=1e-4)
    np.testing.assert_allclose(plastic.numpy(), np.maximum(norm - limit, 0.0), atol=1e-5)


def test_plasticity_leaves_a_permanent_set():
    """A pushed block on a sticky support springs back when elastic; above yield it keeps a
    permanent offset (motion settled by damping)."""
    X = block((0.8, 0.9, 0.75), (1.2, 1.1, 1.05))
    base = SimParams(n_grid=N_GRID, dt=1e-3, boundaries=(DomainWalls(), FixedCuboid(SLAB)))
    m = 1000.0 * (DX / 2) ** 3
    probe = Probe("push", (-0.3 * m / 1e-3, 0.0, 0.0), dt_ref=1e-3)  # a 0.3 m/s kick
    kw = dict(E=2e4, frame_dt=0.1, n_frames=16, probe=probe)
    elastic = run(X, with_effects(base, VelocityDamping(rate=8.0)), **kw).positions.astype(np.float64)
    plastic_params = with_effects(base, VelocityDamping(rate=8.0), VonMisesPlasticity(yield_stress=300.0))
    plastic = run(X, plastic_params, **kw).positions.astype(np.float64)
    off_el = elastic[-1, :, 0].mean() - X[:, 0].mean()
    off_pl = plastic[-1, :, 0].mean() - X[:, 0].mean()
    peak = np.abs(elastic[:, :, 0].mean(axis=1) - X[:, 0].mean()).max()
    assert abs(off_el) < 0.05 * peak
    assert off_pl < -0.2 * peak


def test_poisson_shift_and_stiffness_gradient_change_materials():
    X = block(*FREE)
    E = np.full(len(X), 1e4)
    nu = np.full(len(X), 0.3)
    rho = np.full(len(X), 1000.0)
    _, nu2, _ = PoissonShift(delta_nu=0.1).materials(X, E, nu, rho)
    np.testing.assert_allclose(nu2, 0.4)
    with pytest.raises(InputError):
        PoissonShift(delta_nu=0.25).materials(X, E, nu, rho)
    E2, _, _ = StiffnessGradient(slope=math.log(4.0), axis=2).materials(X, E, nu, rho)
    z = X[:, 2]
    assert E2[z == z.max()].mean() / E2[z == z.min()].mean() == pytest.approx(4.0, rel=1e-9)
    assert np.median(E2) == pytest.approx(1e4, rel=0.05)
    _, _, rho2 = HiddenMass(fraction=1.0, box=Box((1.0, 1.0, 1.0), (0.05, 0.05, 0.05))).materials(X, E, nu, rho)
    inside = np.all(np.abs(X - 1.0) <= 0.05, axis=1)
    np.testing.assert_allclose(rho2[inside], 2000.0)
    np.testing.assert_allclose(rho2[~inside], 1000.0)
    # built into a model: the Lame parameters follow
    params = with_effects(SimParams(n_grid=N_GRID, boundaries=()), PoissonShift(delta_nu=0.1))
    model = build_model(X, E=1e4, nu=0.3, rho=1000.0, params=params)
    assert model.particle_lam.numpy()[0] == pytest.approx(1e4 * 0.4 / (1.4 * 0.2), rel=1e-5)


def test_support_slip_spans_sticky_to_free_sliding():
    """Slip time 0 is the sticky support; a short one nearly sticky; a long one approaches
    frictionless sliding; with_effects takes the sticky support over."""
    X = block(*SLIDER)
    sticky = SimParams(n_grid=N_GRID, dt=5e-4, boundaries=(DomainWalls(), FixedCuboid(SLAB)))
    p = with_effects(sticky, SupportSlip(slip_time=0.01))
    assert not any(isinstance(b, FixedCuboid) for b in p.boundaries)
    assert p.effects[0].boxes == (SLAB,)

    def shift(params):
        r = run(X, params, v0=(0.2, 0, 0), n_frames=11)
        return r.positions[-1, :, 0].mean() - X[:, 0].mean()

    s0 = shift(sticky)
    s_short = shift(with_effects(sticky, SupportSlip(slip_time=1e-4)))
    s_mid = shift(with_effects(sticky, SupportSlip(slip_time=0.02)))
    s_long = shift(with_effects(sticky, SupportSlip(slip_time=100.0)))
    free = shift(SimParams(n_grid=N_GRID, dt=5e-4, boundaries=(DomainWalls(), FixedCuboid(SLAB, friction=0.0))))
    assert abs(s_short - s0) < 0.1 * abs(s_mid - s0)
    assert s0 < s_mid < s_long
    assert s_long == pytest.approx(free, rel=0.01)
    assert free == pytest.approx(0.2 * 0.1, rel=0.01)
    with pytest.raises(InputError):
        with_effects(SimParams(boundaries=()), SupportSlip(slip_time=0.1))


def test_support_friction_effect_configures_the_support():
    sticky = SimParams(boundaries=(DomainWalls(), FixedCuboid(SLAB)))
    p = with_effects(sticky, SupportFriction(mu=0.3))
    assert p.boundaries[1].friction == 0.3 and isinstance(p.effects[0], SupportFriction)
    assert with_effects(sticky, SupportFriction()) == sticky  # off


def test_force_pulse_delivers_its_impulse():
    """A half-sine acceleration a sin(pi (t - t0) / T) on a free body adds 2 a T / pi of velocity."""
    X = block(*FREE)
    a, t0, t1 = 0.5, 0.02, 0.1
    pulse = BodyForcePulse(accel=a, direction=(0, 1, 0), start=t0, end=t1)
    params = with_effects(SimParams(n_grid=N_GRID, dt=1e-3, boundaries=()), pulse)
    model = build_model(X, E=1e4, nu=0.3, rho=1000.0, params=params)
    state = make_state(model, X)
    solver = MPMSolver(model)
    solver.check(state)
    for _ in range(150):
        solver.step(state)
    v = solver.momentum(state) / model.mass_host.astype(np.float64).sum()
    assert v[1] == pytest.approx(2 * a * (t1 - t0) / math.pi, rel=0.02)
    assert abs(v[0]) < 1e-6 and abs(v[2]) < 1e-6


def test_effect_values_and_validation():
    assert VelocityDamping().is_off and Gravity().is_off and VonMisesPlasticity().is_off and SupportSlip().is_off
    e = VelocityDamping().with_value(2.0)
    assert e.rate == 2.0 and e.value == 2.0 and "1/s" in e.describe()
    assert StiffnessGradient(axis=0).with_value(1.5).axis == 0
    for bad in (lambda: VelocityDamping(rate=-1.0), lambda: VonMisesPlasticity(yield_stress=0.0),
                lambda: StiffnessGradient(axis=3), lambda: Gravity(direction=(0, 0, 0)),
                lambda: SupportSlip(slip_time=-1.0), lambda: SupportFriction(mu=-1.0)):
        with pytest.raises(InputError):
            bad()


# -------------------------------------------------------------------------------------
# the effect protocol
# -------------------------------------------------------------------------------------
def test_effect_protocol_no_op_hooks_and_explicit_scratch():
    """An effect overrides only the hooks it needs; its scratch comes from setup(model) and
    is held by the solver, one per effect, in order."""
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class CountSteps(Effect):
        def setup(self, model):
            return {"grid": 0, "particles": 0, "n": model.particle_count}

        def apply_grid(self, model, state, scratch, lo, dims, t):
            scratch["grid"] += 1

    X = block(*FREE)
    params = with_effects(SimParams(n_grid=N_GRID, dt=1e-3, boundaries=()), CountSteps(), VonMisesPlasticity(yield_stress=50.0))
    model = build_model(X, E=1e4, nu=0.3, rho=1000.0, params=params)
    solver = MPMSolver(model)
    state = make_state(model, X, np.tile(np.float32([0.1, 0.0, 0.0]), (len(X), 1)))
    solver.check(state)
    for _ in range(3):
        solver.step(state)
    counts, plastic = solver.effect_scratch
    assert counts == {"grid": 3, "particles": 0, "n": len(X)}
    assert isinstance(plastic, PlasticStrain) and plastic.plastic_strain.shape == (len(X),)
    # a plain effect leaves the materials as they are; an effect off needs no scratch
    assert Effect().materials(X, 1.0, 2.0, 3.0) == (1.0, 2.0, 3.0)
    assert Gravity().setup(model) is None and VonMisesPlasticity().setup(model) is None


def test_effects_must_follow_the_protocol():
    with pytest.raises(InputError, match="effects"):
        with_effects(SimParams(), object())
    with pytest.raises(InputError, match=r"effects\[0\]"):
        build_model(block(*FREE), E=1e4, nu=0.3, rho=1000.0, params=SimParams(n_grid=N_GRID, effects=("damping",)))


def test_overlapping_particle_translations_are_refused():
    box = Box((1.0, 1.0, 0.9), (0.1, 0.1, 0.1))
    a = ParticleTranslation(box, (0.1, 0.0, 0.0), start_time=0.0, end_time=0.1)
    later = ParticleTranslation(box, (0.0, 0.1, 0.0), start_time=0.1, end_time=0.2)
    overlapping = ParticleTranslation(box, (0.0, 0.1, 0.0), start_time=0.05, end_time=0.2)
    X = block(*FREE)
    model = build_model(X, E=1e4, nu=0.3, rho=1000.0, params=SimParams(n_grid=N_GRID, boundaries=(DomainWalls(), a, later)))
    assert len(model.translations) == 2
    with pytest.raises(InputError, match=r"boundaries\[2\].*at most one particle translation"):
        build_model(X, E=1e4, nu=0.3, rho=1000.0, params=SimParams(n_grid=N_GRID, boundaries=(DomainWalls(), a, overlapping)))


def test_still_sticky_support_predicate():
    assert is_still_sticky(FixedCuboid(SLAB))
    assert not is_still_sticky(FixedCuboid(SLAB, friction=0.2))
    assert not is_still_sticky(FixedCuboid(SLAB, velocity=(0.0, 0.0, 0.1)))
    assert not is_still_sticky(FixedCuboid(SLAB, start_time=0.1))
    assert not is_still_sticky(FixedCuboid(SLAB, end_time=0.5))
    assert not is_still_sticky(DomainWalls())
