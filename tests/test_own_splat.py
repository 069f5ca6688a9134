"""One's own object calibrated from a measured Probe-A observation (docs/own_splat.md, the
tutorial; workflow/rules/calibration.smk; knockgs_core.experiments._own_object).

The tutorial test runs the blocks of docs/own_splat.md marked ``<!-- tutorial -->`` as written,
in order, in a scratch copy of the workflow beside a ``shared/data/splats`` that links the real
captures (``KNOCKGS_SPLATS`` or ``../shared/data/splats``; skipped, saying why, without them).
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from _workflow import ROOT, scratch_copy, snakemake, snakemake_env
from knockgs_core.errors import InputError

#: the tutorial test's library: every 9th candidate (six), config calibration.candidate_stride,
#: and the local ridge's k cut to the six. Each candidate costs a rollout and its filming and
#: tracking at the contract camera's 300 x 400 (about 12 CPU s); with six the estimate came out at
#: (0.895, 1.275), joint error 1.3 % against the base material's 17.1 %, Probe-B RMSE 8.6e-5
#: against 1.2e-3 (nine: 1.9 %, 6.6e-5)
TEST_CONFIG = ["calibration={candidate_stride: 9}", "method_params={local_ridge: {k: 6, alpha: 0.001}}"]


def tutorial_blocks(text: str) -> list[tuple[str, str]]:
    """(language, code) of every fenced block marked ``<!-- tutorial -->``, in order."""
    return re.findall(r"^<!-- tutorial -->\n```(\w+)\n(.*?)^```", text, flags=re.S | re.M)


def tutorial_commands(code: str) -> list[list[str]]:
    """A bash block's commands as argument lists (continuation lines joined, comments dropped)."""
    joined = re.sub(r"\\\n\s*", " ", code)
    return [args for args in (shlex.split(line, comments=True) for line in joined.splitlines()) if args]


def test_tutorial_blocks_parse():
    blocks = tutorial_blocks((ROOT / "docs" / "own_splat.md").read_text())
    assert [lang for lang, _ in blocks] == ["bash", "bash", "python"]
    cmds = [c for lang, code in blocks if lang == "bash" for c in tutorial_commands(code)]
    assert [c[0] for c in cmds] == ["knockgs"] * 5 + ["snakemake", "knockgs"]
    assert cmds[5][-2:] == ["--config", "calibration={object: guitar, contract: my/guitar.yaml, measurement: "
                                        "my/probe_a.tracks.parquet}"]
    assert tutorial_blocks("<!-- tutorial -->\n```bash\nknockgs a \\\n  b  # c\n```\n```bash\nx\n```\n") == [
        ("bash", "knockgs a \\\n  b  # c\n")]


# --------------------------------------------------------------------------- the observation


@pytest.fixture(scope="module")
def rendered_probe_a(pillow_ci):
    """The ci Pillow's Probe-A rollout at theta (1, 1) and its RGB-D frames at 96 x 72 by the
    contract's camera (about 3 s)."""
    from knockgs_core.experiments import camera_from_contract
    from knockgs_core.observe import render_rgbd
    from knockgs_core.rollout import run_rollout

    c, asset = pillow_ci
    ro = run_rollout(c, (1.0, 1.0), "standard_x", particles=asset.particles, export_F=True)
    cam = camera_from_contract(c.camera, width=96, height=72)
    frames = render_rgbd(asset.gaussians, np.asarray(asset.static_mask), np.asarray(asset.particles.gaussian_index),
                         ro.positions, ro.F, cam, frame_dt=0.02)
    return c, asset, ro, frames


def test_a_library_member_is_observed_as_its_measured_tracks_are(rendered_probe_a, tmp_path):
    """The library's observation (render, RGB-D precision, tracker, descriptor) of a rollout
    gives the same descriptor, bit for bit, as that rollout filmed to a file by `knockgs observe
    rgbd`'s writer, tracked by `knockgs observe tracks` with its defaults and read as a
    measurement; and as the same file read as an RGB-D measurement."""
    from knockgs_core.cli import main
    from knockgs_core.experiments import ObservationSettings, measured_observation, observe_rollout
    from knockgs_core.observe import write_rgbd

    c, asset, ro, frames = rendered_probe_a
    write_rgbd(tmp_path / "a.npz", frames)
    assert main(["observe", "tracks", str(tmp_path / "a.npz"), "-o", str(tmp_path / "a.parquet")]) == 0
    probe = c.probes["standard_x"]
    phi_tracks, curve, info, camera = measured_observation(tmp_path / "a.parquet", ObservationSettings(), probe)
    assert camera is None and info["tracks"] >= 8
    phi_rgbd, _, _, camera = measured_observation(tmp_path / "a.npz", ObservationSettings(kind="rgbd"), probe)
    phi_lib, curve_lib, _ = observe_rollout(asset.gaussians, np.asarray(asset.static_mask),
                                            np.asarray(asset.particles.gaussian_index), ro.positions, ro.F, camera,
                                            ObservationSettings(), frame_dt=0.02)
    np.testing.assert_array_equal(phi_lib, phi_tracks)
    np.testing.assert_array_equal(phi_lib, phi_rgbd)
    np.testing.assert_array_equal(curve_lib, curve)
    assert curve[0] == 0 and curve.max() > 0


