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
from typing import Sequence

import numpy as np
import skfem

from ..errors import InputError

__all__ = ["Region", "tensor_mesh", "box_mesh", "mesh_size", "tapered_plate_mesh"]

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
