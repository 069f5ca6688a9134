"""The G2P2G experiments' shared substep (``warp_shuffle_experiment.py``,
``arena_g2p2g_experiment.py``): one kernel runs G2P and the next substep's P2G, reading the node
velocities from one set of grids and adding the sums to another, swapped every substep. A
substep is: zero the other grids, the grid update and supports on these, the fused kernel.
Timed from one saved state against the solver's default GPU path."""

from __future__ import annotations

import time
from typing import Any

import warp as wp

from knockgs_core.sim import MPMSolver
from knockgs_core.sim import _kernels as K
from knockgs_core.sim._config import DomainWalls
from knockgs_core.sim._kernels import g2p_particle, p2g_terms, stencil_base, stencil_inside, updated_node


@wp.kernel(enable_backward=False)
def grid_update_zero_other(lo: wp.vec3i, dt: float, gravity: wp.vec3, damping: float, walls: int, n_grid: int,
                           padding: int, sticky: int, affine_flip: int, grid_m: wp.array3d(dtype=float),
                           grid_mv: wp.array3d(dtype=wp.vec3), grid_mv_old: wp.array3d(dtype=wp.vec3),
                           other_mv: wp.array3d(dtype=wp.vec3), other_m: wp.array3d(dtype=float),
                           other_mv_old: wp.array3d(dtype=wp.vec3)):
    """The solver's ``grid_update`` of one set of grids (its node function, :func:`updated_node`)
    and ``grid_zero`` of the other set, in one pass over the active box (one launch a substep
    less)."""
    i, j, k = wp.tid()
    gi = i + lo[0]
    gj = j + lo[1]
    gk = k + lo[2]
    other_mv[gi, gj, gk] = wp.vec3(0.0)
    other_m[gi, gj, gk] = 0.0
    mv_old = wp.vec3(0.0)
    if affine_flip == 1:
        other_mv_old[gi, gj, gk] = wp.vec3(0.0)
        mv_old = grid_mv_old[gi, gj, gk]
    v, v_old = updated_node(wp.vec3i(gi, gj, gk), grid_m[gi, gj, gk], grid_mv[gi, gj, gk], mv_old, dt, gravity, damping,
                            walls, n_grid, padding, sticky, affine_flip)
    if affine_flip == 1:
        grid_mv_old[gi, gj, gk] = v_old
    grid_mv[gi, gj, gk] = v


@wp.func
def g2p_next_terms(p: int, count: int, grid_v: wp.array(dtype=wp.vec3), inv_dx: float, dt: float,
                   trans_mask: wp.array(dtype=wp.int32), trans_velocity: wp.vec3, trans_on: int, lo: wp.vec3i,
                   hi: wp.vec3i, x0: wp.array(dtype=wp.vec3), affine_flip: int, flip_weight: float,
                   grid_v_old: wp.array(dtype=wp.vec3), g2p_lines: int, mass: wp.array(dtype=float),
                   vol: wp.array(dtype=float), mu: wp.array(dtype=float), lam: wp.array(dtype=float),
                   probe_mask: wp.array(dtype=wp.int32), probe_force: wp.vec3, probe_on: int, polar_iters: int,
                   polar_step: float, polar_rational: int, retardation: float, n_grid: int, u: wp.array(dtype=wp.vec3),
                   v: wp.array(dtype=wp.vec3), C: Any, F: Any, rot: wp.array(dtype=wp.quat),
                   overrun: wp.array(dtype=wp.int32)):
    """Particle ``p``'s G2P (written back) and its next P2G terms, as the solver's fused G2P
    computes them: whether it adds to the grid (``p < count`` and its stencils inside the
    active box, else the overrun is counted), its stencil base cell, its position in that cell
    [cells], momentum, mass and the affine matrices of the transfer and of its APIC term (zero
    where it adds nothing)."""
    valid = False
    base = wp.vec3i(0)
    f = wp.vec3(0.0)
    mvp = wp.vec3(0.0)
    m = float(0.0)
    aff = wp.mat33(0.0)
    mCp = wp.mat33(0.0)
    if p < count:
        ok, up, vp, Cp, Fp = g2p_particle(p, grid_v, n_grid, inv_dx, dt, trans_mask, trans_velocity, trans_on, lo, hi, x0,
                                          affine_flip, flip_weight, grid_v_old, g2p_lines, u, v, C, F, overrun)
        if ok:
            mp = mass[p]
            if probe_on == 1 and probe_mask[p] != 0:
                vp = vp + probe_force * (dt / mp)
                v[p] = vp
            q, a, mc = p2g_terms(vp, Cp, Fp, rot[p], mp, vol[p], mu[p], lam[p], inv_dx, dt, polar_iters, polar_step,
                                 polar_rational, retardation)
            rot[p] = q
            gx = (x0[p] + up) * inv_dx
            base = stencil_base(gx)
            if stencil_inside(base, lo, hi):
                valid = True
                f = gx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
                m = mp
                mvp = mp * vp
                aff = a
                mCp = mc
            else:
                wp.atomic_add(overrun, 0, 1)
    return valid, base, f, mvp, m, aff, mCp

