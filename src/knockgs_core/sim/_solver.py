"""MLS-MPM solver: :class:`MPMSolver` advances a :class:`~knockgs_core.sim.State` of a
:class:`~knockgs_core.sim.Model` by one substep, stepping as its
:class:`~knockgs_core.sim.SolverConfig` says.

The grid kernels run only over the *active box*, the part of the grid that the particles'
stencils can reach before the next guard check, so grid work scales with the occupied
region rather than with ``n_grid^3``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..errors import InputError, SimulationError
from . import _kernels as K
from ._config import DomainWalls, FixedCuboid, SolverConfig
from ._model import Model, State, cell_crowding, matrix_array

__all__ = ["MPMSolver"]


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


def _resolved(name: str) -> property:
    """The solver's resolved option ``name``, read from :attr:`MPMSolver.config`."""
    return property(lambda self: getattr(self.config, name), doc=f"The resolved :attr:`SolverConfig.{name}`.")


class MPMSolver:
    """Advances a :class:`State` of a :class:`Model` by substeps of ``params.dt``.

    A guard runs every ``params.guard_every`` substeps (and on demand): non-finite values,
    a CFL number ``max|v| dt / dx`` above ``params.cfl_limit``, or particles leaving the
    domain stop the run with a :class:`~knockgs_core.errors.SimulationError`. The guard also
    sizes the active grid box for the next substeps. ``effect_scratch`` holds the scratch
    object of each of ``params.effects`` (same order), made by its ``setup`` here.

    How it steps is ``config``, a :class:`SolverConfig` (its fields document the options),
    resolved for the model's device and particles (:meth:`SolverConfig.resolve`: every
    ``"auto"`` chosen, every option checked) and kept as :attr:`config`; keyword ``options``
    (the config's fields) replace the given config's (or the default's) fields first, so
    ``MPMSolver(model, p2g="cells")`` is ``MPMSolver(model, SolverConfig(p2g="cells"))``. The
    resolved options read as the solver's attributes (``solver.p2g``, ``solver.fuse``, ...);
    :attr:`resort_every` and :attr:`cell_chunk`, which set speed only, may be changed between
    substeps (checked when the launches are recorded).

    ``crowding``: the model's :func:`cell_crowding` where the caller has it (runs of one
    particle set share it: :func:`~knockgs_core.sim.simulate_many` counts it once); computed
    from the model's rest positions otherwise, and only where ``p2g="auto"`` chooses by it
    (recorded in :attr:`crowding`, else None).
    """

    #: cap on the warm-started polar iterations per particle and substep (they stop when the
    #: correction angle is below 1e-7 rad). Not a discretization knob: the stress needs the
    #: converged rotation. The Ficus's thin, fast-rotating parts need up to 8 iterations; a cap of
    #: 4 (the former value) moved its Probe-A response by 9 % and its dt sensitivity from 1.8 % to
    #: 6.5 % per halving (docs/assets.md). tests/test_sim_physics.py checks that it never binds.
    polar_iters = 32
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

    p2g = _resolved("p2g")
    graph = _resolved("graph")
    fuse = _resolved("fuse")
    deterministic = _resolved("deterministic")
    polar_step = _resolved("polar_step")
    polar_update = _resolved("polar_update")
    g2p_sums = _resolved("g2p_sums")
    window_atomics = _resolved("window_atomics")

    def __init__(self, model: Model, config: SolverConfig | None = None, *, crowding: float | None = None, **options):
        self.model = model
        p = model.params
        config = (SolverConfig() if config is None else config).with_options(**options)
        self.crowding = None
        if config.counts_crowding:
            x0 = model.particle_x0_host
            if crowding is None:
                crowding = cell_crowding(x0, p.dx) if x0 is not None else math.inf
            self.crowding = float(crowding)
        #: the resolved :class:`SolverConfig` the solver steps by
        self.config = config.resolve(cuda=wp.get_device(model.device).is_cuda,
                                     crowding=math.inf if self.crowding is None else self.crowding,
                                     hooks=bool(p.effects or model.translations))
        self.resort_every = self.config.resort_every
        self.cell_chunk = self.config.cell_chunk
        self._polar_rational = int(self.polar_update == "rational")
        self._g2p_lines = int(self.g2p_sums == "lines")
        self._make_scratch()
        self._graphs: dict = {}
        self._prepared: tuple[int, int] | None = None  # (state, step) whose P2G terms the last G2P computed
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

    def _make_scratch(self) -> None:
        """The P2G's scratch for the resolved options: the cells' (P2G by cells), the fixed-point
        sums' (deterministic) and the node records (vector atomics on float window sums), and
        stand-ins for the window kernel's arguments that its variant ignores."""
        model = self.model
        cells = self.p2g == "cells"
        self._cells = _CellScratch.make(model) if cells else None
        self._fixed = _FixedScratch(model) if self.deterministic else None
        # the bitwise-reproducible sums add no floats to the nodes: the vector atomics do not apply there
        float_windows = cells and not self.deterministic
        self._records = _RecordScratch(model) if self.window_atomics == "vector" and float_windows else None
        self._window_records = self._records
        if self._records is None and cells:
            self._window_records = _RecordScratch.placeholder(model.device)
        self._window_fixed = self._fixed
        if self._fixed is None and cells:
            self._window_fixed = _FixedScratch.placeholder(model.device)

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
        p = self.model.params
        lo = wp.vec3i(*self._lo)
        hi = wp.vec3i(*self._hi)
        dims = tuple(h - low for low, h in zip(self._lo, self._hi))
        rec = dict(device=self.model.device, record_cmd=True)
        flip = int(p.transfer == "affine_flip")
        cmds = {"zero": wp.launch(K.grid_zero, dim=dims, inputs=[lo, flip],
                                  outputs=[state.grid_mv, state.grid_m, state.grid_mv_old], **rec)}
        cmds.update(self._record_p2g(state, lo, hi, flip, rec))
        cmds.update(self._record_grid(state, lo, dims, flip, rec))
        cmds.update(self._record_g2p(state, lo, hi, flip, rec))
        self._cmds = cmds
        self._cmds_key = (id(state), self._lo, self._hi)
        self._graphs = {}  # graphs of the launches recorded before
        self._box = (lo, dims)  # the active box as the effects' grid hooks take it

    def _check_cell_settings(self) -> None:
        """:attr:`resort_every` and :attr:`cell_chunk` (adjustable between substeps), checked."""
        for name in ("resort_every", "cell_chunk"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise InputError("MPMSolver", name, f"must be an integer >= 1, got {value!r}")
        if self.cell_chunk > 256:
            raise InputError("MPMSolver", "cell_chunk", f"a window takes at most 256 particles (a block's threads "
                             f"and shared memory), got {self.cell_chunk}")

    def _record_p2g(self, state: State, lo: wp.vec3i, hi: wp.vec3i, flip: int, rec: dict) -> dict:
        """P2G's recorded launches (``probe_on`` is set per substep): the scatter, or by cells the
        per-particle half, the sort's keys and the window sums."""
        m, p = self.model, self.model.params
        # the particle inputs of both P2G variants
        particle_args = [state.particle_x0, state.particle_u, state.particle_C, state.particle_F,
                         m.particle_mass, m.particle_vol, m.particle_mu, m.particle_lam,
                         m.probe_weight, wp.vec3(*m.probe_force), 0, self._inv_dx, p.dt, self.polar_iters, self.polar_step,
                         self._polar_rational, self.retardation, lo, hi]
        if self._cells is None:  # one float atomic per particle and stencil node
            return {"p2g": wp.launch(
                K.p2g,
                dim=m.particle_count,
                inputs=[*particle_args, flip],
                outputs=[state.particle_v, state.particle_rot, state.grid_mv, state.grid_m, state.grid_mv_old, self._overrun],
                **rec,
            )}
        self._check_cell_settings()
        c = self._cells
        cmds = {}
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
        return cmds

    def _record_grid(self, state: State, lo: wp.vec3i, dims: tuple[int, int, int], flip: int, rec: dict) -> dict:
        """The grid update's recorded launch (from the grid's arrays, the fixed-point sums or the
        node records) and the boundary conditions' (``bcs``: (condition, launch) pairs)."""
        p = self.model.params
        dt = p.dt
        damping = p.grid_v_damping_scale ** (dt / p.damping_dt_ref) if p.grid_v_damping_scale < 1.0 else 1.0
        # domain walls listed first are applied in the update pass (same order, one pass less)
        fused = p.boundaries[0] if p.boundaries and isinstance(p.boundaries[0], DomainWalls) else None
        wall_args = [1, p.n_grid, fused.padding, int(fused.mode == "sticky")] if fused else [0, p.n_grid, 0, 0]
        update_args = [lo, dt, wp.vec3(*p.gravity), damping, *wall_args, flip, state.grid_m]
        cmds = {}
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
        return cmds

    def _record_g2p(self, state: State, lo: wp.vec3i, hi: wp.vec3i, flip: int, rec: dict) -> dict:
        """G2P's recorded launch, and with fused substeps the fused G2P's (``probe_on`` of the next
        substep, and the particle translation, set per substep)."""
        m, p = self.model, self.model.params
        dt = p.dt
        cmds = {}
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
                        m.particle_vol, m.particle_mu, m.particle_lam, m.probe_weight, wp.vec3(*m.probe_force), 0,
                        self.polar_iters, self.polar_step, self._polar_rational, self.retardation, p.n_grid, c.none_key],
                outputs=[state.particle_u, state.particle_v, state.particle_C, state.particle_F, state.particle_rot,
                         c.fx, c.affine, c.keys, self._overrun],
                **rec,
            )
        return cmds

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
        K.p2g_windows(SolverConfig.cell_chunk, _flip, _fixed, _records)

