"""Discretization checks of the object contracts at the ci profile.

(a) The simulated particles form one body at the grid resolution: particles closer than
    1.5 dx share most of their quadratic B-spline stencil and move together, so a group of
    particles farther than that from the rest is a separate body. Every group must contain a
    particle held by a support (fixed cuboid or particle translation box); a free group
    would fly off after the knock.
(b) Halving the substep changes the Probe-A response (displacement trajectories of the
    Gaussian-associated particles, first 10 exported frames) by less than 5 % (relative L2).

Measured (docs/assets.md, "Connectivity and substep convergence"): (a) holds for every
object and profile. (b) holds for the Pillow (2.4 %) but not for the Ficus (42 %) nor the
Vasedeck (6.9 %): the solver's APIC transfer loses the non-affine part of the grid velocity
at every substep, so the numerical damping of a rollout grows with its number of substeps
and a smaller dt moves the response further away rather than closer. Those two cases are
strict expected failures: they turn into errors as soon as the solver meets the bound.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from knockgs_core.assets import build_asset
from knockgs_core.contract import load_contract
from knockgs_core.rollout import run_rollout
from knockgs_core.sim import ExportSchedule

OBJECTS = ("pillow", "ficus", "vasedeck")
LINK_CELLS = 1.5       # particles closer than this many cells belong to one body
DT_TOLERANCE = 0.05    # relative L2 change of the response when dt is halved
N_FRAMES = 11          # t = 0 and the first 10 exported frames
THETA = (1.15, 0.75)   # stiffest, lightest candidate: the fastest response

# (object, measured relative change at the contract dt vs dt / 2 over the first 10 frames)
NOT_CONVERGED = {
    "ficus": "0.42: APIC transfer dissipation per substep dominates (docs/assets.md)",
    "vasedeck": "0.069: APIC transfer dissipation per substep (docs/assets.md)",
}


def held_mask(contract, positions: np.ndarray) -> np.ndarray:
    """Particles inside a support box (fixed cuboid or particle translation) at t = 0."""
    held = np.zeros(len(positions), dtype=bool)
    for bc in contract.sim.boundaries:
        box = getattr(bc, "box", None)
        if box is not None:
            held |= box.contains(positions)
    return held


def free_bodies(contract, positions: np.ndarray, *, link_cells: float = LINK_CELLS) -> list[int]:
    """Sizes of the particle groups (linked below ``link_cells * dx``) that hold no
    supported particle, largest first; empty when the object is one supported body."""
    pos = np.asarray(positions, dtype=np.float64)
    tree = cKDTree(pos)
    pairs = tree.sparse_distance_matrix(tree, link_cells * contract.sim.dx, output_type="coo_matrix")
    _, label = connected_components(pairs, directed=False)
    anchored = np.zeros(label.max() + 1, dtype=bool)
    anchored[label[held_mask(contract, pos)]] = True
    sizes = np.bincount(label)
    return sorted((int(s) for s in sizes[~anchored]), reverse=True)


def relative_change(a: np.ndarray, b: np.ndarray) -> float:
    """Relative L2 difference of the displacement trajectories ``a`` against ``b`` (T, N, 3)."""
    da = (a - a[0]).astype(np.float64)
    db = (b - b[0]).astype(np.float64)
    return float(np.linalg.norm(da - db) / np.linalg.norm(db))


# --------------------------------------------------------------------------- (a) one body

@pytest.mark.parametrize("profile", ["ci", "default"])
@pytest.mark.parametrize("name", OBJECTS)
def test_simulated_particles_form_one_supported_body(name, profile):
    c = load_contract(name, profile)
    ps = build_asset(c).particles
    assert held_mask(c, ps.positions).any()
    assert free_bodies(c, ps.positions) == []


def test_a_detached_leaf_cluster_is_found():
    """The check fails on a Ficus whose top leaf cluster is lifted 3 cells off the plant."""
    c = load_contract("ficus", "ci")
    pos = np.array(build_asset(c).particles.positions, dtype=np.float64)
    top = np.linalg.norm(pos - pos[np.argmax(pos[:, 2])], axis=1) < 1.5 * c.sim.dx
    pos[top, 2] += 3.0 * c.sim.dx
    assert free_bodies(c, pos) == [int(top.sum())]


# --------------------------------------------------------------------------- (b) dt

def _probe_a(contract, particles, dt: float) -> np.ndarray:
    probe = contract.resolve_probes(particles)[contract.roles["calibration"]]
    probe = dataclasses.replace(probe, export=ExportSchedule(probe.export.frame_dt, N_FRAMES))
    out = run_rollout(contract, THETA, probe.name, particles=particles, probe=probe, sim_overrides={"dt": dt})
    return out.positions[:, : particles.n_gs]


def _expected(name: str):
    if name not in NOT_CONVERGED:
        return name
    return pytest.param(name, marks=pytest.mark.xfail(strict=True, raises=AssertionError, reason=NOT_CONVERGED[name]))


@pytest.mark.parametrize("name", [_expected(n) for n in OBJECTS])
def test_halving_dt_keeps_the_probe_a_response(name):
    c = load_contract(name, "ci")
    ps = build_asset(c).particles
    dt = c.sim.dt
    coarse, fine = _probe_a(c, ps, dt), _probe_a(c, ps, dt / 2)
    assert np.all(np.isfinite(coarse)) and np.all(np.isfinite(fine))
    assert np.abs(fine - fine[0]).max() > 1e-4           # the knock moves the object
    assert relative_change(coarse, fine) < DT_TOLERANCE
