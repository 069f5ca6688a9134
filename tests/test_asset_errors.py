"""Bad input gets an InputError naming the file and the field, never a traceback."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from knockgs_core.assets import GaussianSet, build_asset, preprocess, read_ply, write_ply
from knockgs_core.cli import main as cli_main
from knockgs_core.contract import find_config_dir, load_contract, load_targets
from knockgs_core.errors import InputError


def gaussians(n=50, seed=0, **over) -> GaussianSet:
    rng = np.random.default_rng(seed)
    kw = dict(means=rng.normal(size=(n, 3)), scales=np.full((n, 3), 0.01), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
              opacities=np.full(n, 0.9), sh_dc=rng.normal(size=(n, 3)))
    kw.update(over)
    return GaussianSet(**kw)


def contract_file(tmp_path, name="pillow", mutate=None):
    """A copy of a repository contract, changed by ``mutate(data)``, in tmp_path/objects."""
    data = yaml.safe_load((find_config_dir() / "objects" / f"{name}.yaml").read_text())
    if mutate:
        mutate(data)
    path = tmp_path / "objects" / f"{name}.yaml"
    path.parent.mkdir(exist_ok=True)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def check(exc_info, source, field):
    err = exc_info.value
    assert str(source) in err.source, err
    assert err.field == field, err
    assert str(source) in str(err) and field in str(err)


# --------------------------------------------------------------------------- PLY

def test_ply_missing_field(tmp_path):
    from plyfile import PlyData, PlyElement

    path = tmp_path / "g.ply"
    write_ply(gaussians(), path)
    v = PlyData.read(str(path), mmap=False)["vertex"].data
    names = [n for n in v.dtype.names if n != "opacity"]
    rec = np.empty(len(v), dtype=[(n, "f4") for n in names])
    for n in names:
        rec[n] = v[n]
    PlyData([PlyElement.describe(rec, "vertex")]).write(str(path))
    with pytest.raises(InputError) as e:
        read_ply(path)
    check(e, path, "opacity")


def test_ply_read_mapped_equals_the_file_and_a_truncated_one_is_named(tmp_path):
    # read_ply maps the file (plyfile reads an unmapped binary file row by row): the values are
    # the file's, read row by row as a check, and the file stays writable after the read
    from plyfile import PlyData

    path = tmp_path / "g.ply"
    gs = gaussians(n=300, sh_rest=np.random.default_rng(1).normal(size=(300, 3, 3)))
    write_ply(gs, path)
    got = read_ply(path)
    v = PlyData.read(str(path), mmap=False)["vertex"].data
    np.testing.assert_array_equal(got.means, np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64))
    np.testing.assert_array_equal(got.sh_dc, np.stack([v[f"f_dc_{i}"] for i in range(3)], 1).astype(np.float64))
    np.testing.assert_array_equal(got.sh_rest[:, :, 0], np.stack([v[f"f_rest_{i}"] for i in range(3)], 1).astype(np.float64))
    write_ply(gaussians(n=10), path)  # replaced while a read's arrays are alive
    assert len(read_ply(path)) == 10 and len(got) == 300
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 20])
    with pytest.raises(InputError) as e:
        read_ply(path)
    check(e, path, "file")


def test_ply_nan_positions(tmp_path):
    from plyfile import PlyData

    path = tmp_path / "g.ply"
    write_ply(gaussians(), path)
    ply = PlyData.read(str(path), mmap=False)
    ply["vertex"].data["y"][3] = np.nan
    ply.write(str(path))
    with pytest.raises(InputError) as e:
        read_ply(path)
    check(e, path, "y")


def test_ply_bad_sh_count(tmp_path):
    from plyfile import PlyData, PlyElement

    path = tmp_path / "g.ply"
    write_ply(gaussians(), path)
    v = PlyData.read(str(path), mmap=False)["vertex"].data
    names = list(v.dtype.names) + ["f_rest_0", "f_rest_1"]
    rec = np.zeros(len(v), dtype=[(n, "f4") for n in names])
    for n in v.dtype.names:
        rec[n] = v[n]
    PlyData([PlyElement.describe(rec, "vertex")]).write(str(path))
    with pytest.raises(InputError) as e:
        read_ply(path)
    check(e, path, "f_rest_*")


def test_ply_missing_file(tmp_path):
    with pytest.raises(InputError) as e:
        read_ply(tmp_path / "nope.ply")
    check(e, tmp_path / "nope.ply", "file")


# --------------------------------------------------------------------------- preprocessing

def test_zero_extent_asset():
    gs = gaussians(means=np.tile([0.3, 0.2, 0.1], (50, 1)))
    with pytest.raises(InputError) as e:
        preprocess(gs, source="scan.ply")
    check(e, "scan.ply", "means")


def test_opacity_threshold_removes_everything(tmp_path):
    path = contract_file(tmp_path, mutate=lambda d: d["asset"].update(opacity_threshold=0.995))
    c = load_contract(path, "ci")
    with pytest.raises(InputError) as e:
        build_asset(c)
    check(e, path, "asset.opacity_threshold")


# --------------------------------------------------------------------------- contracts

def test_unknown_key(tmp_path):
    path = contract_file(tmp_path, mutate=lambda d: d["sim"].update(gravityy=[0, 0, -9.8]))
    with pytest.raises(InputError) as e:
        load_contract(path, "ci")
    check(e, path, "sim.gravityy")
    assert "unknown key" in e.value.message


def test_unknown_key_in_probe(tmp_path):
    path = contract_file(tmp_path, mutate=lambda d: d["probes"]["standard_x"].update(forces=[1, 0, 0]))
    with pytest.raises(InputError) as e:
        load_contract(path, "ci")
    check(e, path, "probes.standard_x.forces")


def test_wrong_type(tmp_path):
    def mutate(d):
        d["probes"]["standard_x"]["force"] = ["-0.18", 0, 0]
    path = contract_file(tmp_path, mutate=mutate)
    with pytest.raises(InputError) as e:
        load_contract(path, "ci")
    check(e, path, "probes.standard_x.force[0]")


def test_wrong_type_in_profile(tmp_path):
    path = contract_file(tmp_path, mutate=lambda d: d["profiles"]["ci"].update(n_grid=32.5))
    with pytest.raises(InputError) as e:
        load_contract(path, "ci")
    check(e, path, "profiles.ci.n_grid")


def test_missing_required_key(tmp_path):
    path = contract_file(tmp_path, mutate=lambda d: d.pop("camera"))
    with pytest.raises(InputError) as e:
        load_contract(path, "ci")
    check(e, path, "camera")


def test_probe_box_selects_nothing(tmp_path):
    def mutate(d):
        d["probes"]["local_center_x"]["box"] = {"center": [0.2, 0.2, 0.2], "half_size": [0.05, 0.05, 0.05]}
    path = contract_file(tmp_path, mutate=mutate)
    c = load_contract(path, "ci")
    with pytest.raises(InputError) as e:
        build_asset(c)
    check(e, path, "probes.local_center_x.box")


def test_support_holds_every_particle(tmp_path):
    def mutate(d):
        d["sim"]["boundaries"][1]["box"] = {"center": [1.0, 1.0, 1.0], "half_size": [0.9, 0.9, 0.9]}
    path = contract_file(tmp_path, mutate=mutate)
    c = load_contract(path, "ci")
    with pytest.raises(InputError) as e:
        build_asset(c)
    check(e, path, "sim.boundaries[1].box")


def test_everything_static(tmp_path):
    def mutate(d):
        d["asset"]["static_boxes"] = [{"center": [1.0, 1.0, 1.0], "half_size": [1.0, 1.0, 1.0]}]
    path = contract_file(tmp_path, mutate=mutate)
    with pytest.raises(InputError) as e:
        build_asset(load_contract(path, "ci"))
    check(e, path, "asset.static_boxes")


def test_unknown_profile(tmp_path):
    path = contract_file(tmp_path)
    with pytest.raises(InputError) as e:
        load_contract(path, "huge")
    check(e, path, "profile")


def test_dt_breaking_cfl_or_frames(tmp_path):
    path = contract_file(tmp_path, mutate=lambda d: d["profiles"]["ci"].update(dt=0.01))
    with pytest.raises(InputError) as e:
        load_contract(path, "ci")
    check(e, path, "profiles.ci.dt")
    path = contract_file(tmp_path, mutate=lambda d: d["profiles"]["ci"].update(dt=0.003))
    with pytest.raises(InputError) as e:
        load_contract(path, "ci")
    assert "does not divide" in e.value.message


def test_region_without_material(tmp_path):
    def mutate(d):
        d["regions"] = {"seat": [{"center": [1, 1, 1], "half_size": [0.1, 0.1, 0.1]}]}
    path = contract_file(tmp_path, mutate=mutate)
    with pytest.raises(InputError) as e:
        load_contract(path, "ci")
    check(e, path, "regions.seat")


def test_role_names_unknown_probe(tmp_path):
    path = contract_file(tmp_path, mutate=lambda d: d["roles"].update(heldout=["standard_y", "sideways"]))
    with pytest.raises(InputError) as e:
        load_contract(path, "ci")
    check(e, path, "roles.heldout[1]")


def test_both_asset_sources(tmp_path):
    path = contract_file(tmp_path, mutate=lambda d: d["asset"].update(ply="scan.ply"))
    with pytest.raises(InputError) as e:
        load_contract(path, "ci")
    check(e, path, "asset")


def test_duplicate_yaml_key(tmp_path):
    path = contract_file(tmp_path)
    path.write_text(path.read_text() + "\nname: pillow\n")
    with pytest.raises(InputError) as e:
        load_contract(path, "ci")
    check(e, path, "yaml")


def test_unknown_split():
    with pytest.raises(InputError) as e:
        load_targets("nope")
    assert e.value.field == "split" and "targets.csv" in e.value.source


def test_cli_reports_one_line(tmp_path, capsys):
    path = contract_file(tmp_path, mutate=lambda d: d["sim"].update(gravityy=[0, 0, -9.8]))
    assert cli_main(["asset", "summary", str(path), "--profile", "ci"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "sim.gravityy" in err and "Traceback" not in err
