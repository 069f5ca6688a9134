"""PhysGaussian preprocessing: opacity threshold, rotations, crop, normalization (private)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from knockgs_core.errors import InputError

from ._gaussians import GaussianSet, matrix_to_quat, quat_multiply

__all__ = ["Normalization", "preprocess", "rotation_matrix"]

_AXES = {"x": 0, "y": 1, "z": 2}


def rotation_matrix(rotations: Sequence[tuple[str, float]], *, source: object = "rotations",
                    field: str = "rotations") -> np.ndarray:
    """Product of axis rotations applied in order: ``[("x", 90.0), ("z", 30.0)]`` rotates
    by 90 degrees about x first, then 30 degrees about z (right-handed, counter-clockwise
    seen from the positive axis). Returns [3, 3] float64."""
    r = np.eye(3)
    for i, item in enumerate(rotations):
        try:
            axis, degrees = item
            a = _AXES[str(axis).lower()]
            t = math.radians(float(degrees))
        except (KeyError, TypeError, ValueError):
            raise InputError(source, f"{field}[{i}]",
                             f"expected (axis in x/y/z, degrees), got {item!r}") from None
        c, s = math.cos(t), math.sin(t)
        m = np.eye(3)
        j, k = [b for b in range(3) if b != a]
        m[j, j], m[j, k], m[k, j], m[k, k] = c, -s, s, c
        r = m @ r
    return r


@dataclass(frozen=True)
class Normalization:
    """The map from the source (capture) frame to the normalized simulation domain.

    ``apply(p) = scale * (R p - center) + offset``: rotate, move the rotated bounding-box
    centre to ``offset`` (PhysGaussian's (1, 1, 1)) and scale the largest extent to 1.
    ``rotation`` is [3, 3] (row-major nested tuples), ``center`` the rotated-frame centre.
    """

    rotation: tuple[tuple[float, float, float], ...]
    center: tuple[float, float, float]
    scale: float
    offset: tuple[float, float, float] = (1.0, 1.0, 1.0)

    @property
    def matrix(self) -> np.ndarray:
        """Rotation ``R``, [3, 3] float64."""
        return np.asarray(self.rotation, dtype=np.float64)

    def apply(self, points) -> np.ndarray:
        """Source-frame points [N, 3] -> normalized domain [N, 3] float64."""
        p = np.asarray(points, dtype=np.float64)
        return self.scale * (p @ self.matrix.T - np.asarray(self.center)) + np.asarray(self.offset)

    def inverse(self, points) -> np.ndarray:
        """Normalized-domain points [N, 3] -> source frame [N, 3] float64."""
        q = np.asarray(points, dtype=np.float64)
        return ((q - np.asarray(self.offset)) / self.scale + np.asarray(self.center)) @ self.matrix

    def apply_covariances(self, covs) -> np.ndarray:
        """Source-frame covariances [N, 3, 3] -> normalized ``s^2 R C R^T`` (float64)."""
        r = self.matrix
        return self.scale ** 2 * np.einsum("ij,njk,lk->nil", r, np.asarray(covs, np.float64), r)

    def inverse_covariances(self, covs) -> np.ndarray:
        """Normalized covariances [N, 3, 3] -> source frame ``R^T C R / s^2`` (float64)."""
        r = self.matrix
        return np.einsum("ji,njk,kl->nil", r, np.asarray(covs, np.float64), r) / self.scale ** 2

    def inverse_directions(self, dirs) -> np.ndarray:
        """Normalized-domain directions [N, 3] -> source frame ``R^T d`` (for evaluating
        view-dependent SH, which preprocessing does not rotate)."""
        return np.asarray(dirs, dtype=np.float64) @ self.matrix

    def to_dict(self) -> dict:
        return {"rotation": [list(map(float, row)) for row in self.rotation],
                "center": list(map(float, self.center)), "scale": float(self.scale),
                "offset": list(map(float, self.offset))}

    @classmethod
    def from_dict(cls, d: dict) -> "Normalization":
        return cls(rotation=tuple(tuple(float(x) for x in row) for row in d["rotation"]),
                   center=tuple(float(x) for x in d["center"]), scale=float(d["scale"]),
                   offset=tuple(float(x) for x in d.get("offset", (1.0, 1.0, 1.0))))


def transform_gaussians(gs: GaussianSet, norm: Normalization) -> GaussianSet:
    """``gs`` mapped by ``norm``: centres moved, scales multiplied by ``norm.scale`` and
    quaternions pre-multiplied by the rotation, so that covariances become
    ``norm.apply_covariances(gs.covariances())``. SH coefficients are kept as they are."""
    q_r = matrix_to_quat(norm.matrix[None])[0]
    quats = quat_multiply(q_r[None], gs.quats.astype(np.float64))
    return GaussianSet(norm.apply(gs.means), gs.scales.astype(np.float64) * norm.scale,
                       quats, gs.opacities, gs.sh_dc, gs.sh_rest)


def preprocess(gs: GaussianSet, *, opacity_threshold: float = 0.0,
               rotations: Sequence[tuple[str, float]] = (), crop=None,
               source: object = "asset", field_prefix: str = "") -> tuple[GaussianSet, Normalization]:
    """PhysGaussian's preprocessing of a reconstructed asset.

    1. drop Gaussians with opacity below ``opacity_threshold``;
    2. rotate by ``rotations`` (see :func:`rotation_matrix`);
    3. keep the Gaussians whose rotated centres lie in ``crop`` (a
       :class:`~knockgs_core.sim._config.Box` in the rotated frame, or None);
    4. normalize: largest bounding-box extent -> 1, box centre -> (1, 1, 1).

    Returns the normalized :class:`GaussianSet` and the :class:`Normalization` (whose
    ``inverse`` maps back to the source frame, for rendering there). ``source`` and
    ``field_prefix`` name the origin in errors: a threshold or crop that removes every
    Gaussian, or an asset of zero extent, raises :class:`InputError`.
    """
    if not (0.0 <= float(opacity_threshold) < 1.0):
        raise InputError(source, f"{field_prefix}opacity_threshold",
                         f"must lie in [0, 1), got {opacity_threshold!r}")
    keep = gs.opacities >= np.float32(opacity_threshold)
    if not np.any(keep):
        raise InputError(source, f"{field_prefix}opacity_threshold",
                         f"{opacity_threshold} removes all {len(gs)} Gaussians "
                         f"(max opacity {float(gs.opacities.max()):.4g})")
    r = rotation_matrix(rotations, source=source, field=f"{field_prefix}rotations")
    rotated = gs.means.astype(np.float64)[keep] @ r.T
    if crop is not None:
        inside = crop.contains(rotated)
        if not np.any(inside):
            raise InputError(source, f"{field_prefix}crop",
                             f"the crop box {crop} keeps none of the {int(keep.sum())} Gaussians")
        idx = np.flatnonzero(keep)
        keep = np.zeros_like(keep)
        keep[idx[inside]] = True
        rotated = rotated[inside]
    lo, hi = rotated.min(axis=0), rotated.max(axis=0)
    extent = float(np.max(hi - lo))
    if not extent > 1e-9 * max(1.0, float(np.max(np.abs(rotated)))):
        raise InputError(source, f"{field_prefix}means",
                         f"the asset has zero extent (all {len(rotated)} centres coincide)")
    norm = Normalization(rotation=tuple(tuple(float(x) for x in row) for row in r),
                         center=tuple(float(x) for x in 0.5 * (lo + hi)), scale=1.0 / extent)
    return transform_gaussians(gs.subset(keep), norm), norm
