"""Procedural stand-ins for the paper's Pillow, Ficus and Vasedeck assets (private).

Each asset is designed in the normalized simulation domain (z up, largest extent 1,
centred at (1, 1, 1)) and emitted in a *capture frame*, as a reconstruction would be:
y up (design z -> capture y), in metres, translated. The object contracts undo this
with ``rotations: [{axis: x, degrees: 90}]`` and PhysGaussian's normalization, which
brings the Gaussians back to (almost exactly) the design coordinates, so contact boxes,
supports and regions in the contracts are written in design coordinates.

Surfaces are covered by flat, anisotropic Gaussians (two tangent standard deviations of
about half the local sample spacing, a normal one of a few percent of it) with colour
patterns (stripes, weave, bark, leaf veins, glaze motifs) so that rendering errors are
visible. About 1 % of the Gaussians are faint floaters (opacity < 0.02) that the
contracts' opacity threshold removes, as in a real reconstruction.

The geometry depends on ``seed`` only; ``n_gaussians`` sets how densely it is sampled,
so every profile of one seed shows the same object.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from knockgs_core.errors import InputError

from ._gaussians import SH_C0, GaussianSet, matrix_to_quat

__all__ = ["PROCEDURAL_ASSETS", "CAPTURE_ROTATION", "GENERATOR_VERSION", "make_procedural",
           "to_capture_frame"]

#: bumped whenever a generator's output changes (it enters the contract hash)
GENERATOR_VERSION = 2

PROCEDURAL_ASSETS = ("pillow", "ficus", "vasedeck")

#: contract rotation that maps the capture frame (y up) back to the design frame (z up)
CAPTURE_ROTATION = (("x", 90.0),)

# capture-frame scale [m per design unit] and translation [m] of each asset
_CAPTURE = {
    "pillow": (0.9, (0.20, 0.45, -0.30)),
    "ficus": (0.8, (-0.10, 0.40, 0.25)),
    "vasedeck": (0.6, (0.30, 0.30, 0.10)),
}
_FLOATER_FRACTION = 0.01
_TANGENT = 0.55   # tangent standard deviation / sample spacing
_NORMAL = 0.06    # normal standard deviation / sample spacing


# --------------------------------------------------------------------------- helpers

def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def _frames(normals: np.ndarray, pref: np.ndarray) -> np.ndarray:
    """Right-handed frames [m, 3, 3] with columns (t1, t2, n); t1 is ``pref`` projected
    onto the tangent plane (another axis where ``pref`` is nearly normal)."""
    n = _unit(normals)
    pref = np.broadcast_to(np.asarray(pref, np.float64), n.shape)
    t1 = pref - np.sum(pref * n, axis=1, keepdims=True) * n
    bad = np.linalg.norm(t1, axis=1) < 1e-6
    if np.any(bad):
        alt = np.where(np.abs(n[bad, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        t1[bad] = alt - np.sum(alt * n[bad], axis=1, keepdims=True) * n[bad]
    t1 = _unit(t1)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=2)


@dataclass
class _Samples:
    points: np.ndarray   # [m, 3] design frame
    frames: np.ndarray   # [m, 3, 3] columns (t1, t2, n)
    scales: np.ndarray   # [m, 3] along (t1, t2, n)
    colors: np.ndarray   # [m, 3] RGB in [0, 1]


@dataclass
class _Part:
    """A surface: its area, a relative sampling density and a sampler."""

    area: float
    sample: Callable[[int, np.random.Generator, float], _Samples]
    density: float = 1.0


def _surface_scales(m: int, spacing: float, rng: np.random.Generator) -> np.ndarray:
    jitter = 1.0 + 0.25 * (rng.random((m, 2)) - 0.5)
    return np.column_stack([_TANGENT * spacing * jitter, np.full(m, _NORMAL * spacing)])


def _noise(colors: np.ndarray, rng: np.random.Generator, amount: float = 0.03) -> np.ndarray:
    return np.clip(colors + amount * (rng.random((len(colors), 1)) - 0.5) * 2, 0.0, 1.0)


def _rect(origin, u, v, color_fn) -> _Part:
    """A rectangle ``origin + s u + t v`` (s, t in [0, 1]); normal ``u x v``."""
    origin, u, v = (np.asarray(a, np.float64) for a in (origin, u, v))
    lu, lv = np.linalg.norm(u), np.linalg.norm(v)
    normal = _unit(np.cross(u, v))

    def sample(m, rng, spacing):
        st = rng.random((m, 2))
        p = origin + st[:, :1] * u + st[:, 1:] * v
        frames = _frames(np.tile(normal, (m, 1)), u)
        return _Samples(p, frames, _surface_scales(m, spacing, rng),
                        color_fn(p, st[:, 0] * lu, st[:, 1] * lv, rng))

    return _Part(lu * lv, sample)


def _box_faces(lo, hi, color_fn, *, skip=()) -> list[_Part]:
    """The six outward faces of the box [lo, hi] (names in ``skip`` left out:
    '-x', '+x', '-y', '+y', '-z', '+z')."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    d = hi - lo
    ex, ey, ez = np.diag(d)
    faces = {
        "-x": (lo, ez, ey), "+x": (lo + ex, ey, ez),
        "-y": (lo, ex, ez), "+y": (lo + ey, ez, ex),
        "-z": (lo, ey, ex), "+z": (lo + ez, ex, ey),
    }
    return [_rect(o, u, v, color_fn) for k, (o, u, v) in faces.items() if k not in skip]


