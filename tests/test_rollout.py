"""Rollouts of the object contracts: each asset simulated under its Probe A (ci profile),
the Parquet rollout format, and the `knockgs simulate` command."""

from __future__ import annotations

import dataclasses
import json
import time

import numpy as np
import pyarrow.parquet as pq
import pytest

from knockgs_core.assets import build_asset
from knockgs_core.cli import main as cli_main
from knockgs_core.contract import load_contract
from knockgs_core.descriptors import descriptor
from knockgs_core.errors import InputError
from knockgs_core.rollout import read_rollout, run_rollout, write_rollout


@pytest.mark.slow
@pytest.mark.parametrize("name", ["pillow", "ficus", "vasedeck"])
def test_each_asset_responds_to_its_probe_a(name, tmp_path):
    contract = load_contract(name, "ci")
    built = build_asset(contract)
    probe = contract.roles["calibration"]
    ro = run_rollout(contract, (1.0, 1.0), probe, particles=built.particles)
    X = ro.positions
    assert X.shape == (contract.probes[probe].export.n_frames, len(built.particles), 3)
    assert np.all(np.isfinite(X))
    disp = np.sqrt(((X - X[0]) ** 2).sum(-1).mean(-1))
    assert disp[-1] > 0 and disp.max() < 0.05  # a small, visible response
    # the probe pushes along its force: the centroid moves that way at first
    f = np.asarray(contract.probes[probe].force)
    axis = int(np.argmax(np.abs(f)))
    assert np.sign(X[3, :, axis].mean() - X[0, :, axis].mean()) == np.sign(f[axis])
    assert np.all(np.isfinite(descriptor(X, n_frames=X.shape[0])))
    meta = ro.meta
    assert meta["n_gs"] == built.particles.n_gs and meta["n_gs"] + meta["n_fill"] == len(built.particles)
    assert meta["contract_hash"] == contract.hash
    # total force is the same at every resolution: f x the particles the probe selects at the paper
    # profile (all of them for a global probe: probe_reference_particles; a box's selected_reference)
    reference = contract.probe_selected_reference.get(probe)
    if reference is None:
        assert contract.probes[probe].box is None
        reference = contract.probe_reference_particles * meta["probe_selected_count"] / len(built.particles)
    np.testing.assert_allclose(
        np.asarray(meta["total_probe_force"]) * meta["sim"]["dt"] / contract.probes[probe].duration,
        f * reference, rtol=1e-5)


def test_rollout_parquet_round_trip_and_metadata(tmp_path, pillow_ci):
    contract, built = pillow_ci
    ro = run_rollout(contract, (0.95, 1.35), "standard_x", particles=built.particles)
    path = tmp_path / "r.parquet"
    write_rollout(path, ro)
    table = pq.read_table(path)
    assert table.column_names == ["frame", "particle", "x", "y", "z"]
    assert str(table.schema.field("frame").type) == "int32" and str(table.schema.field("x").type) == "float"
    meta = json.loads(table.schema.metadata[b"knockgs"])
    for key in ("theta", "probe", "export_times", "n_gs", "n_fill", "total_probe_force", "contract_hash", "versions"):
        assert key in meta
    assert meta["theta"] == [0.95, 1.35]
    back = read_rollout(path)
    assert back.positions.tobytes() == ro.positions.tobytes()


def test_rollouts_are_bitwise_deterministic(pillow_ci):
    contract, built = pillow_ci
    ps = built.particles
    a = run_rollout(contract, (0.7, 1.2), "standard_x", particles=ps)
    b = run_rollout(contract, (0.7, 1.2), "standard_x", particles=ps)
    assert a.positions.tobytes() == b.positions.tobytes()