#: the state's arrays a run starts from
_SAVED = ["particle_u", "particle_v", "particle_C", "particle_F", "particle_rot", "grid_mv", "grid_m", "grid_mv_old"]


class FusedPipeline:
    """The double-buffered substep of ``model``'s ``state`` over the active box of ``solver``
    (the warm-up's), from the state as it is now (saved).

    ``fused(S, D)`` launches the experiment's kernel: G2P from the grids ``S`` (a dict of
    ``grid_mv``, ``grid_m``, ``grid_mv_old``), the next P2G into ``D``."""

    def __init__(self, model, state, solver: MPMSolver):
        self.model, self.state, self.solver = model, state, solver
        p = model.params
        self.device = dev = model.device
        self.cuda = wp.get_device(dev).is_cuda
        self.step0 = state.step
        self.saved = {k: wp.clone(getattr(state, k)) for k in _SAVED}
        g = p.n_grid
        self.other = dict(grid_mv=wp.zeros((g, g, g), dtype=wp.vec3, device=dev),
                          grid_m=wp.zeros((g, g, g), dtype=float, device=dev),
                          grid_mv_old=wp.zeros((g, g, g), dtype=wp.vec3, device=dev))
        self.lo, self.hi = wp.vec3i(*solver._lo), wp.vec3i(*solver._hi)
        self.dims = tuple(h - low for low, h in zip(solver._lo, solver._hi))
        self.flip = int(p.transfer == "affine_flip")
        self.damping = p.grid_v_damping_scale ** (p.dt / p.damping_dt_ref) if p.grid_v_damping_scale < 1.0 else 1.0
        walls = p.boundaries[0] if p.boundaries and isinstance(p.boundaries[0], DomainWalls) else None
        self.wall_args = [1, g, walls.padding, int(walls.mode == "sticky")] if walls else [0, g, 0, 0]
        self.others = [bc for bc in p.boundaries if bc is not walls]
        self.overrun = wp.zeros(1, dtype=wp.int32, device=dev)
        self.zero_mask = wp.zeros(model.particle_count, dtype=wp.int32, device=dev)
        self.base = MPMSolver(model) if self.cuda else MPMSolver(model, p2g="scatter", graph=False, fuse=False)
        #: zero the other grids in the grid update's pass (:func:`grid_update_zero_other`)
        self.merge_zero = False

    def restore(self) -> None:
        """The state as saved."""
        for k, a in self.saved.items():
            wp.copy(getattr(self.state, k), a)
        self.state.step = self.step0

    def probe(self, step: int) -> int:
        """1 where the probe pushes during substep ``step``."""
        m = self.model
        return int(m.probe_steps > 0 and m.probe_first <= step < m.probe_first + m.probe_steps)

    def grids(self, which: int) -> dict:
        """The state's grids (0) or the other set (1)."""
        if which == 0:
            s = self.state
            return dict(grid_mv=s.grid_mv, grid_m=s.grid_m, grid_mv_old=s.grid_mv_old)
        return self.other

    def time_base(self, steps: int) -> float:
        """Seconds a substep of the solver's default path (graphs, fused G2P, windows on a GPU)."""
        self.restore()
        b = self.base
        b._prepared = b._sorted_at = b._cmds_key = None
        b._lo, b._hi = self.solver._lo, self.solver._hi
        for _ in range(2):  # record and capture outside the timing
            b.step(self.state)
        return self._timed(lambda: b.step(self.state), steps)

    def time_fused(self, fused, steps: int, *, first_p2g: str = "scatter") -> float:
        """Seconds a substep of the pipeline with the kernel launched by ``fused``: one
        substep by the solver's ``first_p2g`` path, the next P2G by the scatter into the
        state's grids, one untimed substep (the baseline's two), then ``steps`` substeps
        (two CUDA graphs, one a parity, on a GPU)."""
        self.restore()
        m, p, s, st = self.model, self.model.params, self.state, self.step0
        s0 = MPMSolver(m, p2g=first_p2g, graph=False, fuse=False)
        s0._lo, s0._hi = self.solver._lo, self.solver._hi
        s0._record(s)
        s0._launch(s, st * p.dt, self.probe(st), (True,) * len(s0._cmds["bcs"]), first_p2g == "cells", prepared=False,
                   probe_next=None)
        wp.launch(K.grid_zero, dim=self.dims, inputs=[self.lo, self.flip], outputs=[s.grid_mv, s.grid_m, s.grid_mv_old],
                  device=self.device)
        st += 1
        if self.probe(st) or self.probe(st + steps + 2):
            print("note: the probe is on in the timed substeps; the pipeline leaves it off", flush=True)
        sv = self.solver
        wp.launch(K.p2g, dim=m.particle_count,
                  inputs=[s.particle_x0, s.particle_u, s.particle_C, s.particle_F, m.particle_mass, m.particle_vol,
                          m.particle_mu, m.particle_lam, m.probe_mask, wp.vec3(*m.probe_force), self.probe(st), sv._inv_dx,
                          p.dt, sv.polar_iters, sv.polar_step, sv._polar_rational, sv.retardation, self.lo, self.hi,
                          self.flip],
                  outputs=[s.particle_v, s.particle_rot, s.grid_mv, s.grid_m, s.grid_mv_old, self.overrun],
                  device=self.device)
        graphs = []
        for par in range(2 if self.cuda else 0):
            with wp.ScopedCapture(device=self.device) as cap:
                self._substep(fused, par)
            graphs.append(cap.graph)
        src = [0]

        def one():
            if graphs:
                wp.capture_launch(graphs[src[0]])
            else:
                self._substep(fused, src[0])
            src[0] = 1 - src[0]

        one()
        return self._timed(one, steps)

    def _substep(self, fused, src: int) -> None:
        S, D = self.grids(src), self.grids(1 - src)
        p, dev, lo, dims = self.model.params, self.device, self.lo, self.dims
        update = [lo, p.dt, wp.vec3(*p.gravity), self.damping, *self.wall_args, self.flip, S["grid_m"]]
        if self.merge_zero:
            wp.launch(grid_update_zero_other, dim=dims, inputs=update,
                      outputs=[S["grid_mv"], S["grid_mv_old"], D["grid_mv"], D["grid_m"], D["grid_mv_old"]], device=dev)
        else:
            wp.launch(K.grid_zero, dim=dims, inputs=[lo, self.flip], outputs=[D["grid_mv"], D["grid_m"], D["grid_mv_old"]],
                      device=dev)
            wp.launch(K.grid_update, dim=dims, inputs=update, outputs=[S["grid_mv"], S["grid_mv_old"]], device=dev)
        for bc in self.others:
            if isinstance(bc, DomainWalls):
                wp.launch(K.grid_bc_walls, dim=dims, inputs=[lo, p.n_grid, bc.padding, int(bc.mode == "sticky")],
                          outputs=[S["grid_mv"]], device=dev)
            else:
                assert bc.start_time <= 0 and bc.end_time == float("inf")
                box_args = [wp.vec3(*bc.box.center), wp.vec3(*bc.box.half_size), wp.vec3(*bc.velocity),
                            bc.friction_coefficient]
                wp.launch(K.grid_bc_cuboid, dim=dims, inputs=[lo, p.dx, *box_args], outputs=[S["grid_mv"]], device=dev)
        fused(S, D)

    def _timed(self, one, steps: int) -> float:
        wp.synchronize_device(self.device)
        t0 = time.perf_counter()
        for _ in range(steps):
            one()
        wp.synchronize_device(self.device)
        return (time.perf_counter() - t0) / steps