def _revolution(center_xy, rz: np.ndarray, color_fn) -> _Part:
    """Surface of revolution of the polyline ``rz`` [k, 2] of (radius, z) about the
    vertical axis through ``center_xy``; the normal is (dz, -dr) of the polyline."""
    cx, cy = center_xy
    r0, z0 = rz[:-1, 0], rz[:-1, 1]
    dr, dz = np.diff(rz[:, 0]), np.diff(rz[:, 1])
    length = np.hypot(dr, dz)
    seg_area = np.pi * (2 * r0 + dr) * length
    keep = seg_area > 0
    r0, z0, dr, dz, length, seg_area = (a[keep] for a in (r0, z0, dr, dz, length, seg_area))
    arclen = np.concatenate([[0.0], np.cumsum(length)])

    def sample(m, rng, spacing):
        seg = rng.choice(len(seg_area), size=m, p=seg_area / seg_area.sum())
        u = rng.random(m)
        a, b = r0[seg], r0[seg] + dr[seg]
        lin = np.abs(b - a) > 1e-12
        t = u.copy()
        t[lin] = (np.sqrt(a[lin] ** 2 + u[lin] * (b[lin] ** 2 - a[lin] ** 2)) - a[lin]) / (b[lin] - a[lin])
        r = a + t * dr[seg]
        z = z0[seg] + t * dz[seg]
        phi = rng.random(m) * 2 * np.pi
        c, s = np.cos(phi), np.sin(phi)
        p = np.column_stack([cx + r * c, cy + r * s, z])
        L = length[seg]
        normal = np.column_stack([dz[seg] / L * c, dz[seg] / L * s, -dr[seg] / L])
        merid = np.column_stack([dr[seg] / L * c, dr[seg] / L * s, dz[seg] / L])
        frames = _frames(normal, merid)
        s_arc = arclen[seg] + t * L
        return _Samples(p, frames, _surface_scales(m, spacing, rng),
                        color_fn(p, r, phi, s_arc, rng))

    return _Part(float(seg_area.sum()), sample)


def _tube(points: np.ndarray, radii: np.ndarray, color_fn) -> _Part:
    """A tube along the polyline ``points`` [k, 3] with radii [k] (linear taper)."""
    p0, d = points[:-1], np.diff(points, axis=0)
    length = np.linalg.norm(d, axis=1)
    rbar = 0.5 * (radii[:-1] + radii[1:])
    seg_area = 2 * np.pi * rbar * length
    axis = _unit(d)
    b1 = _frames(axis, np.array([0.0, 0.0, 1.0]))[:, :, 0]
    b2 = np.cross(axis, b1)
    arclen = np.concatenate([[0.0], np.cumsum(length)])

    def sample(m, rng, spacing):
        seg = rng.choice(len(seg_area), size=m, p=seg_area / seg_area.sum())
        t = rng.random(m)
        phi = rng.random(m) * 2 * np.pi
        r = radii[seg] + t * (radii[seg + 1] - radii[seg])
        e = np.cos(phi)[:, None] * b1[seg] + np.sin(phi)[:, None] * b2[seg]
        p = p0[seg] + t[:, None] * d[seg] + r[:, None] * e
        frames = _frames(e, axis[seg])
        sc = _surface_scales(m, spacing, rng)
        sc[:, 1] = np.minimum(sc[:, 1], 0.8 * r)
        sc[:, 2] = np.minimum(sc[:, 2], 0.3 * r)
        return _Samples(p, frames, sc, color_fn(p, arclen[seg] + t * length[seg], phi, rng))

    return _Part(float(seg_area.sum()), sample)


