"""Rollouts: :func:`simulate` runs one simulation and exports its frames, :func:`simulate_many`
runs several in lockstep (on a GPU on streams of their own, their frames copied back behind the
next substeps), each with an :class:`~knockgs_core.sim.MPMSolver` of the options it is given.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Callable

import numpy as np
import warp as wp

from ..errors import InputError
from . import _kernels as K
from ._config import SolverConfig, as_flag
from ._model import Model, State
from ._solver import MPMSolver

__all__ = ["SimResult", "simulate", "simulate_many"]


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



def _solver_options(options: Mapping | None) -> dict:
    """``options`` checked as :class:`MPMSolver` keywords (:class:`SolverConfig`'s fields) that
    :func:`simulate_many` passes on (``deterministic`` it sets itself)."""
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise InputError("simulation", "solver_options", f"must be a mapping of MPMSolver options, got {type(options).__name__}")
    known = [f.name for f in dataclasses.fields(SolverConfig)]
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



def _steps_per_frame(runs: list[tuple[Model, State]], frame_dt: float) -> int:
    """Substeps a frame of ``runs``, which must share one time step that divides ``frame_dt``."""
    dts = {m.params.dt for m, _ in runs}
    if len(dts) != 1:
        raise InputError("simulation", "dt", f"runs simulated together must share one time step, got {sorted(dts)}")
    dt = runs[0][0].params.dt
    ratio = frame_dt / dt
    steps = int(round(ratio))
    if steps < 1 or abs(ratio - steps) > 1e-6 * max(1.0, ratio):
        raise InputError("simulation", "frame_dt", f"frame_dt = {frame_dt:g} s must be a whole multiple of dt = {dt:g} s")
    return steps


class _Lockstep:
    """The runs of :func:`simulate_many`, stepped together: each run's solver (made here, its
    first frame exported), stream (with ``concurrent`` on a CUDA device), exporter, frame arrays
    and last guard statistics, and the frames staged and not yet handed over."""

    def __init__(self, runs: list[tuple[Model, State]], *, n_frames: int, export_F: int, export_index, concurrent: bool,
                 deterministic: bool, options: dict, on_frame, progress):
        self.runs, self.n_frames, self.on_frame, self.progress = runs, n_frames, on_frame, progress
        self.streams = None
        if concurrent and len(runs) > 1 and wp.get_device(runs[0][0].device).is_cuda:
            device = runs[0][0].device
            wp.synchronize_device(device)  # the models' arrays are ready before other streams read them
            self.streams = [wp.Stream(device) for _ in runs]
        self.exporters = [_Exporter(model, export_F, export_index) for model, _ in runs]
        self.solvers, self.positions, self.Fs, self.stats = [], [], [], []
        # (run, frame, its statistics) staged and not yet taken: on a GPU a frame's copies run
        # behind the next substeps, and the frame is handed over before the host waits on anything
        # else (the next guard check or frame)
        self.staged: list[tuple[int, int, dict]] = []
        crowding: dict[tuple, float | None] = {}  # runs of one particle set and grid count their cells once
        for i, (model, state) in enumerate(runs):
            with self.on(i):
                shared = (id(model.particle_x0_host), model.params.dx)
                solver = MPMSolver(model, deterministic=deterministic, crowding=crowding.get(shared), **options)
                crowding[shared] = solver.crowding
                n = model.particle_count
                X = np.empty((n_frames, n, 3), dtype=np.float32)
                F = np.empty((n_frames, export_F, 3, 3), dtype=np.float32) if export_F else None
                self.stats.append(solver.check(state))
                self.exporters[i].export(state, X, F, 0)
            if on_frame is not None:
                on_frame(i, 0, X[0], None if F is None else F[0])
            self.solvers.append(solver)
            self.positions.append(X)
            self.Fs.append(F)

    def on(self, i: int):
        """Run ``i``'s stream as the current one (a no-op without streams)."""
        return wp.ScopedStream(self.streams[i]) if self.streams else contextlib.nullcontext()

    def hand_over(self) -> None:
        """Take the staged frames into the results, in order, and report them."""
        for i, f, st in self.staged:
            self.exporters[i].take(self.positions[i], self.Fs[i], f)
            if self.on_frame is not None:
                self.on_frame(i, f, self.positions[i][f], None if self.Fs[i] is None else self.Fs[i][f])
            if self.progress is not None:
                self.progress(i, f, self.n_frames, st)
        self.staged.clear()

    def substep(self) -> None:
        """One substep of every run in turn, then the guard checks that are due."""
        for i, (_, state) in enumerate(self.runs):
            with self.on(i):
                self.solvers[i].step(state)
        for i, (model, state) in enumerate(self.runs):
            # the guard runs every guard_every substeps and right after the probe's first
            # substep (velocities jump there, and the active box must follow)
            if state.step % model.params.guard_every == 0 or (model.probe_steps and state.step == model.probe_first + 1):
                self.hand_over()
                with self.on(i):
                    self.stats[i] = self.solvers[i].check(state)

    def end_frame(self, frame: int) -> None:
        """Check every run and stage its frame ``frame``; handed over at once where staged on the
        host, else behind the next substeps."""
        self.hand_over()
        for i, (_, state) in enumerate(self.runs):
            with self.on(i):
                self.stats[i] = self.solvers[i].check(state)
                self.exporters[i].stage(state)
            self.staged.append((i, frame, self.stats[i]))
        if not any(e.pending is not None for e in self.exporters):
            self.hand_over()  # staged on the host: handed over at once, as each frame is exported

    def results(self, frame_dt: float, steps_per_frame: int) -> list[SimResult]:
        """One :class:`SimResult` per run, in order (every frame handed over)."""
        times = np.arange(self.n_frames, dtype=np.float64) * frame_dt
        return [
            SimResult(times=times.copy(), positions=self.positions[i], F=self.Fs[i],
                      stats={"max_cfl": solver.max_cfl, "min_det_F": solver.min_det_F, "steps": state.step,
                             "steps_per_frame": steps_per_frame},
                      reproducible_sums=solver.reproducible_sums if solver.deterministic else None)
            for i, (solver, (_, state)) in enumerate(zip(self.solvers, self.runs))
        ]


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
    (:attr:`SolverConfig.deterministic`: a GPU rollout the same bit for bit on every run; True
    or False only, refused otherwise). ``solver_options``: further keywords of each run's
    :class:`MPMSolver`, :class:`SolverConfig`'s fields (e.g. :data:`GPU_SOLVER_OPTIONS`; None:
    the device's choices); an unknown key is refused by name. Returns one :class:`SimResult`
    per run, in order."""
    options = _solver_options(solver_options)
    deterministic = as_flag("simulation", "deterministic", deterministic)
    if not runs:
        return []
    steps_per_frame = _steps_per_frame(runs, frame_dt)
    batch = _Lockstep(runs, n_frames=n_frames, export_F=export_F, export_index=export_index, concurrent=concurrent,
                      deterministic=deterministic, options=options, on_frame=on_frame, progress=progress)
    for frame in range(1, n_frames):
        for _ in range(steps_per_frame):
            batch.substep()
        batch.end_frame(frame)
    batch.hand_over()
    return batch.results(frame_dt, steps_per_frame)
