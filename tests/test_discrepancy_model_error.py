"""The discrepancy loop's model-error floor and time signature (docs/discrepancy.md, section 3)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from knockgs_core.discrepancy import LoopSettings, Measurement, run_discrepancy
from knockgs_core.discrepancy._fitting import Problem
from knockgs_core.discrepancy._forward import ModelSpec
from knockgs_core.discrepancy._model_error import displacement_at, refined_contract
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
class _Export:
    frame_dt, n_frames = 0.02, 12


class _Particles:
    def __init__(self, X0):
        self.positions, self.n_gs = X0, len(X0)


class _Forward:
    """A linear 'simulator': positions = rest + s_E * A(t) (s_rho unused)."""

    def __init__(self, X0, A):
        self.particles, self.A, self.X0 = _Particles(X0), A, X0

    def probe_export(self, probe):
        return _Export

    def rollout(self, spec, probe):
        return self.X0[None] + spec.theta[0] * self.A


def test_coefficient_is_profiled_on_the_fit_window_and_bounded(rng):
    T, M = 12, 30
    X0 = rng.uniform(0, 1, size=(M, 3))
    t = np.arange(T)[:, None, None] * 0.02
    A = np.sin(9 * t) * rng.normal(size=(1, M, 3)) * 1e-3
    term = np.cos(5 * t) * rng.normal(size=(1, M, 3)) * 1e-3
    term[0] = 0
    fw = _Forward(X0, A)
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


def test_settings_refuse_a_refinement_that_refines_nothing():
    with pytest.raises(InputError, match="model_error_refine"):
        LoopSettings(model_error_refine=1.0)
    assert LoopSettings(model_error_refine=None).model_error_refine is None