def _allocate(weights: np.ndarray, n: int) -> np.ndarray:
    """Integer counts summing to ``n``, proportional to ``weights`` (largest remainder)."""
    share = weights / weights.sum() * n
    counts = np.floor(share).astype(np.int64)
    order = np.argsort(-(share - counts), kind="stable")
    counts[order[: n - counts.sum()]] += 1
    return counts


def _assemble(parts: list[_Part], n: int, seed: int, name: str) -> GaussianSet:
    """Sample ``n`` Gaussians (1 % floaters) over ``parts`` and emit the capture frame."""
    n_float = int(round(_FLOATER_FRACTION * n))
    counts = _allocate(np.array([p.area * p.density for p in parts]), n - n_float)
    chunks = []
    for i, (part, m) in enumerate(zip(parts, counts)):
        if m == 0:
            continue
        rng = np.random.default_rng([seed, 1, i])
        spacing = float(np.sqrt(part.area / m))
        chunks.append(part.sample(int(m), rng, spacing))
    pts = np.concatenate([c.points for c in chunks])
    frames = np.concatenate([c.frames for c in chunks])
    scales = np.concatenate([c.scales for c in chunks])
    colors = np.concatenate([c.colors for c in chunks])
    rng = np.random.default_rng([seed, 2])
    opac = 0.93 + 0.06 * rng.random(len(pts))
    if n_float:
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        mid, half = 0.5 * (lo + hi), 0.6 * (hi - lo)
        fp = mid + (2 * rng.random((n_float, 3)) - 1) * half
        pts = np.concatenate([pts, fp])
        frames = np.concatenate([frames, np.tile(np.eye(3), (n_float, 1, 1))])
        scales = np.concatenate([scales, np.full((n_float, 3), 0.01) * (1 + rng.random((n_float, 3)))])
        colors = np.concatenate([colors, rng.random((n_float, 3))])
        opac = np.concatenate([opac, 0.002 + 0.012 * rng.random(n_float)])
    s, t = _CAPTURE[name]
    rot = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # about x by -90 deg
    means = (pts - 1.0) @ rot.T * s + np.asarray(t)
    quats = matrix_to_quat(np.einsum("ij,njk->nik", rot, frames))
    sh_dc = (np.clip(colors, 0.0, 1.0) - 0.5) / SH_C0
    return GaussianSet(means, scales * s, quats, opac, sh_dc, np.zeros((len(means), 0, 3)))


def to_capture_frame(name: str, design_points) -> np.ndarray:
    """Design-frame points [N, 3] of procedural asset ``name`` in its capture frame."""
    s, t = _CAPTURE[name]
    rot = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    return (np.asarray(design_points, np.float64) - 1.0) @ rot.T * s + np.asarray(t)


# --------------------------------------------------------------------------- pillow

