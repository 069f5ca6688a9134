"""Structured tetrahedral meshes of boxes and the axis-aligned regions that select their nodes.

A box is split into a tensor grid of hexahedra, each cut into six tetrahedra
(:meth:`skfem.MeshTet.init_tensor`): a conforming mesh whose element faces lie on the grid
planes, so a support face or a block face on a grid plane is meshed exactly. The grid
coordinates per axis may be non-uniform (e.g. one thick layer inside a held support and a
fine grid in the free body). A plate whose width tapers linearly is the same grid with its
y coordinates scaled per x (:func:`tapered_plate_mesh`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import skfem

from ..errors import InputError

__all__ = ["Region", "tensor_mesh", "box_mesh", "mesh_size", "tapered_plate_mesh", "level_set_mesh"]

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class Region:
    """Closed axis-aligned box ``[lo, hi]`` [m] (both length-3) that selects nodes or elements.

    Plain geometry only: :meth:`from_center` reads any object with ``center`` and
    ``half_size`` (e.g. a simulator box), so the two solvers share box data, not code."""

    lo: Vec3
    hi: Vec3

    def __post_init__(self):
        lo, hi = np.asarray(self.lo, dtype=float), np.asarray(self.hi, dtype=float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi)):
            raise InputError("fem.Region", "lo/hi", f"need two finite length-3 corners, got {self.lo!r}, {self.hi!r}")
        if np.any(hi < lo):
            raise InputError("fem.Region", "hi", f"hi {self.hi!r} is below lo {self.lo!r} on some axis")

    @classmethod
    def from_center(cls, center: Sequence[float], half_size: Sequence[float]) -> "Region":
        c, h = np.asarray(center, dtype=float), np.asarray(half_size, dtype=float)
        return cls(tuple(map(float, c - h)), tuple(map(float, c + h)))

    def contains(self, points, *, tol: float = 1e-9) -> np.ndarray:
        """Boolean mask of ``points`` (shape (n, 3)) inside the closed box, widened by ``tol`` [m]."""
        p = np.asarray(points, dtype=np.float64)
        return np.all((p >= np.asarray(self.lo) - tol) & (p <= np.asarray(self.hi) + tol), axis=1)


def tensor_mesh(xs: Sequence[float], ys: Sequence[float], zs: Sequence[float]) -> skfem.MeshTet:
    """Tetrahedral mesh of the tensor grid with node coordinates ``xs``, ``ys``, ``zs`` [m]
    (each strictly increasing, at least two values): six tetrahedra per grid cell."""
    axes = []
    for name, values in zip("xyz", (xs, ys, zs)):
        a = np.asarray(values, dtype=np.float64)
        if a.ndim != 1 or a.size < 2 or not np.all(np.isfinite(a)) or np.any(np.diff(a) <= 0):
            raise InputError("fem.tensor_mesh", name, "need at least two strictly increasing finite coordinates")
        axes.append(a)
    return skfem.MeshTet.init_tensor(*axes)


def mesh_size(lo: Sequence[float], hi: Sequence[float], h: float) -> tuple[int, int, int]:
    """Cells per axis so that the cell edge is at most ``h`` [m] on every axis of ``[lo, hi]``."""
    if not (h > 0):
        raise InputError("fem.mesh_size", "h", f"need h > 0 [m], got {h!r}")
    ext = np.asarray(hi, dtype=float) - np.asarray(lo, dtype=float)
    return tuple(max(1, int(np.ceil(e / h - 1e-9))) for e in ext)


def box_mesh(lo: Sequence[float], hi: Sequence[float], cells: int | Sequence[int]) -> skfem.MeshTet:
    """Uniform structured tetrahedral mesh of the box ``[lo, hi]`` [m] with ``cells`` grid
    cells per axis (one number for all three axes, or three)."""
    n = (int(cells),) * 3 if np.ndim(cells) == 0 else tuple(int(c) for c in cells)
    if len(n) != 3 or min(n) < 1:
        raise InputError("fem.box_mesh", "cells", f"need one or three positive cell counts, got {cells!r}")
    return tensor_mesh(*(np.linspace(a, b, k + 1) for a, b, k in zip(lo, hi, n)))


def tapered_plate_mesh(length: float, root_width: float, tip_width: float, thickness: float,
                       cells: Sequence[int]) -> skfem.MeshTet:
    """Tetrahedral mesh of a plate along x whose width tapers linearly, symmetric about y = 0:
    x in [0, ``length``], |y| <= w(x) / 2 with w(0) = ``root_width`` and w(length) =
    ``tip_width``, z in [-``thickness`` / 2, ``thickness`` / 2] [m]. ``cells`` = (along x,
    across y, through z). The tensor mesh of [0, length] x [-1/2, 1/2] x [-thickness/2,
    thickness/2] with every node's y scaled by w(x): the tapered edges are straight lines
    through the grid nodes, so the straight-sided tetrahedra fill the plate exactly, and the
    mid-plane z = 0 is a grid plane when the number of layers through z is even."""
    n = tuple(int(c) for c in np.ravel(cells))
    if len(n) != 3 or min(n) < 1:
        raise InputError("fem.tapered_plate_mesh", "cells", f"need three positive cell counts, got {cells!r}")
    dims = np.array([length, root_width, tip_width, thickness], dtype=float)
    if not (np.all(np.isfinite(dims)) and np.all(dims > 0)):
        raise InputError("fem.tapered_plate_mesh", "length/widths/thickness",
                         f"need finite positive sizes [m], got {length!r}, {root_width!r}, {tip_width!r}, {thickness!r}")
    grid = tensor_mesh(np.linspace(0.0, length, n[0] + 1), np.linspace(-0.5, 0.5, n[1] + 1),
                       np.linspace(-thickness / 2, thickness / 2, n[2] + 1))
    p = grid.p.copy()
    p[1] *= root_width + (tip_width - root_width) * p[0] / length
    return skfem.MeshTet(p, grid.t)


#: The prism's symmetries that bring each of its six vertices to position 0 (bottom triangle
#: 0 1 2, top 3 4 5, vertical edges 0-3, 1-4, 2-5)
_PRISM_TURNS = np.array([[0, 1, 2, 3, 4, 5], [1, 2, 0, 4, 5, 3], [2, 0, 1, 5, 3, 4],
                         [3, 5, 4, 0, 2, 1], [4, 3, 5, 1, 0, 2], [5, 4, 3, 2, 1, 0]])


def _split_prisms(g: np.ndarray) -> np.ndarray:
    """Three tetrahedra [3 K, 4] of each prism of global vertex indices ``g`` [K, 6], cut so that
    each quadrilateral face's diagonal runs through its smallest index: two prisms (or a prism
    and a neighbour cut the same way) that share a face cut it alike, so the mesh conforms
    (Dompierre et al. 1999, "How to subdivide pyramids, prisms and hexahedra into tetrahedra")."""
    q = np.take_along_axis(g, _PRISM_TURNS[np.argmin(g, axis=1)], axis=1)
    first = np.minimum(q[:, 1], q[:, 5]) < np.minimum(q[:, 2], q[:, 4])
    a = np.where(first[:, None], q[:, [0, 1, 2, 5]], q[:, [0, 1, 2, 4]])
    b = np.where(first[:, None], q[:, [0, 1, 5, 4]], q[:, [0, 4, 2, 5]])
    c = q[:, [0, 4, 5, 3]]
    return np.concatenate([a, b, c])


def level_set_mesh(distance: Callable[[np.ndarray], np.ndarray], lo: Sequence[float], hi: Sequence[float], h: float,
                   *, snap: float = 0.3, planes: Sequence[tuple[int, float]] = ()) -> skfem.MeshTet:
    """Tetrahedral mesh of the body ``{x : distance(x) > 0}`` inside the box ``[lo, hi]`` [m],
    its boundary following the level set (marching tetrahedra with snapped vertices).

    ``distance``: points [P, 3] m -> [P] signed distance from the body's surface [m], positive
    inside (a distance, slope about 1, so that its linear interpolation along an edge places
    the surface to second order in ``h``). The box is cut into cubes of edge at most ``h``, six
    tetrahedra each (:func:`tensor_mesh`). A vertex closer to the surface than ``snap * h`` is
    moved onto it (one Newton step along the distance's gradient), so that no cut falls close
    to a vertex and no element is a sliver; a tetrahedron's vertex moves by less than the
    tetrahedron's smallest height (``h / sqrt(2)``) even where all four move, for ``snap`` < 0.35,
    so none turns over (on the uniform grid: beside a moved plane, below, a cell may be half as
    thick, and the bound is not kept there).
    A tetrahedron with every vertex inside or on the surface is kept, one with none inside
    dropped, and a cut one keeps its inside part: a tetrahedron (one vertex inside) or a prism
    (two or three), cut into three tetrahedra by :func:`_split_prisms` (a prism with a vertex
    on the surface loses the tetrahedra it makes flat). The surface meets each cut edge where
    the distance interpolated along it is zero, at a point shared by every element around the
    edge, so the mesh conforms. ``planes``: (axis, coordinate [m]) pairs, e.g. a support box's
    faces: the grid line nearest each is moved onto it (cells of 0.5-1.5 ``h`` beside it) and its
    vertices are snapped within it, so that the mesh has a face there and what lies on one side
    of it is meshed exactly."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    n = mesh_size(lo, hi, h)
    if not 0.0 <= snap < 0.35:
        raise InputError("fem.level_set_mesh", "snap", f"must lie in [0, 0.35), got {snap!r}")
    axes = [np.linspace(a, b, k + 1) for a, b, k in zip(lo, hi, n)]
    moved = [set() for _ in range(3)]
    for axis, coord in planes:
        a = axes[int(axis)]
        if a[0] < coord < a[-1]:
            i = int(np.argmin(np.abs(a - coord)))
            if i not in moved[int(axis)] and 0 < i < len(a) - 1:
                a[i] = float(coord)
                moved[int(axis)].add(i)
    grid = tensor_mesh(*axes)
    p, t = grid.p.copy(), grid.t.T                                # [3, N], [T, 4]
    grid_index = [np.searchsorted(axes[k], p[k]).clip(0, len(axes[k]) - 1) for k in range(3)]

    def field(x):
        out = np.asarray(distance(np.ascontiguousarray(x.T)), dtype=np.float64)
        if out.shape != (x.shape[1],) or not np.all(np.isfinite(out)):
            raise InputError("fem.level_set_mesh", "distance", "must return one finite value a point")
        return out

    f = field(p)
    step = float(np.min((hi - lo) / np.asarray(n)))
    near = np.flatnonzero(np.abs(f) < snap * step)
    if near.size:                        # onto the surface: x - f grad f / |grad f|^2
        d = 1e-3 * step
        grad = np.stack([(field(p[:, near] + d * e[:, None]) - field(p[:, near] - d * e[:, None])) / (2 * d)
                         for e in np.eye(3)])
        for axis in range(3):            # a vertex on a moved plane moves within it
            on_plane = np.isin(np.arange(len(axes[axis])), sorted(moved[axis]))
            grad[axis, on_plane[grid_index[axis][near]]] = 0.0
        g2 = np.sum(grad**2, axis=0)
        ok = g2 > 0.25                   # a distance's slope is 1: a flat spot keeps its vertex
        move = near[ok]
        p[:, move] -= f[move] * grad[:, ok] / g2[ok]
        f[move] = 0.0
    inside = f >= 0
    k = inside[t].sum(axis=1)
    whole = t[k == 4]
    mixed = (k > 0) & (k < 4)
    # each cut tetrahedron's vertices, inside ones first (a stable sort keeps the order otherwise)
    v = np.take_along_axis(t[mixed], np.argsort(~inside[t[mixed]], axis=1, kind="stable"), axis=1)
    kc = k[mixed]
    # the surface's points: one on each edge from a vertex inside to one outside, after the grid's
    pairs = np.concatenate([v[:, [i, j]] for i in range(4) for j in range(i + 1, 4)])
    pairs = np.sort(pairs[(f[pairs[:, 0]] > 0) != (f[pairs[:, 1]] > 0)], axis=1)
    pairs = pairs[(f[pairs[:, 0]] != 0) & (f[pairs[:, 1]] != 0)]
    edges = np.unique(pairs, axis=0).reshape(-1, 2)
    a, b = edges[:, 0], edges[:, 1]
    s = f[a] / (f[a] - f[b])
    new_p = p[:, a] + s * (p[:, b] - p[:, a])
    n_pts = p.shape[1]
    key = a.astype(np.int64) * n_pts + b

    def on(i, j):
        """The surface point on the edge from inside vertices ``i`` to outside ``j`` [K]:
        ``i`` itself where it lies on the surface."""
        kk = np.minimum(i, j).astype(np.int64) * n_pts + np.maximum(i, j)
        pos = np.clip(np.searchsorted(key, kk), 0, max(len(key) - 1, 0))
        return np.where(f[i] == 0, i, n_pts + pos)

    parts = [whole]
    one, two, three = v[kc == 1], v[kc == 2], v[kc == 3]
    if len(one):
        parts.append(np.stack([one[:, 0], on(one[:, 0], one[:, 1]), on(one[:, 0], one[:, 2]),
                               on(one[:, 0], one[:, 3])], axis=1))
    if len(two):                         # inside a, b; the prism (a, ac, ad) - (b, bc, bd)
        a2, b2, c2, d2 = two.T
        parts.append(_split_prisms(np.stack([a2, on(a2, c2), on(a2, d2), b2, on(b2, c2), on(b2, d2)], axis=1)))
    if len(three):                       # inside a, b, c; the prism (a, b, c) - (ad, bd, cd)
        a3, b3, c3, d3 = three.T
        parts.append(_split_prisms(np.stack([a3, b3, c3, on(a3, d3), on(b3, d3), on(c3, d3)], axis=1)))
    tets = np.concatenate(parts)
    srt = np.sort(tets, axis=1)
    tets = tets[np.all(srt[:, 1:] != srt[:, :-1], axis=1)]        # the flat ones a surface vertex makes
    if not len(tets):
        raise InputError("fem.level_set_mesh", "distance", "no point of the box lies inside the body")
    pts = np.concatenate([p, new_p], axis=1)
    used, inv = np.unique(tets, return_inverse=True)
    return skfem.MeshTet(np.ascontiguousarray(pts[:, used]), np.ascontiguousarray(inv.reshape(tets.shape).T))
