"""Run one rollout of an object contract and store it as Parquet.

Rollout file (one per object, profile, parameter case and probe), long format::

    frame (int32), particle (int32), x, y, z (float32)

one row per (frame, particle), particles ``0 .. n_gs - 1`` Gaussian-associated, then fill
particles. The schema metadata key ``knockgs`` holds JSON: theta, probe, export times,
n_gs, n_fill, the total probe force, the contract hash, solver settings, guard statistics
and package versions. The deformation gradient of the Gaussian-associated particles, when
asked for, goes to a second Parquet file (``frame, particle, F00 .. F22``).

Files are written through :mod:`knockgs_core.io` (a temporary name, renamed when complete),
so an interrupted run never leaves a partial rollout behind; they are read back with the one
long-format reader, :mod:`knockgs_core.io`. A file is written whole once the
rollout is finished (:func:`write_rollout`, :func:`write_deformation`), or frame by frame
while it is simulated (:class:`RolloutStream`, handed to :func:`run_rollouts`): the same
values, order and metadata either way.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pyarrow as pa

from . import __version__
from .errors import InputError
from .io import (GROUP_ROWS, LONG_COMPRESSION, POSITION_COLUMNS, LongFormatStream, check_rollout_meta, json_safe,
                 long_encoding, long_table, read_long_values, read_metadata, remove_outputs, theta_tag, write_parquet)
from .io._long_format import _has_field, _meta_field
from .sim import Probe

__all__ = [
    "Rollout",
    "run_rollout",
    "run_rollouts",
    "cell_order",
    "batches",
    "write_rollout",
    "read_rollout",
    "read_rollout_meta",
    "check_rollout_meta",
    "write_deformation",
    "read_deformation",
    "F_MAX",
    "BackgroundWriter",
    "RolloutStream",
    "theta_tag",
]

META_KEY = b"knockgs"
F_COLUMNS = [f"F{i}{j}" for i in range(3) for j in range(3)]


@dataclass
class Rollout:
    """A finished rollout: positions [m] (T, N, 3) float32, optional F (T, n_gs, 3, 3), metadata."""

    positions: np.ndarray
    F: np.ndarray | None
    meta: dict[str, Any]


def run_rollout(
    contract,
    theta: tuple[float, float],
    probe_name: str,
    *,
    particles=None,
    device: str | None = None,
    export_F: bool = False,
    probe: Probe | None = None,
    progress: Callable[[int, int, dict], None] | None = None,
    sim_overrides: dict | None = None,
    particle_order: str = "auto",
    stream: RolloutStream | None = None,
    deterministic: bool = False,
) -> Rollout:
    """Simulate ``contract`` at ``theta = (s_E, s_rho)`` under its probe ``probe_name``.

    ``particles`` (a :class:`knockgs_core.assets.ParticleSet`) defaults to building the
    contract's asset. ``probe`` overrides the contract's probe of that name (diagnostics).
    ``sim_overrides`` replaces fields of the contract's :class:`~knockgs_core.sim.SimParams`.
    ``particle_order``, ``stream`` (the rollout's files written as it runs) and
    ``deterministic``: as in :func:`run_rollouts`.
    """
    report = None if progress is None else (lambda run, frame, n, stats: progress(frame, n, stats))
    return run_rollouts(contract, [(theta, probe_name)], particles=particles, device=device, export_F=export_F,
                        probe=probe, progress=report, sim_overrides=sim_overrides, concurrent=False,
                        particle_order=particle_order, streams=None if stream is None else [stream],
                        deterministic=deterministic)[0]


def run_rollouts(
    contract,
    runs: list[tuple[tuple[float, float], str]],
    *,
    particles=None,
    device: str | None = None,
    export_F: bool = False,
    probe: Probe | None = None,
    progress: Callable[[int, int, int, dict], None] | None = None,
    sim_overrides: dict | None = None,
    concurrent: bool = True,
    particle_order: str = "auto",
    streams: Sequence[RolloutStream | None] | None = None,
    deterministic: bool = False,
) -> list[Rollout]:
    """Several rollouts of one contract, ``runs`` = [(theta, probe_name), ...], simulated
    together (:func:`knockgs_core.sim.simulate_many`): each is what :func:`run_rollout` makes
    of it (bit for bit on the CPU), and on a CUDA device the runs overlap on their own
    streams (``concurrent``). The runs' probes must share one export schedule.
    ``progress(run, frame, n_frames, stats)`` after each exported frame of each run.

    ``particle_order``: the order the simulator holds the particles in: ``"asset"`` (the
    particle set's), ``"cell"`` (sorted by grid cell within the Gaussian-associated rows and
    within the fill rows, :func:`cell_order`: neighbours lie together in memory, which the
    GPU's by-cell P2G reads faster) or ``"auto"`` (cell on a CUDA device, asset on the CPU,
    whose rollouts stay bit for bit what they were). The rollouts are returned in the
    particle set's order whatever the order simulated.

    ``streams``: one :class:`RolloutStream` (or None) per run, which writes the run's files
    while it is simulated: each exported frame is handed to it as it comes, and its metadata
    (the returned rollout's) once the batch is done, so only the last frames and the footer
    are written after the simulation. The files equal :func:`write_rollout`'s and
    :func:`write_deformation`'s of the returned rollouts once decoded. When the batch fails
    or is interrupted (a bad input, the guard stopping a blow-up, ``KeyboardInterrupt``),
    every stream is aborted before the error propagates: no file, no temporary file.

    ``deterministic``: the bitwise-reproducible P2G (``MPMSolver(deterministic=True)``): on a
    GPU the same rollout, bit for bit, on every run (the float atomics of the default P2G add
    in the order the GPU schedules them); recorded in the metadata (``deterministic``, and
    ``reproducible_sums``: how the sums were made reproducible, whose bits differ). CPU rollouts are
    reproducible either way (and differ between the two in the last bits). True or False
    only; a study passes its caller's setting to every rollout it runs."""
    with _streamed(streams, len(runs), export_F) as on_frame:
        out = _simulate_rollouts(contract, runs, particles=particles, device=device, export_F=export_F, probe=probe,
                                 progress=progress, sim_overrides=sim_overrides, concurrent=concurrent,
                                 particle_order=particle_order, on_frame=on_frame, deterministic=deterministic)
        for stream, rollout in zip(streams or [], out):
            if stream is not None:
                stream.finish(rollout.meta)
    return out


@contextlib.contextmanager
def _streamed(streams: Sequence[RolloutStream | None] | None, n_runs: int, export_F: bool):
    """Yield the simulator's ``on_frame`` callback that hands run i's frames to ``streams[i]``
    (None without streams); abort every stream when the block fails."""
    if streams is None:
        yield None
        return
    streams = list(streams)
    try:
        if len(streams) != n_runs:
            raise InputError("run_rollouts", "streams", f"one stream (or None) per run: {n_runs} runs, "
                                                        f"{len(streams)} streams")
        for stream in streams:
            if stream is not None and stream.F_path is not None and not export_F:
                raise InputError(stream.F_path, "F", "the rollout was run without export_F")

        def on_frame(run: int, frame: int, positions: np.ndarray, F: np.ndarray | None) -> None:
            if streams[run] is not None:
                streams[run].frame(frame, positions, F)

        yield on_frame
    except BaseException:
        for stream in streams:
            if stream is not None:
                stream.abort()
        raise


def _simulate_rollouts(contract, runs, *, particles, device, export_F, probe, progress, sim_overrides, concurrent,
                       particle_order, on_frame, deterministic=False) -> list[Rollout]:
    """:func:`run_rollouts` without its streams: ``on_frame`` as in
    :func:`knockgs_core.sim.simulate_many`."""
    import warp as wp

    from ._warp import warp_device

    if particles is None:
        from .assets import build_asset

        particles = build_asset(contract).particles
    params = contract.sim
    if sim_overrides:
        params = dataclasses.replace(params, **sim_overrides)
    if particle_order == "auto":
        particle_order = "cell" if warp_device(device).is_cuda else "asset"  # starts Warp, quiet on the CPU
    if particle_order not in ("asset", "cell"):
        raise InputError("run_rollouts", "particle_order", f"must be 'auto', 'asset' or 'cell', got {particle_order!r}")
    riders = _riders(contract, particles)
    if riders is not None and on_frame is not None:
        on_frame = _riding_frames(on_frame, riders)
    perm = cell_order(particles, n_grid=params.n_grid, grid_lim=params.grid_lim) if particle_order == "cell" else None
    if perm is not None:
        particles = _permuted(particles, perm)
    resolved = None
    n = len(particles.positions)
    ref = getattr(contract, "probe_reference_particles", None)
    force_scale = float(ref) / n if ref else 1.0
    setups = []
    for theta, probe_name in runs:
        s_e, s_rho = (float(t) for t in theta)
        if not (s_e > 0 and s_rho > 0 and math.isfinite(s_e) and math.isfinite(s_rho)):
            raise InputError(f"object {contract.name}", "theta", f"scales must be positive and finite, got {theta}")
        if probe is None and probe_name not in contract.probes:
            raise InputError(contract.source, "probes", f"unknown probe '{probe_name}'; known: {sorted(contract.probes)}")
        if probe is None:  # contact boxes checked and matched-total-force probes rescaled
            resolved = resolved or contract.resolve_probes(particles)
            run_probe = resolved[probe_name]
        else:
            run_probe = probe
        E, nu, rho = contract.particle_materials(particles, (s_e, s_rho))
        setups.append(((s_e, s_rho), run_probe, E, nu, rho))
    exports = {(pr.export.frame_dt, pr.export.n_frames) for _, pr, *_ in setups}
    if len(exports) > 1:
        raise InputError(f"object {contract.name}", "probes",
                         f"rollouts run together must share one export schedule, got {sorted(exports)}")
    (frame_dt, n_frames), = exports
    from .sim import build_model, make_state, particle_volumes, simulate_many  # Warp: imported where it runs

    t0 = time.perf_counter()
    models = []
    # one rest-position array for the batch's models, and its per-cell volumes counted once (each
    # model would count them again): the same arrays, so the same bits
    positions = np.ascontiguousarray(particles.positions, dtype=np.float32)
    volumes = particle_volumes(positions, params.dx) if particles.volumes is None else particles.volumes
    for _, run_probe, E, nu, rho in setups:
        model = build_model(
            positions, E=E, nu=nu, rho=rho, params=params, volumes=volumes,
            probe=run_probe, probe_force_scale=force_scale, probe_by_mass=particles.volumes is not None, device=device,
        )
        models.append((model, make_state(model, positions)))
    inv = None
    if perm is not None:  # exported back in the particle set's order, gathered on the device
        inv = np.empty_like(perm)
        inv[perm] = np.arange(len(perm), dtype=perm.dtype)
    results = simulate_many(models, frame_dt=frame_dt, n_frames=n_frames,
                                             export_F=particles.n_gs if export_F else 0, progress=progress,
                                             concurrent=concurrent, export_index=inv, on_frame=on_frame,
                                             deterministic=deterministic)
    wall = time.perf_counter() - t0
    out = []
    for ((s_e, s_rho), run_probe, *_), (model, _), result in zip(setups, models, results):
        meta = {
            "object": contract.name,
            "profile": contract.profile,
            "contract_hash": contract.hash,
            "theta": [s_e, s_rho],
            "probe": json_safe(run_probe),
            "probe_force_scale": force_scale,
            "probe_selected_count": model.probe_count,
            "probe_force_per_particle_step": list(model.probe_force),
            "total_probe_force": list(model.total_probe_force),
            "probe_impulse": list(model.probe_impulse),
            "export_times": result.times.tolist(),
            "n_gs": int(particles.n_gs),
            "n_fill": int(n - particles.n_gs),
            "sim": json_safe(params),
            "stats": json_safe(result.stats),
            "device": model.device,
            "wall_seconds": wall,
            "versions": {"knockgs": __version__, "warp": wp.config.version, "numpy": np.__version__},
        }
        if len(runs) > 1:
            meta["simulated_with"] = len(runs)  # wall_seconds is then the batch's
        if perm is not None:
            meta["particle_order"] = "cell"
        if result.reproducible_sums is not None:
            meta["deterministic"] = True
            meta["reproducible_sums"] = result.reproducible_sums  # how: their bits differ
        positions, F = result.positions, result.F
        if riders is not None:
            positions, F = _ride(riders, positions, F)
            meta["passengers"] = int(len(riders[0]))
        out.append(Rollout(positions=positions, F=F, meta=meta))
    return out


def _riders(contract, particles):
    """(rows [K], anchors [K], offsets [K, 3] m): the particles that ride on the body
    (``fill.passenger_boxes`` under ``enclosed`` volumes, :mod:`knockgs_core.assets._volumes`),
    the body's Gaussian-associated particle nearest each at rest, and each one's rest offset from
    it; None where there are none. The MPM moves them with a negligible share of the body, which
    keeps them out of its dynamics but not out of trouble: a part thinner than a cell, held by no
    body node on a fine grid, is a weightless sheet that pure FLIP lets drift. Their exported
    motion is their anchor's, as the finite-element world moves a point outside its mesh with the
    mesh's nearest point."""
    from .assets._volumes import passengers

    fill = getattr(contract, "fill", None)
    if fill is None or fill.volumes != "enclosed" or not fill.passenger_boxes:
        return None
    g = int(particles.n_gs)
    x = np.asarray(particles.positions, dtype=np.float64)
    rides = passengers(x, fill.passenger_boxes)
    rows = np.flatnonzero(rides)
    body = np.flatnonzero(~rides[:g])
    if not rows.size or not body.size:
        return None
    from scipy.spatial import cKDTree

    anchors = body[cKDTree(x[body]).query(x[rows])[1]]
    return rows, anchors, x[rows] - x[anchors]


def _riding_frames(on_frame, riders):
    """``on_frame`` handed each frame with the riders moved (:func:`_ride`)."""
    def frame(run: int, index: int, positions: np.ndarray, F: np.ndarray | None) -> None:
        on_frame(run, index, *_ride(riders, positions[None], None if F is None else F[None], single=True))

    return frame


def _ride(riders, positions, F, *, single: bool = False):
    """``positions`` [T, N, 3] and ``F`` [T, n_gs, 3, 3] (or None) with each rider at its
    anchor's position plus its rest offset from it and with its anchor's F; with ``single``, one
    frame each, returned without the leading axis."""
    rows, anchors, offset = riders
    pos = np.array(positions, copy=True)
    pos[:, rows] = (pos[:, anchors].astype(np.float64) + offset[None]).astype(pos.dtype)
    if F is not None:
        F = np.array(F, copy=True)
        inside = rows < F.shape[1]
        F[:, rows[inside]] = F[:, anchors[inside]]
    return (pos[0], None if F is None else F[0]) if single else (pos, F)


def cell_order(particles, *, n_grid: int, grid_lim: float) -> np.ndarray:
    """A permutation [N] of ``particles`` sorting them by stencil base cell (``floor(x / dx -
    0.5)`` with ``dx = grid_lim / n_grid`` [m], x-major, as the solver's P2G groups them)
    within the Gaussian-associated rows and within the fill rows, each stably: the
    Gaussian-associated particles stay first."""
    X = np.asarray(particles.positions, dtype=np.float64)
    g = int(particles.n_gs)
    cell = np.clip(np.floor(X / (grid_lim / n_grid) - 0.5).astype(np.int64), 0, n_grid - 1)
    key = (cell[:, 0] * n_grid + cell[:, 1]) * n_grid + cell[:, 2]
    return np.concatenate([_stable_argsort(key[:g]), g + _stable_argsort(key[g:])])


def _stable_argsort(key: np.ndarray) -> np.ndarray:
    """``np.argsort(key, kind="stable")`` for non-negative int64 keys [N]: the keys with each
    row's index in their low bits sorted by value (no two equal, so the order is the stable
    one) and the indices taken back, 5-7x faster than a stable argsort at 600k rows; the
    stable argsort where the two do not fit in 63 bits."""
    n = len(key)
    bits = max(1, (n - 1).bit_length())
    if n == 0 or key.min() < 0 or int(key.max()) >= 1 << (63 - bits):
        return np.argsort(key, kind="stable")
    return np.sort((key.astype(np.int64) << bits) | np.arange(n, dtype=np.int64)) & ((1 << bits) - 1)


def _permuted(particles, perm: np.ndarray):
    """``particles`` with its rows in the order ``perm`` (Gaussian-associated rows first)."""
    g = int(particles.n_gs)
    return dataclasses.replace(particles, positions=particles.positions[perm],
                               volumes=None if particles.volumes is None else particles.volumes[perm],
                               gaussian_index=particles.gaussian_index[perm[:g]], region=particles.region[perm])


def batches(runs: list, key: Callable[[Any], Any], *, together: bool) -> list[list[tuple[int, Any]]]:
    """The ``runs`` (in order, as (index, run) pairs) in the batches :func:`run_rollouts`
    simulates: consecutive runs with the same ``key`` (their export schedule) together when
    ``together`` (on a GPU), one run a batch otherwise."""
    out: list[list[tuple[int, Any]]] = []
    for i, run in enumerate(runs):
        if out and together and key(out[-1][0][1]) == key(run):
            out[-1].append((i, run))
        else:
            out.append([(i, run)])
    return out


def _long_encoding(table: pa.Table) -> dict[str, str]:
    """Parquet encodings of a long-format table (:func:`knockgs_core.io.long_encoding`)."""
    return long_encoding(table.column_names)


def _meta_bytes(meta: dict) -> dict[bytes, bytes]:
    """The schema metadata of a rollout's files: ``meta`` as JSON under :data:`META_KEY`."""
    return {META_KEY: json.dumps(meta).encode()}


def write_rollout(path, rollout: Rollout) -> None:
    """Write positions in the long Parquet format with the metadata (atomically)."""
    X = np.asarray(rollout.positions, dtype=np.float32)
    if not np.all(np.isfinite(X)):
        raise InputError(path, "x", "refusing to write non-finite positions")
    table = long_table(X, POSITION_COLUMNS).replace_schema_metadata(_meta_bytes(rollout.meta))
    write_parquet(path, table, compression=LONG_COMPRESSION, column_encoding=_long_encoding(table))


def write_deformation(path, rollout: Rollout) -> None:
    """Write the deformation gradients (frame, particle, F00..F22) of the GS particles."""
    if rollout.F is None:
        raise InputError(path, "F", "the rollout was run without export_F")
    F = np.asarray(rollout.F, dtype=np.float32)
    T, N = F.shape[:2]
    table = long_table(F.reshape(T, N, 9), F_COLUMNS).replace_schema_metadata(_meta_bytes(rollout.meta))
    write_parquet(path, table, compression=LONG_COMPRESSION, column_encoding=_long_encoding(table))


class RolloutStream:
    """Writes one rollout's files while it is simulated: positions to ``path`` and, with
    ``F_path``, the deformation gradients of the Gaussian-associated particles.

    Hand it to :func:`run_rollouts` (``streams``) or :func:`run_rollout` (``stream``), which
    call :meth:`frame` after each exported frame and :meth:`finish` with the rollout's
    metadata, or :meth:`abort` when the simulation fails. Each file is written on a thread
    of its own (:class:`knockgs_core.io.LongFormatStream`), the frames appended as
    Parquet row groups (at least ``group_rows`` rows each) as they come, so that when the
    simulation ends only the last frames and the footers are left to write; :meth:`wait`
    waits for them. Once decoded, the files equal :func:`write_rollout`'s and
    :func:`write_deformation`'s of the finished rollout (values, row order, metadata), and
    like them they appear only when complete: an abort, a failed write or the program's
    end before :meth:`finish` leaves no file and no temporary file.
    """

    def __init__(self, path, F_path=None, *, group_rows: int = GROUP_ROWS):
        self.path = Path(path)
        self.F_path = None if F_path is None else Path(F_path)
        self._positions = LongFormatStream(path, POSITION_COLUMNS, group_rows=group_rows, refuse_non_finite="positions")
        try:
            self._F = None if F_path is None else LongFormatStream(F_path, F_COLUMNS, group_rows=group_rows)
        except BaseException:
            self._positions.abort()
            raise

    @property
    def _streams(self) -> list[LongFormatStream]:
        return [s for s in (self._positions, self._F) if s is not None]

    @property
    def frames(self) -> int:
        """The frames handed over so far."""
        return self._positions.frames

    @property
    def finished(self) -> bool:
        """Whether :meth:`finish` has handed the metadata over."""
        return self._positions.finished

    @property
    def aborted(self) -> bool:
        """Whether :meth:`abort` was called (by :func:`run_rollouts` when the simulation failed)."""
        return any(s.aborted for s in self._streams)

    @property
    def done(self) -> bool:
        """Whether the writes have stopped (files complete, a write failed, or aborted)."""
        return all(s.done for s in self._streams)

    def frame(self, index: int, positions: np.ndarray, F: np.ndarray | None = None) -> None:
        """Hand exported frame ``index`` over (0, 1, ... in order): ``positions`` [N, 3]
        float32 [m], particles in the particle set's order; ``F`` [n_gs, 3, 3] float32, the
        deformation gradients, needed with ``F_path``. The arrays are kept until written,
        not copied: they must not change afterwards. Raises a failed write's error."""
        if self._F is not None and F is None:
            raise InputError(self.F_path, "F", "the rollout was run without export_F")
        if self._F is not None:
            F = np.asarray(F, dtype=np.float32)
            if F.ndim != 3 or F.shape[1:] != (3, 3):
                raise InputError(self.F_path, "F", f"frame {index} has shape {F.shape}, expected (n_gs, 3, 3)")
        self._positions.put(index, positions)
        if self._F is not None:
            self._F.put(index, F.reshape(len(F), 9))

    def finish(self, meta: dict) -> None:
        """The rollout is done: its ``meta`` goes into both files' footers, which are then
        closed and renamed on their threads. The frames handed over must be as many as
        ``meta["export_times"]`` lists."""
        times = meta.get("export_times")
        n_frames = len(times) if isinstance(times, list) else None
        for stream in self._streams:
            stream.finish(_meta_bytes(meta), n_frames=n_frames)

    def abort(self) -> None:
        """Stop both writes: no files, no temporary files (returns once they have stopped)."""
        for stream in self._streams:
            stream.abort()

    def wait(self) -> None:
        """Wait until both files are complete; raise the first failed write's error."""
        error = None
        for stream in self._streams:
            try:
                stream.wait()
            except Exception as exc:
                error = error or exc
        if error is not None:
            raise error


class BackgroundWriter:
    """Writes finished rollouts on background threads while the caller simulates the next.

    ``submit(path, rollout, F_path=None)`` hands a rollout over (positions, and its deformation
    gradients to ``F_path`` when given). At most ``workers`` rollouts are in flight, each on its
    own thread: ``submit`` first waits for the oldest write when that many are, so a failed
    write is raised by a later ``submit`` or by ``close`` (the context manager's exit), never
    lost. Files are written exactly as :func:`write_rollout` and :func:`write_deformation`
    write them, each atomically; with one worker in submission order. ``output`` (a job's
    output folder or file, or a list of them): removed when the block fails or is
    interrupted, once the writes under way have finished, so no partial output outlives the
    job (a workflow manager may remove it earlier, while a write is still under way). Several workers suit a
    batch of rollouts that finish together (a GPU's library job): their writes overlap.

    ``stream(path, F_path=None)`` instead gives a :class:`RolloutStream` for a rollout about
    to be simulated (hand it to :func:`run_rollouts`): its files are written while it runs,
    on threads of their own (outside the ``workers`` count), so only the last frames are
    written after the simulation. ``close`` also waits for every stream and raises the first
    failed one's error (a later ``stream`` or ``submit`` raises it once it has stopped); a
    stream never finished is aborted there (no file) and reported as an error. When the
    block fails, the unfinished streams are aborted before the output goes.
    """

    def __init__(self, workers: int = 1, *, output=None):
        from collections import deque
        from concurrent.futures import ThreadPoolExecutor

        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise InputError("BackgroundWriter", "workers", f"must be an integer >= 1, got {workers!r}")
        self.workers = workers
        outputs = [] if output is None else output if isinstance(output, (list, tuple)) else [output]
        self.outputs = [Path(o) for o in outputs]
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="rollout-writer")
        self._pending = deque()
        self._streams: list[RolloutStream] = []

    def _wait(self, keep: int = 0) -> None:
        """Wait for the oldest writes until at most ``keep`` are in flight (raising the first error)."""
        while len(self._pending) > keep:
            self._pending.popleft().result()

    def submit(self, path, rollout: Rollout, F_path=None) -> None:
        self._reap_streams()
        self._wait(self.workers - 1)

        def write():
            write_rollout(path, rollout)
            if F_path is not None:
                write_deformation(F_path, rollout)

        self._pending.append(self._pool.submit(write))

    def stream(self, path, F_path=None, *, group_rows: int = GROUP_ROWS) -> RolloutStream:
        """A :class:`RolloutStream` writing a rollout's positions to ``path`` (and its
        deformation gradients to ``F_path``) while it is simulated; raises the error of an
        earlier stream whose write failed."""
        self._reap_streams()
        stream = RolloutStream(path, F_path, group_rows=group_rows)
        self._streams.append(stream)
        return stream

    def _reap_streams(self) -> None:
        """Forget the streams whose writes have stopped, raising the first error of a finished one."""
        stopped = [s for s in self._streams if (s.finished or s.aborted) and s.done]
        self._streams = [s for s in self._streams if s not in stopped]
        for stream in stopped:
            if not stream.aborted:
                stream.wait()

    def _close_streams(self) -> None:
        """Wait for the finished streams, abort the others; raise the first error (an aborted
        stream, whose simulation failed and raised already, is none)."""
        error = None
        streams, self._streams = self._streams, []
        for stream in streams:
            try:
                if stream.aborted:
                    stream.abort()  # returns once its thread has stopped
                elif not stream.finished:
                    stream.abort()
                    raise InputError(stream.path, "frame", "the rollout's stream was never finished: no file written")
                else:
                    stream.wait()
            except Exception as exc:
                error = error or exc
        if error is not None:
            raise error

    def close(self) -> None:
        """Wait for every write and stream (raising the first error) and stop the threads."""
        try:
            self._wait()
        finally:
            try:
                self._close_streams()
            finally:
                self._pool.shutdown(wait=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        else:  # the caller failed: finish the write under way (atomic either way), keep the caller's error
            try:
                self.close()
            except Exception:
                pass
            remove_outputs(*self.outputs)  # no write can follow now: the job's output goes
        return False


def read_rollout_meta(path) -> dict:
    """The ``knockgs`` metadata of a rollout file (a JSON object with the fields that
    :func:`check_rollout_meta` compares)."""
    meta = read_metadata(path, META_KEY)
    if meta is None:
        raise InputError(path, "metadata.knockgs", "missing: not a KnockGS rollout")
    if not isinstance(meta, dict):
        raise InputError(path, "metadata.knockgs", "must be a JSON object")
    return meta


#: the largest |F_ij| a read deformation gradient may have: a hundredfold stretch is far beyond
#: any elastic response the simulator gives (its guards stop a run long before), while a
#: rendered Gaussian scaled by it would cover the whole image
F_MAX = 100.0


def _check_domain(path, meta: dict, positions: np.ndarray) -> None:
    """Positions [T, N, 3] inside the simulation domain [0, grid_lim]^3 of the metadata's
    solver settings (a rollout without them, not made by the simulator, is not judged)."""
    sim = meta.get("sim")
    lim = sim.get("grid_lim") if isinstance(sim, dict) else None
    if not isinstance(lim, (int, float)) or isinstance(lim, bool) or positions.size == 0:
        return
    lo, hi = float(positions.min()), float(positions.max())
    if lo < 0.0 or hi > float(lim):
        t, n, c = np.unravel_index(int(np.argmax((positions < 0) | (positions > lim))), positions.shape)
        raise InputError(path, "xyz"[c], f"particle {n} at frame {t} is at {float(positions[t, n, c]):.6g} m, outside "
                         f"the simulation domain [0, {float(lim):g}] of its metadata (sim.grid_lim)")


def _check_deformation(path, F: np.ndarray) -> None:
    """F [T, N, 3, 3]: det F > 0 (no inversion or reflection) and every |F_ij| <= F_MAX."""
    for t in range(F.shape[0]):
        f = F[t].astype(np.float64)
        big = np.abs(f).max(axis=(1, 2)) > F_MAX if f.size else np.zeros(0, bool)
        if big.any():
            n = int(np.argmax(big))
            raise InputError(path, "F", f"frame {t}, particle {n}: an entry of F is {float(np.abs(f[n]).max()):.6g}, "
                             f"beyond the plausible {F_MAX:g} (a stretch no simulated elastic response reaches)")
        det = np.linalg.det(f) if f.size else np.ones(0)
        if not (det > 0).all():
            n = int(np.argmin(det > 0))
            raise InputError(path, "F", f"frame {t}, particle {n}: det F = {float(det[n]):.6g}, not > 0 "
                             "(an inverted or reflected material element)")


def read_rollout(path) -> Rollout:
    """Read a rollout file: positions (T, N, 3) float32 and its metadata.

    The positions must agree with the metadata: N = n_gs + n_fill particles, particle ids
    0..N-1, T = the number of export times, and every position inside the simulation domain
    the metadata's solver settings give (``sim.grid_lim``).
    """
    meta = read_rollout_meta(path)
    positions = read_long_values(path, POSITION_COLUMNS, dense_ids=True)
    _check_domain(path, meta, positions)
    n = _meta_field(path, meta, "n_particles") if "n_gs" in meta or "n_fill" in meta else positions.shape[1]
    if positions.shape[1] != n:
        raise InputError(path, "particle", f"{positions.shape[1]} particles, the metadata says {n} (n_gs + n_fill)")
    times = meta.get("export_times")
    if isinstance(times, list) and positions.shape[0] != len(times):
        raise InputError(path, "frame", f"{positions.shape[0]} frames, the metadata lists {len(times)} export times")
    return Rollout(positions=positions, F=None, meta=meta)


def read_deformation(path, *, rollout: Rollout | None = None, rollout_path=None) -> np.ndarray:
    """Deformation gradients (T, n_gs, 3, 3) float32 from a file of :func:`write_deformation`:
    particle ids 0..n_gs-1, det F > 0 and every entry at most :data:`F_MAX` in magnitude.

    With ``rollout`` (read from ``rollout_path``), the file must come from the same run:
    its metadata's object, profile, contract hash, theta, probe and n_gs equal the
    rollout's (the fields both files carry), and it holds the rollout's frames.
    """
    F = read_long_values(path, F_COLUMNS, dense_ids=True)
    F = F.reshape(F.shape[0], F.shape[1], 3, 3)
    _check_deformation(path, F)
    if rollout is not None:
        m = rollout.meta
        keys = ("object", "profile", "contract_hash", "theta", "probe", "n_gs")
        check_rollout_meta(path, read_rollout_meta(path), partial=True,
                           **{k: _meta_field(rollout_path or "rollout", m, k) for k in keys if _has_field(m, k)})
        if F.shape[0] != rollout.positions.shape[0]:
            raise InputError(path, "frame", f"{F.shape[0]} frames; the rollout {rollout_path or ''} has "
                             f"{rollout.positions.shape[0]}")
    return F