def _pillow_parts(seed: int) -> list[_Part]:
    # basket (support): outer [0.5, 1.5] x [0.62, 1.38] x [0.64, 1.14], walls 0.05 thick,
    # floor top at z = 0.97; the cushion (bottom 0.98) rests on it, 0.05 from the walls.
    x0, x1, y0, y1, z0, zr, zf, w = 0.5, 1.5, 0.62, 1.38, 0.64, 1.14, 0.97, 0.05
    light, dark, gap = np.array([0.64, 0.47, 0.26]), np.array([0.47, 0.32, 0.16]), np.array([0.28, 0.18, 0.09])

    def weave(p, a, b, rng):
        cell = 0.05
        ia, ib = np.floor(a / cell), np.floor(b / cell)
        col = np.where(((ia + ib) % 2 == 0)[:, None], light, dark)
        edge = (np.minimum(a / cell - ia, b / cell - ib) < 0.12)
        col = np.where(edge[:, None], gap, col)
        return _noise(col, rng, 0.04)

    def rim(p, a, b, rng):
        return _noise(np.tile([0.40, 0.26, 0.13], (len(p), 1)), rng, 0.03)

    parts = _box_faces((x0, y0, z0), (x1, y1, zr), weave, skip=("+z",))
    xi0, xi1, yi0, yi1 = x0 + w, x1 - w, y0 + w, y1 - w
    # rim top (four strips), inner walls (facing inwards), floor top
    parts += [
        _rect((x0, y0, zr), (x1 - x0, 0, 0), (0, w, 0), rim),
        _rect((x0, yi1, zr), (x1 - x0, 0, 0), (0, w, 0), rim),
        _rect((x0, yi0, zr), (w, 0, 0), (0, yi1 - yi0, 0), rim),
        _rect((xi1, yi0, zr), (w, 0, 0), (0, yi1 - yi0, 0), rim),
        _rect((xi0, yi0, zf), (0, 0, zr - zf), (0, yi1 - yi0, 0), weave),     # inner -x wall, faces +x
        _rect((xi1, yi0, zf), (0, yi1 - yi0, 0), (0, 0, zr - zf), weave),     # inner +x wall, faces -x
        _rect((xi0, yi0, zf), (xi1 - xi0, 0, 0), (0, 0, zr - zf), weave),     # inner -y wall, faces +y
        _rect((xi0, yi1, zf), (0, 0, zr - zf), (xi1 - xi0, 0, 0), weave),     # inner +y wall, faces -y
        _rect((xi0, yi0, zf), (xi1 - xi0, 0, 0), (0, yi1 - yi0, 0), weave),   # floor top
    ]
    for part in parts:   # the static support is sampled at half the cushion's density
        part.density = 0.5
    parts.append(_cushion(center=(1.0, 1.0, 1.17), half=(0.40, 0.28, 0.19), e_vert=0.45, e_horiz=0.3))
    return parts


def _cushion(center, half, e_vert, e_horiz) -> _Part:
    """A superellipsoid cushion: striped fabric, piping along the side seam, tufts on top."""
    c = np.asarray(center, np.float64)
    a = np.asarray(half, np.float64)

    def F(q):  # inside-outside function, homogeneous of degree 2 / e_vert
        x, y, z = (np.abs(q[:, i] / a[i]) for i in range(3))
        return (x ** (2 / e_horiz) + y ** (2 / e_horiz)) ** (e_horiz / e_vert) + z ** (2 / e_vert)

    def surface(dirs):
        r = F(dirs) ** (-e_vert / 2)
        q = dirs * r[:, None]
        eps = 1e-6
        grad = np.stack([(F(q + eps * e) - F(q - eps * e)) / (2 * eps) for e in np.eye(3)], axis=1)
        return q, _unit(grad), r

    # area by Monte Carlo over directions (fixed, seed-independent)
    d = _unit(np.random.default_rng(12345).normal(size=(200000, 3)))
    _, nrm, r = surface(d)
    w = r ** 2 / np.maximum(np.sum(d * nrm, axis=1), 1e-6)
    area = float(4 * np.pi * w.mean())
    stripe_a, stripe_b = np.array([0.94, 0.89, 0.78]), np.array([0.16, 0.46, 0.52])
    piping, button = np.array([0.58, 0.10, 0.12]), np.array([0.12, 0.12, 0.18])
    tufts = np.array([[x, y] for x in (0.78, 1.0, 1.22) for y in (0.88, 1.12)])

    def sample(m, rng, spacing):
        dirs = _unit(rng.normal(size=(4 * m, 3)))
        q, nrm, r = surface(dirs)
        w = r ** 2 / np.maximum(np.sum(dirs * nrm, axis=1), 1e-6)
        pick = rng.choice(len(w), size=m, replace=False, p=w / w.sum())
        q, nrm = q[pick], nrm[pick]
        p = q + c
        frames = _frames(nrm, np.array([1.0, 0.0, 0.0]))
        stripe = (np.floor((p[:, 0] - c[0] + a[0]) / 0.08) % 2 == 0)
        col = np.where(stripe[:, None], stripe_a, stripe_b)
        seam = (np.abs(q[:, 2]) < 0.012) & (np.abs(nrm[:, 2]) < 0.6)
        col = np.where(seam[:, None], piping, col)
        dist = np.min(np.linalg.norm(p[:, None, :2] - tufts[None], axis=2), axis=1)
        col = np.where(((dist < 0.022) & (nrm[:, 2] > 0.5))[:, None], button, col)
        return _Samples(p, frames, _surface_scales(m, spacing, rng), _noise(col, rng, 0.03))

    return _Part(area, sample)


