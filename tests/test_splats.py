"""Real users' splats: the SuperSplat compressed PLY, the reading rules for what trained
splats contain, the contract scaffold (`knockgs asset init`) and the refusal of bad files.

Tests marked by the ``splats`` fixture read the real captures of ``../shared/data/splats``
(``KNOCKGS_SPLATS`` overrides the folder) and skip where it is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from knockgs_core.assets import (SH_C0, GaussianSet, build_asset, contract_text, read_splat, scaffold_contract,
                                 write_ply)
from knockgs_core.cli import main as cli_main
from knockgs_core.contract import load_contract
from knockgs_core.errors import InputError

CHUNK = 256


@pytest.fixture(scope="module")
def splats() -> Path:
    root = Path(os.environ.get("KNOCKGS_SPLATS", Path(__file__).resolve().parents[1].parent / "shared" / "data"
                               / "splats"))
    if not (root / "guitar.compressed.ply").is_file():
        pytest.skip(f"the real captures are not here ({root}; set KNOCKGS_SPLATS to their folder)")
    return root


# --------------------------------------------------------------------------- a compressed PLY, written here

def _unorm(t, bits):
    return np.round(np.clip(t, 0, 1) * ((1 << bits) - 1)).astype(np.uint32)


def _pack_111011(t):
    return (_unorm(t[:, 0], 11) << 21) | (_unorm(t[:, 1], 10) << 11) | _unorm(t[:, 2], 11)


def _pack_rotation(q):
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    which = np.argmax(np.abs(q), axis=1)
    q = q * np.sign(q[np.arange(len(q)), which])[:, None]
    rest = np.stack([np.delete(row, i) for row, i in zip(q, which)])
    t = rest / np.sqrt(2.0) + 0.5
    return (which.astype(np.uint32) << 30) | (_unorm(t[:, 0], 10) << 20) | (_unorm(t[:, 1], 10) << 10) | _unorm(t[:, 2], 10)


def write_compressed(path, means, log_scales, quats, rgb, alpha, *, sh_bytes=None, n_chunks=None):
    """A SuperSplat compressed PLY of these values, quantized chunk by chunk (as the format's
    writer does: chunk bounds are the min and max of each chunk's values)."""
    from plyfile import PlyData, PlyElement

    n = len(means)
    nc = -(-n // CHUNK) if n_chunks is None else n_chunks
    names = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z", "min_scale_x", "min_scale_y", "min_scale_z",
             "max_scale_x", "max_scale_y", "max_scale_z", "min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
    chunk = np.zeros(max(nc, -(-n // CHUNK)), dtype=[(k, "<f4") for k in names])
    packed = np.zeros(n, dtype=[(k, "<u4") for k in ("packed_position", "packed_rotation", "packed_scale",
                                                     "packed_color")])
    for c in range(-(-n // CHUNK)):
        s = slice(c * CHUNK, min(n, (c + 1) * CHUNK))
        words = []
        for vals, (lo_names, hi_names) in ((means[s], (names[0:3], names[3:6])),
                                          (log_scales[s], (names[6:9], names[9:12])),
                                          (rgb[s], (names[12:15], names[15:18]))):
            lo, hi = vals.min(0).astype(np.float32), vals.max(0).astype(np.float32)
            for k, a, b in zip(range(3), lo, hi):
                chunk[lo_names[k]][c], chunk[hi_names[k]][c] = a, b
            words.append((vals - lo) / np.where(hi > lo, hi - lo, 1.0))
        packed["packed_position"][s] = _pack_111011(words[0])
        packed["packed_scale"][s] = _pack_111011(words[1])
        t = words[2]
        packed["packed_color"][s] = ((_unorm(t[:, 0], 8) << 24) | (_unorm(t[:, 1], 8) << 16) | (_unorm(t[:, 2], 8) << 8)
                                     | _unorm(alpha[s], 8))
        packed["packed_rotation"][s] = _pack_rotation(quats[s])
    elements = [PlyElement.describe(chunk[:nc], "chunk"), PlyElement.describe(packed, "vertex")]
    if sh_bytes is not None:
        sh = np.zeros(n, dtype=[(f"f_rest_{i}", "u1") for i in range(sh_bytes.shape[1])])
        for i in range(sh_bytes.shape[1]):
            sh[f"f_rest_{i}"] = sh_bytes[:, i]
        elements.append(PlyElement.describe(sh, "sh"))
    PlyData(elements, byte_order="<").write(str(path))


def random_splat(rng, n):
    means = rng.normal(size=(n, 3))
    log_scales = rng.uniform(-6, -2, size=(n, 3))
    quats = rng.normal(size=(n, 4))
    rgb = rng.uniform(0.05, 0.95, size=(n, 3))
    alpha = rng.uniform(0.1, 0.9, size=n)
    return means, log_scales, quats, rgb, alpha


def test_compressed_bits_decode_as_the_format_defines(tmp_path):
    # one chunk, pinned words: the top 11 bits of packed_position are x, the next 10 y, the last 11 z;
    # rotation 2 bits name the largest component (here rot_2 = x of w,x,y,z), the others in order
    from plyfile import PlyData, PlyElement

    names = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z", "min_scale_x", "min_scale_y", "min_scale_z",
             "max_scale_x", "max_scale_y", "max_scale_z", "min_r", "min_g", "min_b", "max_r", "max_g", "max_b"]
    chunk = np.zeros(1, dtype=[(k, "<f4") for k in names])
    for k, v in zip(names, [-1, 0, 2, 1, 4, 3, -5, -5, -5, -1, -3, -1, 0, 0, 0.2, 1, 0.5, 0.6]):
        chunk[k] = v
    rot_half = 512  # (512 / 1023 - 0.5) sqrt(2) ~ 6.9e-4
    vertex = np.array([((2047 << 21) | (0 << 11) | 1023, (2 << 30) | (rot_half << 20) | (rot_half << 10) | rot_half,
                        (0 << 21) | (1023 << 11) | 2047, (255 << 24) | (0 << 16) | (51 << 8) | 255)] * 100,
                      dtype=np.uint32).view([("packed_position", "<u4"), ("packed_rotation", "<u4"),
                                             ("packed_scale", "<u4"), ("packed_color", "<u4")]).ravel()
    path = tmp_path / "pinned.compressed.ply"
    PlyData([PlyElement.describe(chunk, "chunk"), PlyElement.describe(vertex, "vertex")]).write(str(path))
    sf = read_splat(path)
    g = sf.gaussians
    assert sf.layout == "supersplat_compressed"
    np.testing.assert_allclose(g.means[0], [1.0, 0.0, 2.0 + 1023 / 2047], rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.log(g.scales[0]), [-5.0, -3.0, -1.0], rtol=0, atol=1e-6)
    c = (512 / 1023 - 0.5) * np.sqrt(2)
    np.testing.assert_allclose(g.quats[0], np.array([c, c, np.sqrt(1 - 3 * c * c), c]) / 1.0, atol=1e-6)
    np.testing.assert_allclose(g.colors()[0], [1.0, 0.0, 0.2 + 0.4 * 51 / 255], atol=1e-6)
    assert g.opacities[0] == 1.0 and sf.repairs.opacity_saturated == 100


@pytest.mark.parametrize("k", [0, 3, 8, 15])
def test_compressed_values_are_within_half_a_quantization_step(tmp_path, rng, k):
    # what was written comes back within half of each field's step (SH degrees 0-3)
    n = 3 * CHUNK + 17
    means, log_scales, quats, rgb, alpha = random_splat(rng, n)
    sh_bytes = rng.integers(0, 256, size=(n, 3 * k)).astype(np.uint8) if k else None
    path = tmp_path / "g.compressed.ply"
    write_compressed(path, means, log_scales, quats, rgb, alpha, sh_bytes=sh_bytes)
    g = read_splat(path).gaussians
    rgb_got = 0.5 + SH_C0 * g.sh_dc.astype(np.float64)
    for c in range(-(-n // CHUNK)):
        s = slice(c * CHUNK, (c + 1) * CHUNK)
        for got, want, levels in ((g.means[s], means[s], [2047, 1023, 2047]),
                                  (np.log(g.scales[s].astype(np.float64)), log_scales[s], [2047, 1023, 2047]),
                                  (rgb_got[s], rgb[s], [255, 255, 255])):
            step = (want.max(0) - want.min(0)) / np.array(levels)
            assert np.all(np.abs(got - want) <= 0.5 * step + 1e-6 * (1 + np.abs(want))), c
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    err = np.minimum(np.abs(g.quats - q).max(1), np.abs(g.quats + q).max(1))
    assert err.max() <= 1.5 * np.sqrt(2) / 1023  # three components at half a step, the fourth from them
    assert np.abs(g.opacities - alpha).max() <= 0.5 / 255 + 1e-6
    assert g.sh_rest.shape == (n, k, 3)
    if k:
        frac = np.where(sh_bytes == 0, 0.0, np.where(sh_bytes == 255, 1.0, (sh_bytes + 0.5) / 256))
        want = ((frac - 0.5) * 8).reshape(n, 3, k).transpose(0, 2, 1)
        np.testing.assert_allclose(g.sh_rest, want, atol=1e-6)


def test_compressed_guitar_equals_the_independent_decoding(splats):
    # guitar.ply is guitar.compressed.ply decoded by @playcanvas/splat-transform 3.7.0 (PROVENANCE.md).
    # Both decode the same quantized words, so they agree to float32 rounding; the bound asked of each
    # field is 1 % of its quantization step: positions (max - min) / 2047 of the chunk (x, z; / 1023 y),
    # log scales likewise, quaternion components sqrt(2) / 1023, colours (max - min) / 255 of the chunk
    # (f_dc: / C0), opacities 1 / 255. Measured 2026-12-06: max differences 0 (positions), 3.0e-8
    # (scales), 6.0e-8 (quaternions), 0 (f_dc), 3.0e-8 (opacities).
    from plyfile import PlyData

    a = read_splat(splats / "guitar.compressed.ply")
    b = read_splat(splats / "guitar.ply")
    assert a.layout == "supersplat_compressed" and b.layout == "inria"
    ga, gb = a.gaussians, b.gaussians
    assert len(ga) == len(gb) == 90854
    chunk = PlyData.read(str(splats / "guitar.compressed.ply"))["chunk"].data
    ci = np.arange(len(ga)) // CHUNK

    def step(lo, hi, levels):
        return np.stack([(chunk[b] - chunk[a])[ci] / n for a, b, n in zip(lo, hi, levels)], axis=1)

    pos_step = step(("min_x", "min_y", "min_z"), ("max_x", "max_y", "max_z"), (2047, 1023, 2047))
    scl_step = step(("min_scale_x", "min_scale_y", "min_scale_z"), ("max_scale_x", "max_scale_y", "max_scale_z"),
                    (2047, 1023, 2047))
    col_step = step(("min_r", "min_g", "min_b"), ("max_r", "max_g", "max_b"), (255, 255, 255)) / SH_C0
    f64 = np.float64
    assert np.all(np.abs(ga.means.astype(f64) - gb.means) <= 0.01 * pos_step)
    log_a, log_b = np.log(ga.scales.astype(f64)), np.log(gb.scales.astype(f64))
    assert np.all(np.abs(log_a - log_b) <= 0.01 * scl_step)
    qa, qb = ga.quats.astype(f64), gb.quats.astype(f64)
    assert np.minimum(np.abs(qa - qb).max(1), np.abs(qa + qb).max(1)).max() <= 0.01 * np.sqrt(2) / 1023
    assert np.all(np.abs(ga.sh_dc.astype(f64) - gb.sh_dc) <= 0.01 * col_step + 1e-6)
    assert np.abs(ga.opacities.astype(f64) - gb.opacities).max() <= 0.01 / 255
    # the independent decoder writes +inf logits for alpha 255: the same Gaussians, saturated, in both
    assert a.repairs == b.repairs and a.repairs.opacity_saturated == 667


# --------------------------------------------------------------------------- reading rules and refusals

def inria_file(path, gs: GaussianSet, **columns):
    """An INRIA PLY of ``gs`` with some columns replaced (raw file values: logits, log scales)."""
    from plyfile import PlyData, PlyElement

    write_ply(gs, path)
    v = PlyData.read(str(path))["vertex"].data.copy()
    for k, (rows, value) in columns.items():
        v[k][rows] = value
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))
    return path


def gaussians(rng, n=400) -> GaussianSet:
    return GaussianSet(means=rng.normal(size=(n, 3)), scales=np.full((n, 3), 0.02),
                       quats=rng.normal(size=(n, 4)), opacities=np.full(n, 0.8), sh_dc=rng.normal(size=(n, 3)))


def test_trained_splat_extremes_are_read_by_the_stated_rules(tmp_path, rng):
    # +-inf opacity logits are opacity 1 / 0; a zero quaternion is the identity; a log scale of
    # +inf or 1e4 is clamped to the centres' bounding-box diagonal, -inf to 1e-9 of it; each counted
    gs = gaussians(rng)
    path = inria_file(tmp_path / "g.ply", gs, opacity=([0, 1, 2], [np.inf, np.inf, -np.inf]),
                      rot_0=([5], 0.0), rot_1=([5], 0.0), rot_2=([5], 0.0), rot_3=([5], 0.0),
                      scale_0=([7, 8], [np.inf, 1e4]), scale_2=([9], -np.inf))
    sf = read_splat(path)
    g = sf.gaussians
    assert sf.repairs.opacity_saturated == 3 and sf.repairs.zero_quaternions == 1 and sf.repairs.scales_clamped == 3
    assert g.opacities[0] == 1.0 and g.opacities[1] == 1.0 and g.opacities[2] == 0.0
    np.testing.assert_array_equal(g.quats[5], [1, 0, 0, 0])
    diag = np.linalg.norm(gs.means.max(0) - gs.means.min(0))
    np.testing.assert_allclose(g.scales[[7, 8], 0], diag, rtol=1e-6)
    np.testing.assert_allclose(g.scales[9, 2], 1e-9 * diag, rtol=1e-5)
    np.testing.assert_allclose(g.scales[10:], 0.02, rtol=1e-6)  # the others untouched


def one_line_error(capsys, argv):
    rc = cli_main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "Traceback" not in err, err
    return err


def test_bad_splats_get_one_line_naming_the_file_and_the_field(tmp_path, rng, capsys):
    n = 2 * CHUNK + 10
    good = tmp_path / "good.compressed.ply"
    write_compressed(good, *random_splat(rng, n))
    data = good.read_bytes()
    out = str(tmp_path / "obj.yaml")
    # a truncated compressed PLY
    cut = tmp_path / "cut.compressed.ply"
    cut.write_bytes(data[:len(data) - 100])
    err = one_line_error(capsys, ["asset", "init", str(cut), "-o", out])
    assert str(cut) in err and "field 'file'" in err
    # a header that lies: more vertices than its chunks can bound
    lying = tmp_path / "lying.compressed.ply"
    write_compressed(lying, *random_splat(rng, n), n_chunks=2)
    err = one_line_error(capsys, ["asset", "init", str(lying), "-o", out])
    assert str(lying) in err and "field 'chunk'" in err and "need 3" in err
    # a header that promises more vertices than the file holds
    head, body = data.split(b"end_header\n", 1)
    liar = tmp_path / "liar.compressed.ply"
    liar.write_bytes(head.replace(f"element vertex {n}".encode(), f"element vertex {n + 50}".encode())
                     + b"end_header\n" + body)
    err = one_line_error(capsys, ["asset", "init", str(liar), "-o", out])
    assert str(liar) in err and "field 'file'" in err
    # every Gaussian filtered out
    faint = inria_file(tmp_path / "faint.ply", gaussians(rng), opacity=(slice(None), -6.0))
    err = one_line_error(capsys, ["asset", "init", str(faint), "-o", out])
    assert str(faint) in err and "field 'opacity'" in err and "400 of the 400" in err
    # NaN scales
    nan = inria_file(tmp_path / "nan.ply", gaussians(rng), scale_1=([3, 4], np.nan))
    err = one_line_error(capsys, ["asset", "init", str(nan), "-o", out])
    assert str(nan) in err and "field 'scale_1'" in err and "2 NaN" in err
    assert not Path(out).exists()


# --------------------------------------------------------------------------- the scaffold

def upright_box(rng, n=3000, floaters=12):
    """Gaussians on the surface of a 0.3 x 1.0 x 0.4 box standing along -y (y down, as a
    3DGS/COLMAP capture), turned 30 degrees about y, with far floaters."""
    size = np.array([0.3, 1.0, 0.4])
    p = rng.uniform(-0.5, 0.5, size=(n, 3)) * size
    face = rng.integers(0, 3, n)
    p[np.arange(n), face] = np.sign(rng.normal(size=n)) * 0.5 * size[face]
    t = np.radians(30.0)
    rot = np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]])
    p = p @ rot.T + [2.0, -0.5, 1.0]
    far = rng.normal(size=(floaters, 3)) * 0.05 + [2.0, -0.5, 4.0]
    means = np.concatenate([p, far])
    m = len(means)
    return GaussianSet(means=means, scales=np.full((m, 3), 0.01), quats=np.tile([1.0, 0, 0, 0], (m, 1)),
                       opacities=np.full(m, 0.9), sh_dc=np.zeros((m, 3))), p


def test_scaffold_stands_an_upright_box_on_its_base_and_crops_its_floaters(tmp_path, rng):
    gs, body = upright_box(rng)
    splat = tmp_path / "scan" / "point_cloud.ply"
    splat.parent.mkdir()
    write_ply(gs, splat)
    out = tmp_path / "objects" / "box.yaml"
    out.parent.mkdir()
    s = scaffold_contract(splat, out)
    np.testing.assert_allclose(s.up, [0, -1, 0], atol=1e-12)  # the long axis, y down
    assert s.counts["floaters_removed"] == 12 and s.counts["kept"] == 3000
    out.write_text(contract_text(s))
    text = out.read_text()
    assert yaml.safe_load(text) == s.data  # the commented text is the data
    c = load_contract(out, "ci")
    assert c.asset.ply == splat.resolve()
    built = build_asset(c)
    p = built.gaussians.means.astype(np.float64)
    # normalized: the box's 1.0 height is the largest extent, along z now; its long horizontal axis (0.4) is x
    ext = p.max(0) - p.min(0)
    np.testing.assert_allclose(ext, [0.4, 0.3, 1.0], atol=0.02)
    assert len(built.gaussians) == 3000
    # the support holds the lowest slab of the body and nothing above it
    box = c.sim.boundaries[1].box
    held = box.contains(p)
    zmin = p[:, 2].min()
    assert np.all(held[p[:, 2] <= zmin + 0.09]) and not np.any(held[p[:, 2] > zmin + 0.1])
    # the camera sees the whole body: every centre projects inside the image
    from knockgs_core.experiments import camera_from_contract

    cam = camera_from_contract(c.camera)
    x = np.c_[p, np.ones(len(p))] @ np.asarray(cam.world_to_camera, np.float64).T
    u, v = cam.fx * x[:, 0] / x[:, 2] + cam.cx, cam.fy * x[:, 1] / x[:, 2] + cam.cy
    assert np.all(x[:, 2] > 0) and np.all((u > 0) & (u < cam.width) & (v > 0) & (v < cam.height))


def test_scaffold_up_override_and_a_flat_body(tmp_path, rng):
    gs, _ = upright_box(rng, floaters=0)
    splat = tmp_path / "box.ply"
    write_ply(gs, splat)
    s = scaffold_contract(splat, tmp_path / "side.yaml", up="x")
    assert s.up == (1.0, 0.0, 0.0) and s.up_rule == "given (--up)"
    # a flat body: its short axis is up, pointing to +z
    flat = GaussianSet(means=rng.uniform(-1, 1, (2000, 3)) * [1.0, 0.9, 0.3], scales=np.full((2000, 3), 0.01),
                       quats=np.tile([1.0, 0, 0, 0], (2000, 1)), opacities=np.full(2000, 0.9), sh_dc=np.zeros((2000, 3)))
    write_ply(flat, tmp_path / "flat.ply")
    assert scaffold_contract(tmp_path / "flat.ply", tmp_path / "flat.yaml").up == (0.0, 0.0, 1.0)
    with pytest.raises(InputError) as e:
        scaffold_contract(splat, tmp_path / "Bad-Name.yaml")
    assert e.value.field == "name"


@pytest.mark.parametrize("name, file, up", [("guitar", "guitar.compressed.ply", (0, -1, 0)),
                                            ("biker", "biker.compressed.ply", (0, -1, 0)),
                                            ("donut", "donut.ply", (0, 0, 1))])
def test_captures_scaffold_upright_and_build_at_ci(tmp_path, splats, name, file, up, capsys):
    # the up axes are the captures' own (seen in docs/figures/own_splat_*.png: the SuperSplat scenes are
    # y down, the donut z up)
    out = tmp_path / "objects" / f"{name}.yaml"
    out.parent.mkdir()
    assert cli_main(["asset", "init", str(splats / file), "-o", str(out)]) == 0
    assert f"up axis ({', '.join(f'{float(x):.3g}' for x in up)} in the splat's frame)" in out.read_text()
    c = load_contract(out, "ci")
    built = build_asset(c)
    s = built.summary()
    assert s["gs_particles"] > 2000 and s["particles"] < 20000
    # the support holds some particles, and not most of them
    held = c.sim.boundaries[1].box.contains(built.particles.positions)
    assert 0.005 < held.mean() < 0.2