def test_reproducible_rollouts_are_the_default_up_to_rounding_and_say_so(pillow_ci):
    # the reproducible P2G (deterministic=True, for GPU runs) sums the same terms in another
    # order: the same motion to float rounding, the option and its sums recorded in the metadata
    contract, built = pillow_ci
    ps = built.particles
    a = run_rollout(contract, (0.7, 1.2), "standard_x", particles=ps)
    b = run_rollout(contract, (0.7, 1.2), "standard_x", particles=ps, deterministic=True)
    c = run_rollout(contract, (0.7, 1.2), "standard_x", particles=ps, deterministic=True)
    assert b.positions.tobytes() == c.positions.tobytes()
    disp = np.abs(a.positions - a.positions[0]).max()
    assert disp > 1e-3
    assert np.abs(b.positions - a.positions).max() < 1e-4 * disp
    assert b.meta["deterministic"] is True and "deterministic" not in a.meta
    assert b.meta["reproducible_sums"] == "fixed_point" and "reproducible_sums" not in a.meta
    # the setting is the call's own keyword, False unless given: no process-wide default
    e = run_rollout(contract, (0.7, 1.2), "standard_x", particles=ps, deterministic=False)
    assert e.positions.tobytes() == a.positions.tobytes() and "deterministic" not in e.meta
    for bad in ("yes", None, 1.5):
        with pytest.raises(InputError, match="deterministic") as exc:
            run_rollout(contract, (0.7, 1.2), "standard_x", particles=ps, deterministic=bad)
        assert exc.value.field == "deterministic"
    # a study's model holds the setting beside its device and hands it to every rollout
    from knockgs_core.discrepancy._forward import ForwardModel, ModelSpec

    fw = ForwardModel(contract, ps, deterministic=True)
    assert fw.rollout(ModelSpec((0.7, 1.2)), "standard_x").tobytes() == b.positions.tobytes()


def test_a_study_hands_the_reproducible_setting_to_its_solvers(monkeypatch):
    # the verification study's block rollouts, as every study: deterministic= next to device=,
    # given to each solver the study makes (False unless given)
    from knockgs_core.fem import VerificationSettings, mpm_block_rollout
    from knockgs_core.sim import MPMSolver

    made = []
    init = MPMSolver.__init__

    def recording(self, *args, **kwargs):
        init(self, *args, **kwargs)
        made.append(self.deterministic)

    monkeypatch.setattr(MPMSolver, "__init__", recording)
    s = VerificationSettings(n_grid=(16, 24), n_frames=3, fem_cells=2, fem_dt=0.025)
    mpm_block_rollout(16, s, device="cpu", deterministic=True)
    mpm_block_rollout(16, s, device="cpu")
    assert made == [True, False]


def test_stiffer_heavier_scaling_on_an_asset(pillow_ci):
    """On an asset: E and rho both x a divide the small-strain response by a."""
    contract, built = pillow_ci
    ps = built.particles
    a = run_rollout(contract, (0.5, 0.75), "standard_x", particles=ps).positions
    b = run_rollout(contract, (1.0, 1.5), "standard_x", particles=ps).positions
    da, db = a - a[0], b - b[0]
    rel = np.linalg.norm(2.0 * db - da) / np.linalg.norm(da)
    assert rel < 0.03, rel  # linear response up to the material's small nonlinearity
    # while a pure density change is not a rescaling (the time scale moves)
    c = run_rollout(contract, (0.5, 1.5), "standard_x", particles=ps).positions
    assert np.linalg.norm(2.0 * (c - c[0]) - da) / np.linalg.norm(da) > 0.1


def test_simulate_cli_writes_the_rollout_format(tmp_path, capsys):
    out = tmp_path / "ro.parquet"
    rc = cli_main(["simulate", "--object", "pillow", "--profile", "ci", "--theta", "1.05,1.1", "--probe", "standard_y",
                   "-o", str(out), "--quiet"])
    assert rc == 0 and out.exists()
    ro = read_rollout(out)
    assert ro.meta["probe"]["name"] == "standard_y" and ro.positions.shape[0] == 31
    assert "reproducible_sums" not in ro.meta
    # --deterministic: the fixed-point sums (a GPU's reproducible rollouts), recorded; the same
    # motion to float rounding
    det = tmp_path / "det.parquet"
    rc = cli_main(["simulate", "--object", "pillow", "--profile", "ci", "--theta", "1.05,1.1", "--probe", "standard_y",
                   "-o", str(det), "--quiet", "--deterministic"])
    assert rc == 0
    rd = read_rollout(det)
    assert rd.meta["deterministic"] is True and rd.meta["reproducible_sums"] == "fixed_point"
    disp = np.abs(ro.positions - ro.positions[0]).max()
    assert disp > 1e-3 and 0 < np.abs(rd.positions - ro.positions).max() < 1e-4 * disp