# --------------------------------------------------------------------------- ficus

def _ficus_parts(seed: int) -> list[_Part]:
    geo = np.random.default_rng([seed, 0])
    terracotta, band, ring = np.array([0.72, 0.38, 0.22]), np.array([0.82, 0.52, 0.33]), np.array([0.50, 0.22, 0.13])
    soil = np.array([0.24, 0.16, 0.09])

    # pot profile (radius, z): bottom, outer wall, lip, rim top, inner wall, soil
    pot = np.array([[0.0, 0.5], [0.12, 0.5], [0.155, 0.735], [0.172, 0.742], [0.172, 0.78],
                    [0.152, 0.78], [0.150, 0.76], [0.0, 0.76]])

    def pot_color(p, r, phi, s, rng):
        z = p[:, 2]
        col = np.tile(terracotta, (len(p), 1))
        col[(z > 0.735) & (r > 0.151)] = band
        col[np.abs(z - 0.62) < 0.012] = ring
        is_soil = (np.abs(z - 0.76) < 1e-9) & (r < 0.1505)
        speck = rng.random(len(p)) < 0.15
        col[is_soil] = np.where(speck[is_soil, None], soil * 1.6, soil)
        col[(r < 0.1505) & (z > 0.76)] = ring * 0.8   # inner wall above the soil
        return _noise(col, rng, 0.03)

    parts = [_revolution((1.0, 1.0), pot, pot_color)]
    parts[0].density = 0.6

    def bark(p, s, phi, rng):
        light = (np.sin(40 * s + 3 * phi) > 0.3)
        col = np.where(light[:, None], [0.45, 0.32, 0.20], [0.33, 0.22, 0.13])
        return _noise(col, rng, 0.03)

    # trunk with an S curve, then a leader to the top
    zt = np.linspace(0.74, 1.495, 18)
    trunk = np.column_stack([1.0 + 0.025 * np.sin((zt - 0.74) * 7.0), 1.0 - 0.015 * np.sin((zt - 0.74) * 5.0), zt])
    parts.append(_tube(trunk, np.linspace(0.024, 0.008, len(zt)), bark))
    parts[-1].density = 1.5

    leaves = []
    n_branch = 7
    golden = np.pi * (3 - np.sqrt(5))
    for k in range(n_branch):
        zb = 0.92 + 0.17 * k / (n_branch - 1) + 0.01 * geo.standard_normal()
        i0 = np.searchsorted(zt, zb)
        start = trunk[min(i0, len(zt) - 1)].copy()
        start[2] = zb
        az = k * golden + 0.3 * geo.standard_normal()
        reach = geo.uniform(0.20, 0.31)
        rise = geo.uniform(0.10, 0.24)
        out = np.array([np.cos(az), np.sin(az), 0.0])
        ctrl = start + 0.5 * reach * out + np.array([0, 0, rise * 0.9])
        end = start + reach * out + np.array([0, 0, rise])
        t = np.linspace(0, 1, 10)[:, None]
        curve = (1 - t) ** 2 * start + 2 * (1 - t) * t * ctrl + t ** 2 * end
        parts.append(_tube(curve, np.linspace(0.010, 0.004, 10), bark))
        parts[-1].density = 1.5
        # leaves along the outer 60 % of the branch and at the tip
        for j in range(13):
            tt = 0.4 + 0.6 * j / 12
            base = (1 - tt) ** 2 * start + 2 * (1 - tt) * tt * ctrl + tt ** 2 * end
            leaves.append(_leaf(geo, base, out))
    # leaves around the leader (z 1.2 .. 1.4)
    for j in range(14):
        base = trunk[np.searchsorted(zt, 1.2 + 0.2 * j / 13)]
        az = geo.uniform(0, 2 * np.pi)
        leaves.append(_leaf(geo, base, np.array([np.cos(az), np.sin(az), 0.0]), up=0.5))
    # a horizontal apex leaf: its flat blade is the highest point (z = 1.5 exactly), so
    # the normalized height, and with it the scale, does not depend on the sampling
    top = trunk[-1]
    leaves.append({"center": np.array([top[0] + 0.03, top[1], 1.5]), "u": np.array([1.0, 0.0, 0.0]),
                   "v": np.array([0.0, 1.0, 0.0]), "a": 0.036, "b": 0.017,
                   "color": np.array([0.26, 0.56, 0.20])})
    parts.append(_leaves_part(leaves))
    # centre the plant: the leaves' analytic x/y extents -> (1, 1), so the normalization
    # (bounding-box centre) keeps the pot on the axis whatever the branch layout
    ext = np.array([np.abs(lf["u"]) * lf["a"] + np.abs(lf["v"]) * lf["b"] for lf in leaves])
    ctr = np.array([lf["center"] for lf in leaves])
    lo, hi = (ctr - ext).min(axis=0), (ctr + ext).max(axis=0)
    shift = np.array([1.0 - 0.5 * (lo[0] + hi[0]), 1.0 - 0.5 * (lo[1] + hi[1]), 0.0])
    return [_translated(part, shift) for part in parts]