def test_a_measurement_of_another_probe_or_frames_is_refused(tmp_path, rng, pillow_ci):
    from knockgs_core.discrepancy import Measurement, write_measured
    from knockgs_core.experiments import ObservationSettings, measured_observation

    probe = pillow_ci[0].probes["standard_x"]
    X = 1.0 + np.cumsum(rng.normal(0, 1e-3, size=(31, 12, 3)), axis=0)

    def refused(meta, points=X, frames=None):
        m = Measurement(points=points, frames=np.arange(len(points)) if frames is None else frames, times=None,
                        particle=None, track=np.arange(1, points.shape[1] + 1), meta=meta, source="m.parquet")
        write_measured(tmp_path / "m.parquet", m)
        with pytest.raises(InputError) as e:
            measured_observation(tmp_path / "m.parquet", ObservationSettings(), probe)
        return str(e.value)

    assert "metadata.probe" in refused({"probe": "standard_y"}) and "standard_x" in refused({"probe": "standard_y"})
    assert "field 'frame'" in refused({}, points=X[:30])
    assert "field 'frame'" in refused({}, frames=np.r_[np.arange(30), 31])
    # the same measurement of the calibration probe, every frame: read
    m = Measurement(points=X, frames=np.arange(31), times=None, particle=None, track=np.arange(1, 13),
                    meta={"probe": "standard_x"}, source="m.parquet")
    write_measured(tmp_path / "ok.parquet", m)
    phi, curve, info, _ = measured_observation(tmp_path / "ok.parquet", ObservationSettings(), probe)
    assert np.all(np.isfinite(phi)) and curve.shape == (31,) and info["tracks"] == 12


def test_the_calibration_tracker_defaults_are_those_of_knockgs_observe_tracks():
    """What ``knockgs observe tracks`` tracks with by default is what the calibration observes
    the library with by default (ObservationSettings), and the config schema says the same."""
    import argparse

    from knockgs_core.cli import observe as cli_observe
    from knockgs_core.experiments import ObservationSettings

    parser = argparse.ArgumentParser()
    cli_observe.register(parser.add_subparsers())
    args = parser.parse_args(["observe", "tracks", "f.npz", "-o", "t.parquet"])
    cli = ObservationSettings(track={"method": args.method, "max_seeds": args.max_seeds, "radius": args.radius}).tracker()
    assert ObservationSettings().tracker() == cli and args.fb_max is None and args.depth_noise == 0
    schema = yaml.safe_load((ROOT / "workflow/schemas/config.schema.yaml").read_text())["properties"]["calibration"]
    track = {k: v["default"] for k, v in schema["properties"]["track"]["properties"].items()}
    assert ObservationSettings(track=track).tracker() == ObservationSettings().tracker()
    assert schema["properties"]["kind"]["default"] == ObservationSettings().kind


# --------------------------------------------------------------------------- the workflow


@pytest.mark.slow
def test_a_calibration_config_problem_is_one_line_naming_the_key(tmp_path):
    work = scratch_copy(tmp_path / "w")
    out = snakemake(work, "-n", "--configfile=config/ci.yaml", "calibration")
    assert out.returncode != 0 and "config calibration.object: not set" in out.stdout + out.stderr
    out = snakemake(work, "-n", "--configfile=config/ci.yaml", "calibration", "--config",
                    "calibration={object: pillow, measurement: nowhere.parquet}")
    assert out.returncode != 0 and "config calibration.measurement: nowhere.parquet is not a file" in out.stdout + out.stderr
    (work / "m.parquet").write_text("")
    out = snakemake(work, "-n", "--configfile=config/ci.yaml", "calibration", "--config",
                    "calibration={object: ficus, contract: config/objects/pillow.yaml, measurement: m.parquet}")
    assert out.returncode != 0 and "config calibration.object: 'ficus', but the contract pillow.yaml is of 'pillow'" in \
        out.stdout + out.stderr
    out = snakemake(work, "-n", "--configfile=config/ci.yaml", "calibration", "--config",
                    "calibration={object: pillow, measurement: m.parquet, candidate_stride: 6}")
    assert out.returncode != 0 and ("config calibration.candidate_stride: 6 keeps 9 candidates, fewer than "
                                    "method_params.local_ridge.k = 10") in out.stdout + out.stderr