def test_simulate_cli_bad_input_is_a_message(tmp_path, capsys):
    rc = cli_main(["simulate", "--object", "pillow", "--profile", "ci", "--probe", "no_such_probe",
                   "-o", str(tmp_path / "x.parquet")])
    assert rc == 2
    assert "no_such_probe" in capsys.readouterr().err
    rc = cli_main(["simulate", "--object", "pillow", "--profile", "ci", "--theta=-1,1", "--probe", "standard_x",
                   "-o", str(tmp_path / "x.parquet")])
    assert rc == 2


def test_read_rollout_rejects_missing_rows(tmp_path):
    import pyarrow as pa

    t = pa.table({"frame": pa.array([0, 0, 1], pa.int32()), "particle": pa.array([0, 1, 0], pa.int32()),
                  "x": pa.array([0.0, 1, 2], pa.float32()), "y": pa.array([0.0, 1, 2], pa.float32()),
                  "z": pa.array([0.0, 1, 2], pa.float32())})
    t = t.replace_schema_metadata({b"knockgs": b"{}"})
    pq.write_table(t, tmp_path / "bad.parquet")
    with pytest.raises(InputError, match="bad.parquet.*frame"):
        read_rollout(tmp_path / "bad.parquet")


def _synthetic(n=500, t=4, seed=3):
    rng = np.random.default_rng(seed)
    X = rng.random((t, n, 3), dtype=np.float32)
    # a plausible deformation (det F > 0, as the readers require): the identity plus random bits
    F = np.eye(3, dtype=np.float32) + 0.1 * rng.random((t, n // 2, 3, 3), dtype=np.float32)
    from knockgs_core.rollout import Rollout

    return Rollout(positions=X, F=F, meta={"theta": [1.0, 1.0], "probe": "standard_y", "n_gs": n // 2, "n_fill": n - n // 2,
                                           "export_times": list(range(t))})


def test_the_long_format_encoding_round_trips_bit_for_bit(tmp_path):
    from knockgs_core.rollout import read_deformation, write_deformation

    ro = _synthetic()
    write_rollout(tmp_path / "r.parquet", ro)
    write_deformation(tmp_path / "r.F.parquet", ro)
    back = read_rollout(tmp_path / "r.parquet")
    assert np.array_equal(back.positions.view(np.uint32), ro.positions.view(np.uint32))
    assert np.array_equal(read_deformation(tmp_path / "r.F.parquet").view(np.uint32), ro.F.view(np.uint32))
    group = pq.ParquetFile(tmp_path / "r.parquet").metadata.row_group(0)
    col = {c.path_in_schema: c for c in (group.column(i) for i in range(group.num_columns))}
    assert "DELTA_BINARY_PACKED" in col["particle"].encodings and "BYTE_STREAM_SPLIT" in col["x"].encodings
    assert col["x"].compression.startswith("LZ4")


def test_the_background_writer_writes_the_same_bytes_and_raises_a_failed_write(tmp_path):
    from knockgs_core.rollout import BackgroundWriter, write_deformation

    a, b = _synthetic(seed=1), _synthetic(seed=2)
    write_rollout(tmp_path / "a_direct.parquet", a)
    write_deformation(tmp_path / "a_direct.F.parquet", a)
    with BackgroundWriter() as w:
        w.submit(tmp_path / "a.parquet", a, tmp_path / "a.F.parquet")
        w.submit(tmp_path / "b.parquet", b)
    assert (tmp_path / "a.parquet").read_bytes() == (tmp_path / "a_direct.parquet").read_bytes()
    assert (tmp_path / "a.F.parquet").read_bytes() == (tmp_path / "a_direct.F.parquet").read_bytes()
    assert np.array_equal(read_rollout(tmp_path / "b.parquet").positions, b.positions)
    assert not (tmp_path / "b.F.parquet").exists()
    # a write that fails (non-finite positions) is raised by the next submit, not lost
    bad = _synthetic(seed=4)
    bad.positions[0, 0, 0] = np.nan
    w = BackgroundWriter()
    w.submit(tmp_path / "bad.parquet", bad)
    with pytest.raises(InputError, match="non-finite"):
        w.submit(tmp_path / "c.parquet", a)
    w.close()
    # ... or by close, and it leaves no file behind
    w = BackgroundWriter()
    w.submit(tmp_path / "bad2.parquet", bad)
    with pytest.raises(InputError, match="non-finite"):
        w.close()
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("bad")) == []
    # several workers (a batch that finishes together): the same files, a failure still raised
    rollouts = {f"w{k}": _synthetic(seed=10 + k) for k in range(4)}
    with BackgroundWriter(workers=3) as w:
        for name, ro in rollouts.items():
            w.submit(tmp_path / f"{name}.parquet", ro, tmp_path / f"{name}.F.parquet")
    for name, ro in rollouts.items():
        write_rollout(tmp_path / f"{name}_direct.parquet", ro)
        assert (tmp_path / f"{name}.parquet").read_bytes() == (tmp_path / f"{name}_direct.parquet").read_bytes()
        assert (tmp_path / f"{name}.F.parquet").exists()
    w = BackgroundWriter(workers=2)
    w.submit(tmp_path / "bad3.parquet", bad)
    w.submit(tmp_path / "d.parquet", a)
    with pytest.raises(InputError, match="non-finite"):
        w.close()
    assert (tmp_path / "d.parquet").exists() and not (tmp_path / "bad3.parquet").exists()
    with pytest.raises(InputError, match="workers"):
        BackgroundWriter(workers=0)


def test_a_failed_job_leaves_no_output_once_its_writes_have_stopped(tmp_path):
    # a job's block fails (or is interrupted) after handing over a rollout: the writer finishes
    # that write, then removes the job's output folder (or file), so a resumed run redoes it
    from knockgs_core.rollout import BackgroundWriter

    a = _synthetic(seed=5)
    for output, target in [(tmp_path / "job", tmp_path / "job" / "r.parquet"), (tmp_path / "one.parquet",) * 2]:
        (tmp_path / "job").mkdir(exist_ok=True)
        with pytest.raises(KeyboardInterrupt):
            with BackgroundWriter(output=output) as w:
                w.submit(target, a)
                raise KeyboardInterrupt
        assert not output.exists()
    # a job with two output folders (positions, and deformation gradients apart) loses both
    (tmp_path / "pos").mkdir()
    (tmp_path / "F").mkdir()
    with pytest.raises(KeyboardInterrupt):
        with BackgroundWriter(output=[tmp_path / "pos", tmp_path / "F"]) as w:
            w.submit(tmp_path / "pos" / "r.parquet", a, tmp_path / "F" / "r.F.parquet")
            raise KeyboardInterrupt
    assert not (tmp_path / "pos").exists() and not (tmp_path / "F").exists()
    # a block that succeeds keeps its output
    with BackgroundWriter(output=tmp_path / "job") as w:
        w.submit(tmp_path / "job" / "r.parquet", a)
    assert (tmp_path / "job" / "r.parquet").exists()


def test_rollouts_simulated_together_equal_separate_rollouts_bit_for_bit(pillow_ci):
    from knockgs_core.rollout import run_rollouts

    contract, built = pillow_ci
    ps = built.particles
    runs = [((0.95, 1.35), "standard_x"), ((1.6, 0.8), "standard_x"), ((0.7, 1.1), "standard_y")]
    together = run_rollouts(contract, runs, particles=ps, export_F=True)
    for (theta, probe), ro in zip(runs, together):
        alone = run_rollout(contract, theta, probe, particles=ps, export_F=True)
        assert ro.positions.tobytes() == alone.positions.tobytes()
        assert ro.F.tobytes() == alone.F.tobytes()
        assert ro.meta["theta"] == list(theta) and ro.meta["probe"] == alone.meta["probe"]
        assert ro.meta["stats"] == alone.meta["stats"] and ro.meta["simulated_with"] == 3


def test_rollouts_simulated_together_count_their_cells_once(pillow_ci, monkeypatch):
    # a batch's runs share one particle set: its per-cell volumes and its cell crowding are
    # counted once for the batch, not once a model and a solver (the same values: the test above
    # holds the bits)
    from knockgs_core.rollout import run_rollouts
    from knockgs_core.sim import _model, _solver

    contract, built = pillow_ci
    calls = {"volumes": 0, "crowding": 0}

    def counted(name, inner):
        def wrapper(*args, **kwargs):
            calls[name] += 1
            return inner(*args, **kwargs)
        return wrapper

    volumes = counted("volumes", _model.particle_volumes)
    monkeypatch.setattr(_model, "particle_volumes", volumes)  # build_model's
    monkeypatch.setattr("knockgs_core.sim.particle_volumes", volumes)  # run_rollouts' (imported where it runs)
    monkeypatch.setattr(_solver, "cell_crowding", counted("crowding", _model.cell_crowding))  # MPMSolver's
    runs = [((0.95, 1.35), "standard_x"), ((1.6, 0.8), "standard_x"), ((0.7, 1.1), "standard_y")]
    run_rollouts(contract, runs, particles=dataclasses.replace(built.particles, volumes=None))
    assert calls == {"volumes": 1, "crowding": 1}


def test_the_cell_orders_argsort_is_the_stable_argsort():
    # the keys with the row index in their low bits, sorted: NumPy's stable argsort, ties in row
    # order, where the two fit in 63 bits, and the stable argsort itself where they do not
    from knockgs_core.rollout import _stable_argsort

    rng = np.random.default_rng(5)
    cases = [np.zeros(0, np.int64), np.array([7]), np.array([3, 3, 1, 2, 3, 1, 0, 0]), rng.integers(0, 4, 5000),
             rng.integers(0, 10**6, 200_000), np.arange(1000)[::-1].copy(), np.array([2**60, 1, 2**60, 0])]
    for key in cases:
        np.testing.assert_array_equal(_stable_argsort(key.astype(np.int64)), np.argsort(key, kind="stable"))


def test_rollouts_simulated_in_cell_order_come_back_in_the_asset_order(pillow_ci):
    # the GPU's order (particles sorted by cell within the Gaussian-associated rows and within
    # the fill), run on the CPU: the same motion up to float rounding, returned row for row in
    # the particle set's order (F too); the CPU's default keeps the asset order, bit for bit
    from knockgs_core.rollout import cell_order, run_rollouts

    contract, built = pillow_ci
    ps = built.particles
    perm = cell_order(ps, n_grid=contract.sim.n_grid, grid_lim=contract.sim.grid_lim)
    assert sorted(perm[: ps.n_gs]) == list(range(ps.n_gs)) and not np.array_equal(perm, np.arange(len(perm)))
    # sorted by stencil base cell (the key the GPU's P2G groups by), x-major, in each group
    n = contract.sim.n_grid
    base = np.floor(ps.positions[perm].astype(np.float64) / contract.sim.dx - 0.5).astype(np.int64)
    key = (base[:, 0] * n + base[:, 1]) * n + base[:, 2]
    assert np.all(np.diff(key[: ps.n_gs]) >= 0) and np.all(np.diff(key[ps.n_gs:]) >= 0)
    runs = [((0.95, 1.35), "standard_x")]
    (asset,) = run_rollouts(contract, runs, particles=ps, export_F=True)
    (cell,) = run_rollouts(contract, runs, particles=ps, export_F=True, particle_order="cell")
    (auto,) = run_rollouts(contract, runs, particles=ps, export_F=True, particle_order="auto")
    assert auto.positions.tobytes() == asset.positions.tobytes() and "particle_order" not in auto.meta
    assert cell.meta["particle_order"] == "cell"
    np.testing.assert_array_equal(cell.positions[0], ps.positions)
    U = asset.positions - asset.positions[0]
    scale = np.sqrt((U.astype(np.float64) ** 2).sum(-1).mean())
    assert scale > 1e-4
    assert np.sqrt(((cell.positions - asset.positions).astype(np.float64) ** 2).sum(-1).mean()) < 1e-4 * scale
    np.testing.assert_allclose(cell.F, asset.F, atol=1e-4)
    with pytest.raises(InputError, match="particle_order"):
        run_rollouts(contract, runs, particles=ps, particle_order="morton")


def test_rollouts_simulated_together_refuse_mixed_schedules_and_stop_a_blow_up(pillow_ci):
    from knockgs_core.errors import SimulationError
    from knockgs_core.rollout import run_rollouts

    contract, built = pillow_ci
    ps = built.particles
    with pytest.raises(InputError, match="one export schedule"):
        _mixed(contract, ps)
    # a time step far beyond the stable one: the guard stops the batch with a message
    with pytest.raises(SimulationError, match="CFL|outran|non-finite|left the simulation"):
        run_rollouts(contract, [((1.0, 1.0), "standard_x"), ((5.0, 0.2), "standard_x")], particles=ps,
                     sim_overrides={"dt": 0.02})


def _mixed(contract, ps):
    """Two probes whose export schedules differ (the second one's frames halved)."""
    import dataclasses

    from knockgs_core.rollout import run_rollouts

    pa_ = contract.probes["standard_x"]
    other = dataclasses.replace(pa_, export=dataclasses.replace(pa_.export, n_frames=pa_.export.n_frames // 2))
    probes = dict(contract.probes, other=other)
    c2 = dataclasses.replace(contract, probes=probes)
    return run_rollouts(c2, [((1.0, 1.0), "standard_x"), ((1.0, 1.0), "other")], particles=ps)


def test_batches_group_consecutive_runs_of_one_schedule_only_when_together():
    from knockgs_core.rollout import batches

    runs = [{"probe": "a"}, {"probe": "a"}, {"probe": "b"}, {"probe": "a"}]
    key = lambda run: run["probe"]  # noqa: E731
    assert [[i for i, _ in b] for b in batches(runs, key, together=True)] == [[0, 1], [2], [3]]
    assert [[i for i, _ in b] for b in batches(runs, key, together=False)] == [[0], [1], [2], [3]]
    assert batches([], key, together=True) == []


def _decoded(path, F_path=None):
    """What the readers give of a rollout's files: positions, metadata and F, and the raw tables."""
    from knockgs_core.rollout import read_deformation

    ro = read_rollout(path)
    F = None if F_path is None else read_deformation(F_path, rollout=ro, rollout_path=path)
    tables = [pq.read_table(p) for p in (path, F_path) if p is not None]
    return ro.positions.tobytes(), ro.meta, None if F is None else F.tobytes(), tables


def test_rollouts_written_while_simulated_decode_as_the_finished_rollouts_files(pillow_ci, tmp_path):
    # the GPU library job's way (runs in lockstep, a stream each; F for one, row groups of one
    # frame and of the default size) and the one-at-a-time CPU way (no F, row groups of 3
    # frames and a last one of 1): the files decode to exactly what write_rollout /
    # write_deformation write of the returned rollouts
    from knockgs_core.rollout import RolloutStream, run_rollouts, write_deformation

    contract, built = pillow_ci
    ps = built.particles
    runs = [((0.95, 1.35), "standard_x"), ((1.6, 0.8), "standard_y")]
    streams = [RolloutStream(tmp_path / "a.parquet", tmp_path / "a.F.parquet", group_rows=1),
               RolloutStream(tmp_path / "b.parquet")]
    together = run_rollouts(contract, runs, particles=ps, export_F=True, streams=streams)
    alone = run_rollout(contract, (0.7, 1.2), "standard_x", particles=ps,
                        stream=(single := RolloutStream(tmp_path / "c.parquet", group_rows=5000)))
    for stream in (*streams, single):
        stream.wait()
    for name, ro, F in (("a", together[0], True), ("b", together[1], False), ("c", alone, False)):
        write_rollout(tmp_path / f"{name}_whole.parquet", ro)
        if F:
            write_deformation(tmp_path / f"{name}_whole.F.parquet", ro)
        F_paths = (tmp_path / f"{name}.F.parquet", tmp_path / f"{name}_whole.F.parquet") if F else (None, None)
        streamed = _decoded(tmp_path / f"{name}.parquet", F_paths[0])
        whole = _decoded(tmp_path / f"{name}_whole.parquet", F_paths[1])
        assert streamed[:3] == whole[:3] and streamed[0] == ro.positions.tobytes() and streamed[1] == ro.meta
        assert all(s.equals(w) for s, w in zip(streamed[3], whole[3]))  # rows in the writers' order
    assert together[0].F is not None and not (tmp_path / "b.F.parquet").exists()
    n_frames = contract.probes["standard_x"].export.n_frames
    assert pq.ParquetFile(tmp_path / "a.parquet").metadata.num_row_groups == n_frames  # written frame by frame
    assert pq.ParquetFile(tmp_path / "a.F.parquet").metadata.num_row_groups == n_frames
    per_group = -(-5000 // len(ps.positions))  # frames of c's row groups, the last one shorter
    assert pq.ParquetFile(tmp_path / "c.parquet").metadata.num_row_groups == -(-n_frames // per_group)
    assert n_frames % per_group != 0
    # and the simulation is the one without streams, bit for bit
    assert alone.positions.tobytes() == run_rollout(contract, (0.7, 1.2), "standard_x", particles=ps).positions.tobytes()
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]


@pytest.mark.parametrize("failure", ["interrupt", "blow-up", "bad input"])
def test_a_rollout_that_fails_while_its_files_are_written_leaves_nothing(pillow_ci, tmp_path, failure):
    # an interrupt at frame 3 (the temporary files hold frames already), the guard stopping a
    # blow-up, a refused input: every stream of the batch aborted, no file, no temporary file
    from knockgs_core.errors import SimulationError
    from knockgs_core.rollout import RolloutStream, run_rollouts

    contract, built = pillow_ci
    seen = []

    def progress(run, frame, n_frames, stats):
        seen.append(frame)
        if frame == 3 and failure == "interrupt":
            deadline = time.monotonic() + 10
            while not any(".tmp" in p.name for p in tmp_path.iterdir()) and time.monotonic() < deadline:
                time.sleep(0.01)  # the writer threads have the frames' row groups in their temporary files
            seen.append(sorted(p.name for p in tmp_path.iterdir()))
            raise KeyboardInterrupt

    runs = {"interrupt": [((1.0, 1.0), "standard_x")], "blow-up": [((1.0, 1.0), "standard_x"), ((5.0, 0.2), "standard_x")],
            "bad input": [((1.0, 1.0), "standard_x"), ((-1.0, 1.0), "standard_x")]}[failure]
    streams = [RolloutStream(tmp_path / f"{k}.parquet", tmp_path / f"{k}.F.parquet", group_rows=1) for k in range(len(runs))]
    error = {"interrupt": KeyboardInterrupt, "blow-up": SimulationError, "bad input": InputError}[failure]
    with pytest.raises(error, match=None if failure == "interrupt" else "CFL|outran|non-finite|left|theta"):
        run_rollouts(contract, runs, particles=built.particles, export_F=True, streams=streams, progress=progress,
                     sim_overrides={"dt": 0.02} if failure == "blow-up" else None)
    assert list(tmp_path.iterdir()) == []
    assert all(s.aborted and s.done for s in streams)
    if failure == "interrupt":
        assert any(".tmp" in name for name in seen[-1])  # it failed midway through the write
    elif failure == "blow-up":
        assert streams[0].frames >= 1  # the first run had handed frames over before the guard stopped the batch


def test_a_job_writing_its_rollouts_as_they_run_keeps_them_or_loses_them_whole(pillow_ci, tmp_path):
    # BackgroundWriter.stream, as the rollout job uses it: files complete at the block's end;
    # a failed block (an interrupt during the second batch) removes the job's folder; a stream
    # never finished (nor aborted) is an error at the end, with no file
    from knockgs_core.rollout import BackgroundWriter, run_rollouts

    contract, built = pillow_ci
    ps = built.particles
    job = tmp_path / "job"
    with BackgroundWriter(output=job) as writer:
        (ro,) = run_rollouts(contract, [((0.95, 1.35), "standard_x")], particles=ps,
                             streams=[writer.stream(job / "r.parquet")])
    assert read_rollout(job / "r.parquet").positions.tobytes() == ro.positions.tobytes()

    def interrupt(run, frame, n_frames, stats):
        if frame == 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        with BackgroundWriter(output=job) as writer:
            run_rollouts(contract, [((0.95, 1.35), "standard_x")], particles=ps, streams=[writer.stream(job / "a.parquet")])
            run_rollouts(contract, [((1.2, 1.0), "standard_x")], particles=ps, streams=[writer.stream(job / "b.parquet")],
                         progress=interrupt)
    assert not job.exists()
    writer = BackgroundWriter()
    stream = writer.stream(tmp_path / "never.parquet")
    stream.frame(0, ro.positions[0])
    with pytest.raises(InputError, match="never.parquet.*never finished"):
        writer.close()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(InputError, match="export_F"):
        run_rollout(contract, (1.0, 1.0), "standard_x", particles=ps,
                    stream=writer.stream(tmp_path / "r.parquet", tmp_path / "r.F.parquet"))
    assert list(tmp_path.iterdir()) == []
