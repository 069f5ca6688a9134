"""Hostile and mismatched inputs to the ``knockgs`` commands (issue 17), one class per section.

Every case runs the command in-process and asserts the refusal: exit code 2 (130 for an
interrupt), one line on stderr naming the file and the field, no traceback, no file of
the shared inputs or of the case's own folder changed, created or left half-written
(no temporary file). The inputs (ci-profile assets, rollouts, a measured case) are built
once per module.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from knockgs_core.cli import main

ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- fixtures and the check


def _ok(*args) -> None:
    assert main([str(a) for a in args]) == 0, args


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    """ci-profile Pillow asset (normalized PLY, scene, particles with their contract), a
    Vasedeck particle set, Pillow rollouts under standard_x and standard_y (with F), a
    Vasedeck rollout, a measured Pillow case, and a copy of the configuration."""
    S = tmp_path_factory.mktemp("shared")
    shutil.copytree(ROOT / "config", S / "config", ignore=shutil.ignore_patterns("*.yaml.bak"))
    _ok("asset", "make", "pillow", "--profile", "ci", "--normalized", "-o", S / "pillow.ply",
        "--particles", S / "pillow.particles.npz")
    _ok("asset", "make", "vasedeck", "--profile", "ci", "--normalized", "-o", S / "vasedeck.ply",
        "--particles", S / "vasedeck.particles.npz")
    for probe in ("standard_x", "standard_y"):
        _ok("simulate", "--object", "pillow", "--profile", "ci", "--probe", probe, "--particles", S / "pillow.particles.npz",
            "-o", S / f"{probe}.parquet", "--export-F", S / f"{probe}.F.parquet", "--quiet")
    _ok("simulate", "--object", "vasedeck", "--profile", "ci", "--probe", "standard_x", "--particles",
        S / "vasedeck.particles.npz", "-o", S / "vasedeck.parquet", "--export-F", S / "vasedeck.F.parquet", "--quiet")
    _ok("discrepancy", "make-case", "--object", "pillow", "--profile", "ci", "--particles", S / "pillow.particles.npz",
        "--case", "c1", "--planted", "none", "--measured-dir", S / "meas", "--truth-dir", S / "truth")
    return S


def _snapshot(*folders: Path) -> dict:
    out = {}
    for folder in folders:
        for p in sorted(Path(folder).rglob("*")):
            if p.is_symlink() or not p.exists():
                out[str(p)] = ("link", os.readlink(p) if p.is_symlink() else None)
            elif p.is_file():
                st = p.stat()
                out[str(p)] = (hashlib.sha256(p.read_bytes()).hexdigest(), st.st_mtime_ns)
            else:
                out[str(p)] = ("dir" if p.is_dir() else "other",)
    return out


class Refusal:
    """Run a command and check the refusal (see the module docstring)."""

    def __init__(self, shared: Path, tmp: Path, capsys):
        self.shared, self.tmp, self.capsys = shared, tmp, capsys

    def __call__(self, *args, names=(), code: int = 2) -> str:
        before = _snapshot(self.shared, self.tmp)
        try:
            rc = main([str(a) for a in args])
        except SystemExit as exc:  # argparse usage errors
            rc = exc.code
        err = self.capsys.readouterr().err
        assert rc == code, err
        lines = [line for line in err.splitlines() if line.strip()]
        assert len(lines) == 1, err
        line = lines[0]
        assert line.startswith("knockgs ") and "Traceback" not in err
        assert "error: " in line or (code == 130 and line.endswith("interrupted"))
        for name in names:
            assert str(name) in line, (name, line)
        assert _snapshot(self.shared, self.tmp) == before, "a file changed, appeared or was left behind"
        return line


@pytest.fixture
def refuse(shared, tmp_path, capsys):
    return Refusal(shared, tmp_path, capsys)


def _sim(S, *extra, obj="pillow", probe="standard_x"):
    return ("simulate", "--object", obj, "--profile", "ci", "--probe", probe, "--quiet", *extra)


def _run(S, *extra, measured=None, out=None):
    return ("discrepancy", "run", "--object", "pillow", "--profile", "ci", "--particles", S / "pillow.particles.npz",
            "--measured", measured or S / "meas/measured_calib.parquet", "-o", out or S / "never_written", "--quiet", *extra)


def _measured_with_meta(S, dest: Path, **meta) -> Path:
    """The measured calibration file of the shared case with its metadata replaced."""
    t = pq.read_table(S / "meas/measured_calib.parquet")
    md = json.loads(t.schema.metadata[b"knockgs_measurement"])
    md.update(meta)
    pq.write_table(t.replace_schema_metadata({b"knockgs_measurement": json.dumps(md).encode()}), dest)
    return dest


# --------------------------------------------------------------------------- 1. outputs that destroy inputs


def test_simulate_output_is_its_contract(shared, refuse):
    contract = shared / "config/objects/pillow.yaml"
    refuse("simulate", "--object", contract, "--profile", "ci", "--probe", "standard_x", "-o", contract,
           names=("pillow.yaml", "--output", "--object"))


def test_simulate_output_is_its_F_file(shared, refuse, tmp_path):
    refuse(*_sim(shared, "-o", tmp_path / "x.parquet", "--export-F", tmp_path / "x.parquet"), names=("x.parquet", "--export-F"))


def test_simulate_output_is_its_particles(shared, refuse):
    p = shared / "pillow.particles.npz"
    refuse(*_sim(shared, "--particles", p, "-o", p), names=("pillow.particles.npz", "--particles"))


def test_simulate_output_is_a_symbolic_link_to_its_particles(shared, refuse, tmp_path):
    link = tmp_path / "link.parquet"
    link.symlink_to(shared / "pillow.particles.npz")
    refuse(*_sim(shared, "--particles", shared / "pillow.particles.npz", "-o", link), names=("link.parquet", "--particles"))


def test_simulate_output_is_the_candidates_table(shared, refuse):
    contract = shared / "config/objects/pillow.yaml"
    refuse("simulate", "--object", contract, "--profile", "ci", "--probe", "standard_x", "-o", shared / "config/candidates.csv",
           names=("candidates.csv", "--output"))


def test_simulate_output_is_a_directory(shared, refuse, tmp_path):
    (tmp_path / "out").mkdir()
    refuse(*_sim(shared, "-o", tmp_path / "out"), names=("out", "directory"))


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_simulate_output_is_a_fifo(shared, refuse, tmp_path):
    os.mkfifo(tmp_path / "fifo")
    refuse(*_sim(shared, "-o", tmp_path / "fifo"), names=("fifo", "not a regular file"))


@pytest.mark.skipif(not os.path.exists("/dev/null"), reason="needs a device node")
def test_simulate_output_is_a_link_to_a_device(shared, refuse, tmp_path):
    (tmp_path / "dev.parquet").symlink_to("/dev/null")
    refuse(*_sim(shared, "-o", tmp_path / "dev.parquet"), names=("dev.parquet", "not a regular file"))


def test_simulate_output_below_a_file(shared, refuse, tmp_path):
    (tmp_path / "plain.txt").write_text("x")
    refuse(*_sim(shared, "-o", tmp_path / "plain.txt" / "r.parquet"), names=("r.parquet", "plain.txt", "not a folder"))


def test_asset_make_output_is_its_particles(shared, refuse, tmp_path):
    refuse("asset", "make", "pillow", "--profile", "ci", "-o", tmp_path / "X.ply", "--particles", tmp_path / "X.ply",
           names=("X.ply", "--particles"))


def test_asset_make_particles_is_its_scene_file(shared, refuse, tmp_path):
    refuse("asset", "make", "pillow", "--profile", "ci", "--normalized", "-o", tmp_path / "X.ply",
           "--particles", tmp_path / "X.scene.npz", names=("X.scene.npz", "scene file"))


def test_asset_make_output_is_its_contract(shared, refuse):
    contract = shared / "config/objects/vasedeck.yaml"
    refuse("asset", "make", contract, "--profile", "ci", "-o", contract, names=("vasedeck.yaml", "--object"))


def test_asset_figure_output_is_a_directory(shared, refuse, tmp_path):
    (tmp_path / "fig.png").mkdir()
    refuse("asset", "figure", "pillow", "--profile", "ci", "-o", tmp_path / "fig.png", names=("fig.png", "directory"))


FICUS = ROOT / "tests/data/knockgs-ficus"


def test_calibrate_output_is_its_queries(shared, refuse, tmp_path):
    q = tmp_path / "Q.csv"
    shutil.copy(FICUS / "queries.csv", q)
    refuse("calibrate", "--library", FICUS / "library.csv", "--queries", q, "--method", "knn", "--output", q,
           names=("Q.csv", "--queries"))


def test_calibrate_output_is_a_directory(shared, refuse, tmp_path):
    (tmp_path / "est.json").mkdir()
    refuse("calibrate", "--library", FICUS / "library.csv", "--queries", FICUS / "queries.csv", "--method", "knn",
           "--output", tmp_path / "est.json", names=("est.json", "directory"))


def test_render_output_folder_is_a_file(shared, refuse, tmp_path):
    (tmp_path / "frames").write_text("not a folder")
    refuse("render", "ply", "--asset", shared / "pillow.ply", "--rollout", shared / "standard_x.parquet",
           "-o", tmp_path / "frames", names=("frames", "--output", "not a folder"))


def test_render_would_overwrite_its_asset_in_the_output_folder(shared, refuse, tmp_path):
    asset = tmp_path / "frame_0000.ply"
    shutil.copy(shared / "pillow.ply", asset)
    shutil.copy(shared / "pillow.scene.npz", tmp_path / "frame_0000.scene.npz")
    refuse("render", "ply", "--asset", asset, "--rollout", shared / "standard_x.parquet", "-o", tmp_path,
           names=("frame_0000.ply", "--asset"))


def test_discrepancy_run_output_is_an_existing_file_refused_before_the_loop(shared, refuse, tmp_path, monkeypatch):
    import knockgs_core.discrepancy._files as files

    monkeypatch.setattr(files, "run_discrepancy", lambda *a, **k: pytest.fail("the loop ran before the output check"))
    (tmp_path / "report").write_text("an existing file")
    refuse(*_run(shared, out=tmp_path / "report"), names=("report", "--output", "not a folder"))


def test_discrepancy_make_case_measured_and_truth_in_one_folder(shared, refuse, tmp_path):
    refuse("discrepancy", "make-case", "--object", "pillow", "--profile", "ci", "--case", "c", "--planted", "none",
           "--particles", shared / "pillow.particles.npz", "--measured-dir", tmp_path / "d", "--truth-dir", tmp_path / "d",
           names=("--truth-dir", "--measured-dir"))


def test_discrepancy_evaluate_output_is_its_truth(shared, refuse, tmp_path):
    refuse("discrepancy", "evaluate", "--run-dir", tmp_path, "--truth-dir", shared / "truth",
           "-o", shared / "truth/truth.json", names=("truth.json", "--truth-dir"))


def test_discrepancy_table_csv_is_a_row(shared, refuse, tmp_path):
    row = tmp_path / "row.json"
    row.write_text("{}")
    refuse("discrepancy", "table", row, "--csv", row, "--md", tmp_path / "t.md", names=("row.json", "--csv"))


def _disk_full(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_disk_full_while_writing_a_ply_leaves_the_previous_file(shared, refuse, tmp_path, monkeypatch):
    import plyfile

    out = tmp_path / "pillow_source.ply"
    out.write_bytes(b"previous")
    monkeypatch.setattr(plyfile.PlyData, "write", _disk_full)
    line = refuse("asset", "make", "pillow", "--profile", "ci", "-o", out, names=("pillow_source.ply", "No space left"))
    assert "unchanged" in line


def test_disk_full_while_writing_a_rollout_leaves_the_previous_file(shared, refuse, tmp_path, monkeypatch):
    out = tmp_path / "r.parquet"
    out.write_bytes(b"previous")
    monkeypatch.setattr(pq, "write_table", _disk_full)
    monkeypatch.setattr(pq.ParquetWriter, "write_table", _disk_full)  # the frames written as the rollout runs
    refuse(*_sim(shared, "--particles", shared / "pillow.particles.npz", "-o", out), names=("r.parquet", "No space left"))


def test_permission_denied_while_writing_names_the_file(shared, refuse, tmp_path, monkeypatch):
    import knockgs_core.io._files as io_mod

    def deny(src, dst):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), dst)

    monkeypatch.setattr(io_mod.os, "replace", deny)
    refuse("calibrate", "--library", FICUS / "library.csv", "--queries", FICUS / "queries.csv", "--method", "knn",
           "--output", tmp_path / "est.json", names=("est.json", "Permission denied"))


# --------------------------------------------------------------------------- 2. mismatched inputs


def test_simulate_with_another_objects_particles(shared, refuse, tmp_path):
    refuse(*_sim(shared, "--particles", shared / "vasedeck.particles.npz", "-o", tmp_path / "r.parquet"),
           names=("vasedeck.particles.npz", "meta.object", "vasedeck", "pillow"))


def test_simulate_with_another_profiles_particles(shared, refuse, tmp_path):
    refuse("simulate", "--object", "pillow", "--profile", "default", "--probe", "standard_x", "--quiet",
           "--particles", shared / "pillow.particles.npz", "-o", tmp_path / "r.parquet",
           names=("pillow.particles.npz", "meta.profile"))


def test_simulate_with_another_objects_regions(shared, refuse, tmp_path):
    refuse(*_sim(shared, "--particles", shared / "pillow.particles.npz", "-o", tmp_path / "r.parquet", obj="ficus"),
           names=("pillow.particles.npz", "meta."))


def test_render_F_of_another_probe(shared, refuse, tmp_path):
    refuse("render", "ply", "--asset", shared / "pillow.ply", "--rollout", shared / "standard_x.parquet",
           "--deformation", shared / "standard_y.F.parquet", "-o", tmp_path / "ply",
           names=("standard_y.F.parquet", "metadata.knockgs.probe", "standard_y", "standard_x"))


def test_render_frames_with_another_objects_camera(shared, refuse, tmp_path):
    refuse("render", "frames", "--object", "vasedeck", "--profile", "ci", "--asset", shared / "pillow.ply",
           "--rollout", shared / "standard_x.parquet", "-o", tmp_path / "png",
           names=("standard_x.parquet", "metadata.knockgs.object", "vasedeck"))


def test_render_frames_with_another_profile(shared, refuse, tmp_path):
    refuse("render", "frames", "--object", "pillow", "--profile", "default", "--asset", shared / "pillow.ply",
           "--rollout", shared / "standard_x.parquet", "-o", tmp_path / "png",
           names=("standard_x.parquet", "metadata.knockgs.profile"))


def test_render_rollout_of_another_asset(shared, refuse, tmp_path):
    refuse("render", "ply", "--asset", shared / "pillow.ply", "--rollout", shared / "vasedeck.parquet",
           "-o", tmp_path / "ply", names=("vasedeck.F.parquet", "F"))


def test_discrepancy_rollout_as_a_measurement(shared, refuse):
    refuse(*_run(shared, measured=shared / "standard_x.parquet"), names=("standard_x.parquet", "metadata.knockgs", "rollout"))


def test_discrepancy_another_objects_rollout_as_a_measurement(shared, refuse):
    refuse(*_run(shared, measured=shared / "vasedeck.parquet"), names=("vasedeck.parquet", "metadata.knockgs"))


def test_discrepancy_measurement_of_another_object(shared, refuse, tmp_path):
    m = _measured_with_meta(shared, tmp_path / "m.parquet", object="vasedeck")
    refuse(*_run(shared, measured=m), names=("m.parquet", "metadata.object", "vasedeck"))


def test_discrepancy_measurement_of_another_profile(shared, refuse, tmp_path):
    m = _measured_with_meta(shared, tmp_path / "m.parquet", profile="paper")
    refuse(*_run(shared, measured=m), names=("m.parquet", "metadata.profile", "paper"))


def test_discrepancy_measurement_of_another_probe(shared, refuse):
    refuse(*_run(shared, "--probe", "strong_x"), names=("measured_calib.parquet", "metadata.probe", "strong_x"))


def test_discrepancy_heldout_of_another_probe(shared, refuse):
    held = shared / "meas/measured_heldout.parquet"  # metadata: standard_y
    refuse(*_run(shared, "--heldout-probe", "strong_x", "--heldout-measured", f"strong_x={held}"),
           names=("measured_heldout.parquet", "metadata.probe", "standard_y", "strong_x"))


def test_discrepancy_heldout_of_another_object(shared, refuse, tmp_path):
    m = _measured_with_meta(shared, tmp_path / "h.parquet", object="ficus", probe="standard_y")
    refuse(*_run(shared, "--heldout-probe", "standard_y", "--heldout-measured", f"standard_y={m}"),
           names=("h.parquet", "metadata.object", "ficus"))


def test_discrepancy_library_rollout_of_another_probe(shared, refuse):
    refuse(*_run(shared, "--library-rollout", shared / "standard_y.parquet"),
           names=("standard_y.parquet", "metadata.knockgs.probe"))


def test_discrepancy_library_rollout_of_another_object(shared, refuse):
    refuse(*_run(shared, "--library-rollout", shared / "vasedeck.parquet"), names=("vasedeck.parquet", "metadata.knockgs.object"))


def test_discrepancy_make_case_with_another_objects_particles(shared, refuse, tmp_path):
    refuse("discrepancy", "make-case", "--object", "pillow", "--profile", "ci", "--case", "c", "--planted", "none",
           "--particles", shared / "vasedeck.particles.npz", "--measured-dir", tmp_path / "m", "--truth-dir", tmp_path / "t",
           names=("vasedeck.particles.npz", "meta.object"))


# --------------------------------------------------------------------------- 3. values that mean nothing


@pytest.mark.parametrize("noise", [-1, float("nan"), "loud"])
def test_measurement_noise_std_must_mean_something(shared, refuse, tmp_path, noise):
    m = _measured_with_meta(shared, tmp_path / "m.parquet", noise_std=noise)
    refuse(*_run(shared, measured=m), names=("m.parquet", "metadata.noise_std"))


def test_measurement_fractional_frame(shared, refuse, tmp_path):
    t = pq.read_table(shared / "meas/measured_calib.parquet").to_pandas()
    t["frame"] = t["frame"].astype(float)
    t.loc[t["frame"] == 7, "frame"] = 7.5
    t.to_csv(tmp_path / "m.csv", index=False)
    refuse(*_run(shared, measured=tmp_path / "m.csv"), names=("m.csv", "'frame'", "7.5"))


def test_measurement_text_coordinates(shared, refuse, tmp_path):
    t = pq.read_table(shared / "meas/measured_calib.parquet").to_pandas()
    t["x"] = t["x"].astype(str)
    t.loc[3, "x"] = "left"
    t.to_csv(tmp_path / "m.csv", index=False)
    refuse(*_run(shared, measured=tmp_path / "m.csv"), names=("m.csv", "'x'"))


def test_negative_max_effects(shared, refuse):
    refuse(*_run(shared, "--max-effects", "-1"), names=("--max-effects", ">= 0"))


def _contract_with(shared, tmp_path, old: str, new: str) -> Path:
    text = (shared / "config/objects/pillow.yaml").read_text()
    assert old in text
    folder = tmp_path / "objects"
    folder.mkdir(exist_ok=True)
    (folder / "pillow.yaml").write_text(text.replace(old, new, 1))
    return folder / "pillow.yaml"


@pytest.mark.parametrize("old, new, field", [
    ("E: 1.0e4", "E: .nan", "materials.base.E"),
    ("nu: 0.3", "nu: .nan", "materials.base.nu"),
    ("rho: 2000.0", "rho: .NaN", "materials.base.rho"),
    ("E: 1.0e4", "E: .inf", "materials.base.E"),
    ("rho: 2000.0", "rho: -.inf", "materials.base.rho"),
])
def test_contract_material_not_finite(shared, refuse, tmp_path, old, new, field):
    c = _contract_with(shared, tmp_path, old, new)
    refuse("asset", "summary", c, "--profile", "ci", names=("pillow.yaml", field))


def test_contract_probe_force_nan(shared, refuse, tmp_path):
    text = (shared / "config/objects/pillow.yaml").read_text()
    i = text.index("force:", text.index("standard_x:"))
    j = text.index("]", i)
    folder = tmp_path / "objects"
    folder.mkdir()
    (folder / "pillow.yaml").write_text(text[:i] + "force: [.nan, 0.0, 0.0" + text[j:])
    refuse("asset", "summary", folder / "pillow.yaml", "--profile", "ci", names=("pillow.yaml", "probes.standard_x.force[0]"))


@pytest.mark.parametrize("flag, value", [("--width", "0"), ("--width", "100000"), ("--height", "-5"), ("--height", "wide")])
def test_render_image_size(shared, refuse, tmp_path, flag, value):
    refuse("render", "frames", "--object", "pillow", "--profile", "ci", "--asset", shared / "pillow.ply",
           "--rollout", shared / "standard_x.parquet", flag, value, "-o", tmp_path / "png", names=(flag, value))


@pytest.mark.parametrize("flag, value", [("--level", "-1"), ("--level", "huge"), ("--level", "nan"), ("--noise", "-0.5"),
                                         ("--theta", "0,1"), ("--theta", "1,inf")])
def test_make_case_values(shared, refuse, tmp_path, flag, value):
    refuse("discrepancy", "make-case", "--object", "pillow", "--profile", "ci", "--case", "c", "--planted", "damping",
           "--particles", shared / "pillow.particles.npz", "--measured-dir", tmp_path / "m", "--truth-dir", tmp_path / "t",
           f"{flag}={value}", names=(flag, value))


@pytest.mark.parametrize("theta", ["nan,1", "1,-2"])
def test_simulate_theta_not_positive_finite(shared, refuse, tmp_path, theta):
    refuse(*_sim(shared, f"--theta={theta}", "-o", tmp_path / "r.parquet"), names=("--theta",))


def test_calibrate_alpha_nan(shared, refuse, tmp_path):
    refuse("calibrate", "--library", FICUS / "library.csv", "--queries", FICUS / "queries.csv", "--method", "local_ridge",
           "--alpha", "nan", "--output", tmp_path / "est.json", names=("--alpha", "nan"))


def test_too_few_gaussians_in_a_ply_is_a_one_line_warning(shared, tmp_path, capsys):
    from knockgs_core.assets import read_ply, write_ply

    g = read_ply(shared / "pillow.ply")
    write_ply(g.subset(np.arange(10)), tmp_path / "tiny.ply")
    text = (shared / "config/objects/pillow.yaml").read_text()
    start = text.index("asset:")
    end = text.index("\n", text.index("procedural:", start))
    (tmp_path / "pillow.yaml").write_text(text[:start] + "asset:\n  ply: tiny.ply" + text[end:])
    main(["asset", "summary", str(tmp_path / "pillow.yaml"), "--profile", "ci", "--config-dir", str(shared / "config")])
    err = capsys.readouterr().err
    assert "knockgs: warning: " in err and "tiny.ply" in err and "holds 10 Gaussians" in err and "Traceback" not in err


# --------------------------------------------------------------------------- 4. tracebacks where a line belongs


def test_contract_binary_file(shared, refuse, tmp_path):
    (tmp_path / "pillow.yaml").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00" * 8)
    refuse("asset", "summary", tmp_path / "pillow.yaml", "--profile", "ci", names=("pillow.yaml", "'file'", "UTF-8"))


def test_contract_is_a_folder(shared, refuse, tmp_path):
    (tmp_path / "pillow.yaml").mkdir()
    refuse("asset", "summary", tmp_path / "pillow.yaml", "--profile", "ci", names=("pillow.yaml", "'NAME'", "folder"))


def test_contract_not_yaml(shared, refuse, tmp_path):
    (tmp_path / "pillow.yaml").write_text("name: [unclosed\n  probes: {")
    refuse("asset", "summary", tmp_path / "pillow.yaml", "--profile", "ci", names=("pillow.yaml", "'yaml'"))


def _particles_variant(shared, tmp_path, kind) -> Path:
    p = tmp_path / "p.npz"
    data = (shared / "pillow.particles.npz").read_bytes()
    if kind == "text":
        p.write_text("positions: not an archive\n")
    elif kind == "truncated":
        p.write_bytes(data[: len(data) // 2])
    elif kind == "empty":
        p.write_bytes(b"")
    elif kind == "object array":
        np.savez(p, positions=np.array([object()], dtype=object), gaussian_index=np.zeros(1), region=np.zeros(1),
                 meta=np.zeros(1, np.uint8))
    elif kind == "bad meta":
        with np.load(shared / "pillow.particles.npz") as z:
            arrays = {k: z[k] for k in z.files}
        arrays["meta"] = np.frombuffer(b"\xff{not json", dtype=np.uint8)
        np.savez(p, **arrays)
    return p


@pytest.mark.parametrize("kind", ["text", "truncated", "empty", "object array", "bad meta"])
def test_bad_particle_file(shared, refuse, tmp_path, kind):
    p = _particles_variant(shared, tmp_path, kind)
    refuse(*_sim(shared, "--particles", p, "-o", tmp_path / "r.parquet"), names=("p.npz",))


def _truncate(src: Path, dest: Path) -> Path:
    data = src.read_bytes()
    dest.write_bytes(data[: len(data) // 3])
    return dest


def test_truncated_rollout(shared, refuse, tmp_path):
    r = _truncate(shared / "standard_x.parquet", tmp_path / "r.parquet")
    shutil.copy(shared / "standard_x.F.parquet", tmp_path / "r.F.parquet")
    refuse("render", "ply", "--asset", shared / "pillow.ply", "--rollout", r, "-o", tmp_path / "ply",
           names=("r.parquet", "'file'"))


def test_rollout_is_a_folder(shared, refuse, tmp_path):
    (tmp_path / "r.parquet").mkdir()
    refuse("render", "ply", "--asset", shared / "pillow.ply", "--rollout", tmp_path / "r.parquet",
           "--deformation", shared / "standard_x.F.parquet", "-o", tmp_path / "ply", names=("r.parquet", "--rollout"))


def test_ply_garbage(shared, refuse, tmp_path):
    (tmp_path / "a.ply").write_bytes(b"ply\nformat nonsense\n\x00\x01")
    shutil.copy(shared / "pillow.scene.npz", tmp_path / "a.scene.npz")
    refuse("render", "ply", "--asset", tmp_path / "a.ply", "--rollout", shared / "standard_x.parquet", "-o", tmp_path / "ply",
           names=("a.ply", "'file'"))


def test_scene_file_garbage(shared, refuse, tmp_path):
    (tmp_path / "s.npz").write_bytes(b"PK\x03\x04 broken")
    refuse("render", "ply", "--asset", shared / "pillow.ply", "--scene", tmp_path / "s.npz", "--rollout",
           shared / "standard_x.parquet", "-o", tmp_path / "ply", names=("s.npz", "'file'"))


@pytest.mark.parametrize("suffix, content", [
    (".parquet", b"PAR1 this is not parquet PAR1"),
    (".csv", b"\xff\xfe\x00\x81 binary \x00"),
    (".npz", b"PK\x03\x04 truncated"),
    (".npz", b""),
])
def test_bad_measurement_file(shared, refuse, tmp_path, suffix, content):
    m = tmp_path / f"m{suffix}"
    m.write_bytes(content)
    refuse(*_run(shared, measured=m), names=(f"m{suffix}", "'file'"))


def test_measurement_is_a_folder(shared, refuse, tmp_path):
    (tmp_path / "m.parquet").mkdir()
    refuse(*_run(shared, measured=tmp_path / "m.parquet"), names=("m.parquet", "'--measured'", "folder"))


def test_calibrate_binary_library(shared, refuse, tmp_path):
    (tmp_path / "L.csv").write_bytes(b"\x00\xff\xfe\x81" * 50)
    refuse("calibrate", "--library", tmp_path / "L.csv", "--queries", FICUS / "queries.csv", "--method", "knn",
           "--output", tmp_path / "est.json", names=("L.csv",))


def test_evaluate_garbage_result(shared, refuse, tmp_path):
    (tmp_path / "run").mkdir()
    (tmp_path / "run/result.json").write_text("{not json")
    refuse("discrepancy", "evaluate", "--run-dir", tmp_path / "run", "--truth-dir", shared / "truth",
           "-o", tmp_path / "row.json", names=("result.json", "--run-dir"))


def test_table_row_not_json(shared, refuse, tmp_path):
    (tmp_path / "row.json").write_bytes(b"\x00\x01binary")
    refuse("discrepancy", "table", tmp_path / "row.json", "--csv", tmp_path / "t.csv", "--md", tmp_path / "t.md",
           names=("row.json", "ROW.json"))


def _no_gpu() -> bool:
    import warp as wp

    from knockgs_core._warp import init_warp

    init_warp("cpu")
    return wp.get_cuda_device_count() == 0


@pytest.mark.parametrize("device", ["bogus", "cuda:99", pytest.param("cuda", marks=pytest.mark.skipif(
    not _no_gpu(), reason="'cuda' claims a card where there is one"))])
def test_unknown_device(shared, refuse, tmp_path, device):
    refuse(*_sim(shared, "--particles", shared / "pillow.particles.npz", "--device", device, "-o", tmp_path / "r.parquet"),
           names=(device, "device"))


def test_unknown_render_device_refused_before_rendering(shared, refuse, tmp_path):
    refuse("render", "frames", "--object", "pillow", "--profile", "ci", "--asset", shared / "pillow.ply", "--rollout",
           shared / "standard_x.parquet", "--device", "bogus", "-o", tmp_path / "png", names=("bogus", "device"))


def test_ctrl_c_is_exit_130_without_traceback(shared, refuse, tmp_path, monkeypatch):
    import knockgs_core.rollout as rollout

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(rollout, "run_rollout", interrupted)
    refuse(*_sim(shared, "-o", tmp_path / "r.parquet"), code=130, names=("simulate",))


def test_ctrl_c_while_writing_leaves_the_previous_file(shared, refuse, tmp_path, monkeypatch):
    out = tmp_path / "r.parquet"
    out.write_bytes(b"previous")

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pq, "write_table", interrupted)
    monkeypatch.setattr(pq.ParquetWriter, "write_table", interrupted)  # the frames written as the rollout runs
    refuse(*_sim(shared, "--particles", shared / "pillow.particles.npz", "-o", out), code=130)


def test_missing_column_in_a_rollout(shared, refuse, tmp_path):
    t = pq.read_table(shared / "standard_x.parquet")
    pq.write_table(t.drop(["z"]), tmp_path / "r.parquet")
    shutil.copy(shared / "standard_x.F.parquet", tmp_path / "r.F.parquet")
    refuse("render", "ply", "--asset", shared / "pillow.ply", "--rollout", tmp_path / "r.parquet", "-o", tmp_path / "ply",
           names=("r.parquet", "'z'"))


def test_rollout_rows_disagree_with_its_metadata(shared, refuse, tmp_path):
    t = pq.read_table(shared / "standard_x.parquet")
    keep = pa.compute.less(t.column("particle"), 1000)
    pq.write_table(t.filter(keep), tmp_path / "r.parquet")
    shutil.copy(shared / "standard_x.F.parquet", tmp_path / "r.F.parquet")
    refuse("render", "ply", "--asset", shared / "pillow.ply", "--rollout", tmp_path / "r.parquet", "-o", tmp_path / "ply",
           names=("r.parquet", "'particle'", "n_gs + n_fill"))


# --------------------------------------------------------------------------- 5. resource abuse


def _alias_bomb(levels: int) -> str:
    lines = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    names = "abcdefghijklmnop"
    for prev, name in zip(names, names[1:levels]):
        lines.append(f"{name}: &{name} [" + ",".join([f"*{prev}"] * 9) + "]")
    return "\n".join(lines) + "\n"


def test_yaml_alias_bomb_is_refused_at_once(shared, refuse, tmp_path):
    (tmp_path / "bomb.yaml").write_text(_alias_bomb(12))
    t0 = time.perf_counter()
    refuse("asset", "summary", tmp_path / "bomb.yaml", "--profile", "ci", names=("bomb.yaml", "'yaml'", "aliases"))
    assert time.perf_counter() - t0 < 2.0


def test_a_single_yaml_alias_is_refused(shared, refuse, tmp_path):
    c = _contract_with(shared, tmp_path, "materials:\n  base: {E: 1.0e4, nu: 0.3, rho: 2000.0}",
                       "materials:\n  base: &m {E: 1.0e4, nu: 0.3, rho: 2000.0}\n  other: *m")
    refuse("asset", "summary", c, "--profile", "ci", names=("pillow.yaml", "line", "aliases (*m)"))


def test_deeply_nested_yaml_is_refused(shared, refuse, tmp_path):
    (tmp_path / "deep.yaml").write_text("a: " + "[" * 20000 + "]" * 20000 + "\n")
    refuse("asset", "summary", tmp_path / "deep.yaml", "--profile", "ci", names=("deep.yaml", "'yaml'", "nested"))


def test_huge_ply_header_is_refused_at_once(shared, refuse, tmp_path):
    (tmp_path / "huge.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\n"
                                        b"property float x\nend_header\n")
    shutil.copy(shared / "pillow.scene.npz", tmp_path / "huge.scene.npz")
    t0 = time.perf_counter()
    refuse("render", "ply", "--asset", tmp_path / "huge.ply", "--rollout", shared / "standard_x.parquet",
           "-o", tmp_path / "ply", names=("huge.ply", "'file'"))
    assert time.perf_counter() - t0 < 2.0


def test_huge_render_size_refused_before_allocating(shared, refuse, tmp_path):
    t0 = time.perf_counter()
    refuse("render", "frames", "--object", "pillow", "--profile", "ci", "--asset", shared / "pillow.ply", "--rollout",
           shared / "standard_x.parquet", "--width", "100000", "--height", "100000", "-o", tmp_path / "png",
           names=("--width", "8192"))
    assert time.perf_counter() - t0 < 2.0