def _translated(part: _Part, shift: np.ndarray) -> _Part:
    def sample(m, rng, spacing):
        out = part.sample(m, rng, spacing)
        out.points = out.points + shift
        return out

    return _Part(part.area, sample, part.density)


def _leaf(geo: np.random.Generator, base: np.ndarray, out: np.ndarray, up: float = 0.0) -> dict:
    """One ficus leaf hanging off ``base``: an ellipse drooping outwards."""
    az = np.arctan2(out[1], out[0]) + geo.normal(0, 0.9)
    droop = geo.uniform(-0.7, 0.2) + up
    u = np.array([np.cos(az) * np.cos(droop), np.sin(az) * np.cos(droop), np.sin(droop)])
    side = _unit(np.cross(u, [0.0, 0.0, 1.0]) + 1e-9)
    roll = geo.normal(0, 0.5)
    side = np.cos(roll) * side + np.sin(roll) * np.cross(u, side)
    a, b = geo.uniform(0.030, 0.042), geo.uniform(0.014, 0.019)
    center = base + (a + 0.006) * u
    palette = np.array([[0.16, 0.42, 0.14], [0.22, 0.52, 0.18], [0.12, 0.34, 0.12], [0.30, 0.58, 0.20]])
    return {"center": center, "u": u, "v": side, "a": a, "b": b,
            "color": palette[geo.integers(len(palette))]}


def _leaves_part(leaves: list[dict]) -> _Part:
    centers = np.array([lf["center"] for lf in leaves])
    us = np.array([lf["u"] for lf in leaves])
    vs = np.array([lf["v"] for lf in leaves])
    ab = np.array([[lf["a"], lf["b"]] for lf in leaves])
    base_col = np.array([lf["color"] for lf in leaves])
    areas = np.pi * ab[:, 0] * ab[:, 1]

    def sample(m, rng, spacing):
        k = rng.choice(len(leaves), size=m, p=areas / areas.sum())
        rho, th = np.sqrt(rng.random(m)), rng.random(m) * 2 * np.pi
        x, y = rho * np.cos(th), rho * np.sin(th)
        width = 1.0 - 0.35 * np.clip(x, 0, None)   # tapering towards the tip
        p = centers[k] + (ab[k, 0] * x)[:, None] * us[k] + (ab[k, 1] * y * width)[:, None] * vs[k]
        nrm = np.cross(us[k], vs[k])
        frames = _frames(nrm, us[k])
        col = base_col[k].copy()
        col[np.abs(y * width) < 0.12] += 0.14                         # midrib
        tip = np.clip((x - 0.7) / 0.3, 0, 1)[:, None]
        col = col * (1 - 0.5 * tip) + 0.5 * tip * np.array([0.55, 0.62, 0.22])
        return _Samples(p, frames, _surface_scales(m, spacing, rng), _noise(col, rng, 0.04))

    return _Part(float(areas.sum()), sample)


# --------------------------------------------------------------------------- vasedeck

