"""The discrepancy loop's model-error floor and time signature (docs/discrepancy.md, section 3)."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest
from _linear import LinearForward

from knockgs_core.discrepancy import LoopSettings, Measurement, run_discrepancy
from knockgs_core.discrepancy._fitting import Problem
from knockgs_core.discrepancy._forward import ModelSpec
from knockgs_core.discrepancy._model_error import FLOOR_SHIFTS, displacement_at, refined_contract, translated
from knockgs_core.errors import InputError


# -------------------------------------------------------------------------------------
# the refined model and the displacement kernel
# -------------------------------------------------------------------------------------
def test_refined_contract_refines_grid_fill_and_the_time_step():
    from knockgs_core.contract import cfl_dt, load_contract

    c = load_contract("pillow", "ci")
    r = refined_contract(c, 1.5)
    assert (r.sim.n_grid, r.fill.resolution) == (48, 48)
    assert r.asset == c.asset and r.probes == c.probes and r.materials == c.materials
    # the contracts' rule: frame-commensurate, at most 0.3 dx / c_p at the stiffest candidate
    limit = cfl_dt(c.materials, n_grid=48, grid_lim=c.sim.grid_lim)
    assert r.sim.dt <= limit * (1 + 1e-12) and r.sim.dt < c.sim.dt
    for p in c.probes.values():
        n = p.export.frame_dt / r.sim.dt
        assert abs(n - round(n)) < 1e-9
    with pytest.raises(InputError, match="model_error_refine"):
        refined_contract(c, 1.0)


def test_displacement_kernel_reproduces_constant_and_smooth_fields(rng):
    rest = rng.uniform(0, 1, size=(4000, 3))
    pts = rng.uniform(0.2, 0.8, size=(50, 3))
    const = np.broadcast_to(np.array([1e-3, -2e-3, 5e-4]), (2, 4000, 3))
    np.testing.assert_allclose(displacement_at(rest, const, pts, length=0.05), np.broadcast_to(const[:, :50], (2, 50, 3)),
                               rtol=1e-12)
    # a smooth (linear) field: the kernel's error is of the order of gradient x spacing
    U = (rest @ np.diag([1e-3, 2e-3, -1e-3]))[None]
    got = displacement_at(rest, U, pts, length=0.05)[0]
    want = pts @ np.diag([1e-3, 2e-3, -1e-3])
    spacing = 4000 ** (-1 / 3)
    assert np.abs(got - want).max() < 2e-3 * spacing


# -------------------------------------------------------------------------------------
# the term's coefficient, profiled on the fit window
# -------------------------------------------------------------------------------------
def test_coefficient_is_profiled_on_the_fit_window_and_bounded(rng):
    T, M = 12, 30
    X0 = rng.uniform(0, 1, size=(M, 3))
    t = np.arange(T)[:, None, None] * 0.02
    A = np.sin(9 * t) * rng.normal(size=(1, M, 3)) * 1e-3
    term = np.cos(5 * t) * rng.normal(size=(1, M, 3)) * 1e-3
    term[0] = 0
    fw = LinearForward(X0, A)
    spec = ModelSpec((1.0, 1.0))
    for c_true, c_max, expected in [(0.7, 6.0, 0.7), (-0.5, 6.0, 0.0), (9.0, 6.0, 6.0)]:
        Y = fw.rollout(spec, "p") + c_true * term
        m = Measurement(points=Y, frames=np.arange(T), times=None, particle=np.arange(M), track=np.arange(M))
        pb = Problem(m, fw, "p", LoopSettings()).with_term(term, c_max)
        raw = pb.raw_residual(spec)
        assert pb.coefficient(raw) == pytest.approx(expected, abs=1e-9)
        if c_true == expected:
            assert np.abs(pb.residual(spec)).max() < 1e-12
        assert pb.model_floor(pb.val_rows) == pytest.approx(float(np.sum(term[1:].reshape(-1)[pb.val_rows] ** 2)))
        # a measured floor shape replaces the term's energy as the floor
        shape = 0.5 * np.roll(term[1:], 1, axis=1).reshape(-1)
        pf = Problem(m, fw, "p", LoopSettings()).with_term(term, c_max, floor_shape=shape)
        assert pf.model_floor(pf.val_rows, 2.0) == pytest.approx(2.0 * float(np.sum(shape[pf.val_rows] ** 2)))
        assert pf.coefficient(pf.raw_residual(spec)) == pb.coefficient(raw)
        # several shapes (the grid placements'): the floor is their mean energy
        shapes = np.stack([shape, 3.0 * shape, np.zeros_like(shape)])
        pk = Problem(m, fw, "p", LoopSettings()).with_term(term, c_max, floor_shape=shapes)
        assert pk.model_floor(pk.val_rows) == pytest.approx(float(np.sum(shape[pk.val_rows] ** 2)) * (1 + 9 + 0) / 3)
    # only the fit window sets it: a validation-window-only disturbance leaves c unchanged
    Y = fw.rollout(spec, "p") + 0.7 * term
    Y2 = Y.copy()
    Y2[pb.fit_frames + 1:] += 5e-3
    m2 = Measurement(points=Y2, frames=np.arange(T), times=None, particle=np.arange(M), track=np.arange(M))
    pb2 = Problem(m2, fw, "p", LoopSettings()).with_term(term, 6.0)
    assert pb2.coefficient(pb2.raw_residual(spec)) == pytest.approx(0.7, abs=1e-9)
    # without a term nothing changes
    plain = Problem(m2, fw, "p", LoopSettings())
    np.testing.assert_array_equal(plain.residual(spec), plain.raw_residual(spec))
    assert plain.model_floor(plain.val_rows) == 0.0 and plain.coefficient(plain.raw_residual(spec)) == 0.0


class _ForwardWithEffect(LinearForward):
    """positions = rest + s_E * A(t) + u * B(t), u the strength of effect ``"set"`` (s_rho unused)."""

    def __init__(self, X0, A, B):
        super().__init__(X0, A)
        self.effect = B

    def rollout(self, spec, probe):
        return super().rollout(spec, probe) + dict(spec.effects).get("set", 0.0) * self.effect


def test_time_signature_reads_only_thirds_the_discretization_floor_cannot_move(rng):
    """A contribution that grows in time (a permanent set) held by the data at 0.3 in the
    first third and fully after it: the share 0.3 is read there, unless the floor's shapes
    project on the contribution in that third by as much as the limit (then the third is not
    judged); a floor too small to move the share leaves it read."""
    from knockgs_core.discrepancy._attribution import _window_shares

    T, M = 12, 20
    X0 = rng.uniform(0, 1, size=(M, 3))
    t = np.arange(T)[:, None, None] / (T - 1)
    A = np.sin(7 * t) * rng.normal(size=(1, M, 3)) * 1e-3
    B = t**2 * rng.normal(size=(1, M, 3)) * 1e-3
    fw = _ForwardWithEffect(X0, A, B)
    spec = ModelSpec((1.0, 1.0)).with_effect("set", 1.0)
    held = np.where(np.arange(T) <= 4, 0.3, 1.0)[:, None, None]  # thirds of the 11 frames after t = 0: 1-4, 5-8, 9-11
    Y = X0[None] + A + held * B
    m = Measurement(points=Y, frames=np.arange(T), times=None, particle=np.arange(M), track=np.arange(M))
    term = np.zeros_like(A)
    first = np.zeros_like(B)
    first[1:5] = B[1:5]
    for scale, weight, expected_first in [(3.0, 0.0, 0.3), (3.0, 1.0, None), (0.2, 1.0, 0.3)]:
        pb = Problem(m, fw, "p", LoopSettings()).with_term(term, 6.0, floor_shape=scale * first[1:].reshape(-1))
        shares = _window_shares(pb, spec, "set", 1e-16, floor_weight=weight, limit=0.5)
        assert shares[1:] == pytest.approx([1.0, 1.0], abs=1e-9)
        if expected_first is None:
            assert np.isnan(shares[0])
        else:
            assert shares[0] == pytest.approx(expected_first, abs=1e-9)
    # a contribution lost in the noise is not judged either
    pb = Problem(m, fw, "p", LoopSettings()).with_term(term, 6.0)
    assert all(np.isnan(_window_shares(pb, spec, "set", 1.0)))


def test_settings_refuse_a_refinement_that_refines_nothing():
    with pytest.raises(InputError, match="model_error_refine"):
        LoopSettings(model_error_refine=1.0)
    assert LoopSettings(model_error_refine=None).model_error_refine is None
    with pytest.raises(InputError, match="model_error_floor"):
        LoopSettings(model_error_floor="richardson")


def test_translated_moves_every_box_with_the_particles():
    """A placement on the grid: particles and every box (support, probe and region boxes)
    move together, nothing else changes; a bad shift is refused."""
    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract

    kinds = set()
    for name in ("ficus", "vasedeck"):  # regions and a support (Ficus), a probe box (Vasedeck)
        c = load_contract(name, "ci")
        particles = build_asset(c).particles
        shift = np.array([0.01, -0.02, 0.03])
        c2, p2 = translated(c, particles, shift)
        np.testing.assert_allclose(np.asarray(p2.positions, np.float64) - np.asarray(particles.positions, np.float64),
                                   np.broadcast_to(shift, (len(particles.positions), 3)), atol=1e-6)
        assert p2.n_gs == particles.n_gs and p2.volumes is particles.volumes
        boxes = [("support", b.box, b2.box) for b, b2 in zip(c.sim.boundaries, c2.sim.boundaries)
                 if getattr(b, "box", None) is not None]
        boxes += [("probe", p.box, c2.probes[k].box) for k, p in c.probes.items() if p.box is not None]
        boxes += [("region", b, b2) for k in c.regions for b, b2 in zip(c.regions[k], c2.regions[k])]
        for kind, b, b2 in boxes:
            kinds.add(kind)
            np.testing.assert_allclose(np.subtract(b2.center, b.center), shift, atol=1e-12)
            assert b2.half_size == b.half_size
        assert c2.materials == c.materials and c2.sim.n_grid == c.sim.n_grid and c2.sim.dt == c.sim.dt
    assert kinds == {"support", "probe", "region"}
    with pytest.raises(InputError, match="shift"):
        translated(c, particles, [np.nan, 0.0, 0.0])


def test_placements_on_the_grid_whole_cells_change_nothing_half_cells_do(pillow):
    """The floor's placements: moving the Pillow and its support by one whole cell leaves its
    Probe-A response as it is (to float32 rounding of the positions), moving it by half a cell
    (a placement of the floor, ``FLOOR_SHIFTS``) changes it by percents at ci (the grid does not
    resolve the thin body)."""
    from knockgs_core.rollout import run_rollout

    contract, particles = pillow
    dx = contract.sim.grid_lim / contract.sim.n_grid
    n = particles.n_gs

    def motion(shift):
        c2, p2 = translated(contract, particles, shift)
        X = np.asarray(run_rollout(c2, (0.8, 1.2), "standard_x", particles=p2).positions, np.float64)[:, :n]
        return X - X[0]

    U = motion(np.zeros(3))
    size = np.linalg.norm(U)
    whole = np.linalg.norm(motion(np.array([dx, 0.0, 0.0])) - U) / size
    half = np.linalg.norm(motion(np.asarray(FLOOR_SHIFTS[0]) * dx) - U) / size
    assert whole < 2e-3, whole
    assert half > 10 * whole and half > 0.01, (half, whole)


# -------------------------------------------------------------------------------------
# the loop on data its model cannot match exactly (ci pillow)
# -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def pillow():
    from knockgs_core.assets import build_asset
    from knockgs_core.contract import load_contract

    contract = load_contract("pillow", "ci")
    return contract, build_asset(contract).particles


@pytest.fixture(scope="module")
def loop_model(pillow):
    """The loop's model in the runs below: the ci Pillow (the same particles) with its
    calibration probe alone and 2 substeps per frame (dt = 1e-2 s, not the contract's 5e-3 s).
    The step changes the Probe-A response by 0.5 % at the thetas of these runs (a CFL number of
    at most about 0.4 there), a tenth of the half-cell placements' change that the floor is made
    of, and halves every rollout; the refined models and the finer worlds take their steps by
    the contracts' rule over this probe's frame interval."""
    contract, particles = pillow
    probe = contract.roles["calibration"]
    model = dataclasses.replace(
        contract, probes={probe: contract.probes[probe]}, roles={"calibration": probe, "heldout": [], "diagnostic": []},
        probe_selected_reference={}, probe_force_match={},
        sim=dataclasses.replace(contract.sim, dt=contract.probes[probe].export.frame_dt / 2))
    return model, particles


def _tracks(contract, particles, theta, probe, effects, rng, *, noise=0.02, share=0.6):
    """Noisy tracks without identity of a random share of the Gaussian particles of a world
    (``contract`` on ``particles`` with ``effects``), and the clean displacement field."""
    from knockgs_core.rollout import run_rollout
    from knockgs_core.sim import with_effects

    p = with_effects(contract.sim, *effects)
    X = np.asarray(run_rollout(contract, theta, probe, particles=particles,
                               sim_overrides={"effects": p.effects, "boundaries": p.boundaries}).positions, np.float64)
    idx = rng.permutation(particles.n_gs)[: int(share * particles.n_gs)]
    D = np.sqrt(np.mean(np.sum((X[:, : particles.n_gs] - X[0, : particles.n_gs]) ** 2, -1)))
    P = X[:, idx] + rng.normal(0.0, noise * D, size=(X.shape[0], len(idx), 3))
    m = Measurement(points=P, frames=np.arange(X.shape[0]), times=None, particle=None, track=np.arange(len(idx)) + 1,
                    meta={"object": contract.name, "probe": probe})
    return m, X


@pytest.mark.slow
def test_a_finer_world_without_effect_names_nothing_and_its_floor_is_the_residual_size(loop_model):
    """Data from the same MPM on a grid twice as fine: the term's coefficient is well above
    the standard cases' (<= 0.01), no catalogue effect is named, the floor measured by the
    grid placements is of the size of the residual that theta and the term leave (this world
    leaves a little more than the placements' mean: the verdict may be "unexplained" with both
    sizes reported, or "discretization", which opens with the floor's size), and the theta
    interval holds the truth though the point estimate is off by the discretization bias: the
    refinement moves theta by more than the fit's statistics (a pair not in the asymptotic
    range), so the interval is unbounded on the refinement's side and no continuum is given."""
    # About 30 s: one rollout of the world on a grid of 64^3, then the loop (about 100 rollouts
    # of the model at 2 substeps per frame, 4 of the refined one) over three catalogue terms.
    from knockgs_core.assets import build_asset

    contract, particles = loop_model
    world = refined_contract(contract, 2.0)
    truth = (0.8, 1.2)
    m, _ = _tracks(world, build_asset(world).particles, truth, "standard_x", (), np.random.default_rng(5))
    res = run_discrepancy(m, contract, particles, settings=LoopSettings(catalogue=("damping", "gravity", "stiffness_gradient_z")))
    assert res.identified == [] and res.verdict_kind in ("discretization", "unexplained", "none"), res.verdict
    assert res.model_error["coefficient"] > 0.3 and res.model_error["floor_weight"] == 1.0
    # the floor was measured by the grid placements: the share of their change the term misses
    assert res.model_error["floor"] == "shifts" and len(res.model_error["placement_shifts_cells"]) == len(FLOOR_SHIFTS)
    assert 0.0 < res.model_error["leftover_share"] < 1.0
    assert 0.5 < res.model_error["floor_rms_per_point"] / res.residual["excess_rms_per_point"] < 2.0
    assert res.model_error["significant_without_term"]
    (lo_e, hi_e), (lo_r, hi_r) = res.theta_interval
    assert lo_e <= truth[0] <= hi_e and lo_r <= truth[1] <= hi_r, res.theta_interval
    assert "discretization floor" in res.verdict
    u = res.theta_uncertainty
    assert u["basis"] == "refinement" and u["asymptotic"] == [False, False]
    for k in range(2):
        up = u["theta_at"]["refined"][k] > u["theta_at"]["estimate"][k]
        assert u["unbounded"][k] == [not up, up] and u["continuum"][k] is None and u["continuum_reason"][k]
    within = res.rounds[-1]["visible"] and not res.rounds[-1]["significant"]
    assert (res.floor_statement is not None) == within
    if within:
        assert res.verdict.startswith("the model at this resolution differs from its refined self by")


@pytest.mark.slow
def test_a_push_that_starts_late_is_not_named_gravity(loop_model):
    """A vertical push on the whole body between 20 % and 60 % of the record (outside the
    catalogue) looks like gravity on the validation window; the time signature refuses it
    (nothing acts in the first third) and the verdict names it an approximation. A planted
    gravity passes the same check."""
    from knockgs_core.sim import BodyForcePulse, Box, Gravity

    contract, particles = loop_model
    # the data come from the loop's own model (no discretization term); the candidates' fits run
    # 2 LM iterations in the attribution (the pushed case's gravity row must still explain most
    # of the residual, the planted case's joint fit then finds the value) and 5 in the joint fit
    settings = LoopSettings(catalogue=("damping", "gravity"), model_error_refine=None, refine_iterations=2,
                            joint_iterations=5)
    push = BodyForcePulse(accel=0.6, direction=(0.0, 0.0, -1.0), box=Box((1.0, 1.0, 1.0), (1.0, 1.0, 1.0)), start=0.12, end=0.36)
    m, _ = _tracks(contract, particles, (0.8, 1.2), "standard_x", (push,), np.random.default_rng(6))
    res = run_discrepancy(m, contract, particles, settings=settings)
    assert res.identified == [] and res.unexplained
    assert res.approximation is not None and res.approximation["key"] == "gravity"
    assert res.approximation["signature_share"] < settings.signature_min and "approximation" in res.verdict
    gravity_row = next(r for r in res.rounds[0]["table"] if r["key"] == "gravity")
    assert gravity_row["explained_val"] > 0.5 and gravity_row["signature_ok"] is False
    m, _ = _tracks(contract, particles, (0.8, 1.2), "standard_x", (Gravity(g=0.03),), np.random.default_rng(7))
    res = run_discrepancy(m, contract, particles, settings=settings)
    assert res.identified == ["gravity"] and res.approximation is None
    row = next(r for r in res.rounds[0]["table"] if r["key"] == "gravity")
    assert row["signature_ok"] and row["signature_share"] > 0.8
    assert res.effects[0]["value"] == pytest.approx(0.03, rel=0.1)


YIELD_TRUTH = (0.95, 1.35)
YIELD_CATALOGUE = ("plasticity", "stiffness_gradient_z")
#: the loops on the yield world: two catalogue terms, the candidates' fits in the attribution at
#: 2 LM iterations (both loops alike: what differs between them is only the term they are scored with)
YIELD_SETTINGS = LoopSettings(catalogue=YIELD_CATALOGUE, refine_iterations=2)


class _SharedRollouts:
    """Rollouts shared by loops on the same data: ``with shared:`` runs its block with
    :func:`knockgs_core.rollout.run_rollout` answered from every call made under ``shared``
    before (a contract of the same hash, particles of the same arrays, the same theta, probe
    and options), else simulated and kept. CPU rollouts are the same bit for bit on every run,
    so a loop run again on the same data with other settings makes every decision it would make
    alone, and simulates only the models where it departs from the first (``simulated`` of
    ``calls`` counts them): the refined model and the grid placements, which each loop builds
    anew, are the same contracts on the same particles, and are read too."""

    def __init__(self):
        self._done, self.calls, self.simulated = {}, 0, 0

    @staticmethod
    def _particles_key(particles):
        import hashlib

        digest = hashlib.sha256()
        for name in ("positions", "volumes", "gaussian_index", "region"):
            a = getattr(particles, name)
            digest.update(b"-" if a is None else np.ascontiguousarray(a).tobytes() + str(np.asarray(a).dtype).encode())
        return digest.hexdigest(), particles.n_gs, tuple(particles.region_names)

    def __enter__(self):
        import knockgs_core.rollout as rollout

        real = rollout.run_rollout

        def run_rollout(contract, theta, probe_name, *, particles=None, **options):
            key = (contract.hash, self._particles_key(particles), tuple(float(t) for t in theta), probe_name,
                   pickle.dumps(sorted(options.items())))
            self.calls += 1
            if key not in self._done:
                self.simulated += 1
                self._done[key] = real(contract, theta, probe_name, particles=particles, **options)
            return self._done[key]

        self._patch = pytest.MonkeyPatch()
        self._patch.setattr(rollout, "run_rollout", run_rollout)
        return self

    def __exit__(self, *exc):
        self._patch.undo()


@pytest.fixture(scope="module")
def yield_world(loop_model):
    """Plasticity in data from the same MPM on a grid twice as fine (one rollout of the world on
    a grid of 64^3), and the loop on them at its smallest (:data:`YIELD_SETTINGS`, the loop's
    model at 2 substeps per frame; about 120 rollouts of the model and a few of the refined one):
    (measurement, result, the loop's rollouts, shared with the second loop on these data)."""
    from knockgs_core.assets import build_asset
    from knockgs_core.sim import VonMisesPlasticity

    contract, particles = loop_model
    world = refined_contract(contract, 2.0)
    m, _ = _tracks(world, build_asset(world).particles, YIELD_TRUTH, "standard_x",
                   (VonMisesPlasticity(yield_stress=80.0),), np.random.default_rng(11))
    shared = _SharedRollouts()
    with shared:
        res = run_discrepancy(m, contract, particles, settings=YIELD_SETTINGS)
    return m, res, shared


@pytest.mark.slow
def test_a_yield_in_a_finer_world_is_named_with_its_own_discretization_term(yield_world):
    """A yield resolved on the finer grid sets in elsewhere, so the model with a yield moves
    under refinement in its own way: scored with the term of its own fitted model it is named
    and its theta interval holds the truth."""
    # About a minute on an idle 2-core machine (the fixture: one whole loop, see yield_world)
    _, res, _ = yield_world
    assert res.identified == ["plasticity"], res.verdict
    row = next(r for r in res.rounds[0]["table"] if r["key"] == "plasticity")
    assert row["own_term"] and row["signature_ok"]
    assert row["floor_weight"] >= res.rounds[0]["floor_weight"] > 0  # its own floor, at least the round's
    assert 40.0 < res.effects[0]["value"] < 160.0
    # the term reported (and the theta interval's refinement shift) is the final model's
    assert res.model_error["computed_at_theta"] == pytest.approx(list(res.theta_final), rel=1e-12)
    (lo_e, hi_e), (lo_r, hi_r) = res.theta_interval
    assert lo_e <= YIELD_TRUTH[0] <= hi_e and lo_r <= YIELD_TRUTH[1] <= hi_r, res.theta_interval


@pytest.mark.slow
def test_a_yield_in_a_finer_world_is_missed_with_the_theta_only_models_term(loop_model, yield_world):
    """The same data scored with the term of the theta-only model: the yield explains less of
    the residual beyond the floor and is not added (a stiffness gradient, ahead of it there, may
    be named in its place): what the own term of the test above changes."""
    # A second whole loop on the same data: the models that it simulates where it follows the
    # loop of the fixture (which differs from it only by the own terms it adds), that loop has
    # simulated, so it reads them (the refined model and the placements too, rebuilt by each
    # loop: the same contracts on the same particles)
    contract, particles = loop_model
    m, res, shared = yield_world
    row = next(r for r in res.rounds[0]["table"] if r["key"] == "plasticity")
    with shared:
        old = run_discrepancy(m, contract, particles,
                              settings=dataclasses.replace(YIELD_SETTINGS, model_error_own_term=False))
    assert "plasticity" not in old.identified, old.verdict
    old_row = next(r for r in old.rounds[0]["table"] if r["key"] == "plasticity")
    assert "own_term" not in old_row and old_row["explained_excess"] < row["explained_excess"]