@pytest.fixture(scope="module")
def splats() -> Path:
    root = Path(os.environ.get("KNOCKGS_SPLATS", ROOT.parent / "shared" / "data" / "splats"))
    if not (root / "guitar.compressed.ply").is_file():
        pytest.skip(f"the real captures are not here ({root}; set KNOCKGS_SPLATS to their folder)")
    return root


@pytest.mark.slow
def test_the_tutorial_calibrates_the_guitar_from_its_filmed_response(tmp_path, splats):
    """The tutorial's blocks as written (the library cut to every 9th candidate, six: config
    calibration.candidate_stride, and k to six) make the calibration folder; the measurement's descriptor is
    the hidden rollout observed as the library is; the frozen estimate is nearer the hidden
    theta than the base material, and its Probe-B prediction nearer the hidden truth's.

    About 135 CPU s, and no smaller: the tutorial's commands are run as written (the guitar's
    asset, the hidden rollouts, the filming at 300 x 400 and tracking: about 30 s), then the
    route's own jobs: the library, each candidate simulated, filmed and tracked as the
    measurement was (:data:`TEST_CONFIG`: six, spanning the hidden theta on both axes, s_E 0.5 to
    1.15 and s_rho 0.75 to 1.75), and the write-back's four rollouts with F, their renders and
    their observation."""
    from knockgs_core.assets import load_scene, read_ply
    from knockgs_core.contract import load_contract
    from knockgs_core.descriptors import FEATURE_NAMES
    from knockgs_core.experiments import ObservationSettings, camera_from_contract, observe_rollout
    from knockgs_core.metrics import joint_error_pct, trajectory_rmse
    from knockgs_core.rollout import read_deformation, read_rollout

    (tmp_path / "shared" / "data").mkdir(parents=True)
    (tmp_path / "shared" / "data" / "splats").symlink_to(splats, target_is_directory=True)
    work = scratch_copy(tmp_path / "work")
    env = {k: v for k, v in snakemake_env().items() if k not in ("KNOCKGS_CONFIG_DIR", "KNOCKGS_DEVICE")}
    for lang, code in tutorial_blocks((ROOT / "docs" / "own_splat.md").read_text()):
        runs = ([[sys.executable, "-c", code]] if lang == "python" else
                [[sys.executable, "-m", {"knockgs": "knockgs_core", "snakemake": "snakemake"}[a[0]], *a[1:]]
                 + (TEST_CONFIG if a[0] == "snakemake" else [])
                 for a in tutorial_commands(code)])
        for args in runs:
            proc = subprocess.run(args, cwd=work, env=env, capture_output=True, text=True, timeout=1500)
            assert proc.returncode == 0, f"{shlex.join(args)}\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    assert "joint error" in proc.stdout and "Probe-B RMSE before" in proc.stdout

    C = work / "results" / "ci" / "calibration" / "guitar"
    for name in ("report.md", "report.png", "calibration.csv", "calibration.md", "estimate.json"):
        assert (C / name).stat().st_size > 0, name
    library = np.genfromtxt(C / "library.csv", delimiter=",", names=True, dtype=None, encoding=None)
    assert len(library) == 6
    for which in ("before", "after"):
        for probe in ("standard_x", "standard_y"):
            assert (C / "frames" / which / f"{probe}.npz").is_file(), (which, probe)
            assert (C / "predictions" / which / f"{probe}.parquet").is_file(), (which, probe)
    # the measurement is the hidden rollout observed exactly as every library member is
    c = load_contract(work / "my" / "guitar.yaml", "ci")
    g = read_ply(C / "asset.ply")
    static, index = load_scene(C / "asset.scene.npz", n_gaussians=len(g))
    ro = read_rollout(work / "my" / "hidden_a.parquet")
    phi, _, _ = observe_rollout(g, static, index, ro.positions, read_deformation(work / "my" / "hidden_a.F.parquet"),
                                camera_from_contract(c.camera), ObservationSettings(), frame_dt=0.02)
    query = np.genfromtxt(C / "measurement.csv", delimiter=",", names=True, dtype=None, encoding=None)
    np.testing.assert_allclose([float(query[f]) for f in FEATURE_NAMES], phi, rtol=1e-9)
    # calibration beats the base material, in theta and under the held-out probe
    est = json.loads((C / "estimate.json").read_text())["predictions"][0]
    theta, hidden = (est["E_scale"], est["density_scale"]), (0.9, 1.3)
    assert joint_error_pct(theta, hidden) < joint_error_pct((1.0, 1.0), hidden)
    truth = read_rollout(work / "my" / "hidden_b.parquet")
    n = int(truth.meta["n_gs"])
    rmse = {w: trajectory_rmse(read_rollout(C / "predictions" / w / "standard_y.parquet").positions[:, :n],
                               truth.positions[:, :n]) for w in ("before", "after")}
    assert rmse["after"] < rmse["before"], rmse