def _vasedeck_parts(seed: int) -> list[_Part]:
    from scipy.interpolate import PchipInterpolator

    geo = np.random.default_rng([seed, 0])
    # deck: planks along x, [0.5, 1.5] x [0.62, 1.38] x [0.6, 0.7]
    n_plank = 6
    tones = np.array([[0.60, 0.42, 0.26], [0.67, 0.48, 0.30], [0.55, 0.38, 0.22]])
    plank_tone = tones[geo.integers(len(tones), size=n_plank)]
    phase = geo.uniform(0, 2 * np.pi, size=n_plank)
    y0, y1 = 0.62, 1.38

    def planks(p, a, b, rng):
        w = (y1 - y0) / n_plank
        k = np.clip(np.floor((p[:, 1] - y0) / w).astype(int), 0, n_plank - 1)
        frac = (p[:, 1] - y0) / w - k
        grain = 0.05 * np.sin(60 * p[:, 0] + 9 * np.sin(7 * p[:, 0] + phase[k]) + phase[k])
        col = plank_tone[k] * (1 + grain[:, None])
        col[(frac < 0.06) | (frac > 0.94)] = [0.20, 0.14, 0.08]
        return _noise(col, rng, 0.03)

    def deck_side(p, a, b, rng):
        return _noise(np.tile([0.42, 0.29, 0.17], (len(p), 1)), rng, 0.03)

    parts = [_rect((0.5, y0, 0.7), (1.0, 0, 0), (0, y1 - y0, 0), planks)]
    parts += _box_faces((0.5, y0, 0.6), (1.5, y1, 0.7), deck_side, skip=("+z",))
    for part in parts:   # the static deck is sampled at half the vase's density
        part.density = 0.5

    # vase of revolution standing on the deck at (1, 1), bottom at z = 0.71
    zc = np.array([0.71, 0.74, 0.80, 0.92, 1.02, 1.12, 1.22, 1.30, 1.37, 1.40])
    rc = np.array([0.090, 0.100, 0.145, 0.172, 0.165, 0.120, 0.065, 0.058, 0.075, 0.090])
    zz = np.linspace(0.71, 1.40, 120)
    outer = np.column_stack([PchipInterpolator(zc, rc)(zz), zz])
    prof = np.concatenate([[[0.0, 0.71]], outer,
                           [[0.078, 1.40], [0.070, 1.36], [0.060, 1.34], [0.0, 1.34]]])
    # arc length where the outer surface ends and the lip / mouth begins
    s_outer = float(np.sum(np.hypot(*np.diff(prof[: len(outer) + 1], axis=0).T)))
    white, blue, inside = np.array([0.93, 0.94, 0.96]), np.array([0.12, 0.22, 0.62]), np.array([0.08, 0.08, 0.11])

    def glaze(p, r, phi, s, rng):
        z = p[:, 2]
        col = np.tile(white, (len(p), 1))
        motif = np.abs(np.sin(5 * phi + 14 * (z - 0.8))) > 0.8
        body = (z > 0.82) & (z < 1.14)
        col[body & motif] = blue
        col[(np.abs(z - 0.79) < 0.012) | (np.abs(z - 1.17) < 0.012)] = blue
        col[(z > 1.22) & (z < 1.33)] = blue * 1.15
        col[z < 0.745] = blue * 0.8
        col[s > s_outer + 0.013] = inside                 # mouth: inner wall and floor
        return _noise(col, rng, 0.025)

    parts.append(_revolution((1.0, 1.0), prof, glaze))
    return parts


_BUILDERS = {"pillow": _pillow_parts, "ficus": _ficus_parts, "vasedeck": _vasedeck_parts}


def make_procedural(name: str, *, n_gaussians: int, seed: int) -> GaussianSet:
    """A procedural 3DGS asset in its capture frame (see the module docstring).

    ``name`` in :data:`PROCEDURAL_ASSETS`; ``n_gaussians`` Gaussians in all (about 1 %
    faint floaters); deterministic from ``seed`` (same arrays, same PLY bytes).
    Use ``rotations=CAPTURE_ROTATION`` in :func:`preprocess` to recover the design frame.
    """
    if name not in _BUILDERS:
        raise InputError("make_procedural", "name",
                         f"unknown procedural asset {name!r}; choose one of {', '.join(PROCEDURAL_ASSETS)}")
    if isinstance(n_gaussians, bool) or int(n_gaussians) != n_gaussians or int(n_gaussians) < 100:
        raise InputError("make_procedural", "n_gaussians", f"must be an integer >= 100, got {n_gaussians!r}")
    return _assemble(_BUILDERS[name](int(seed)), int(n_gaussians), int(seed), name)
