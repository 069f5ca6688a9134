"""The Gaussian set of a 3DGS asset and quaternion helpers (private)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from knockgs_core.errors import InputError

#: degree-0 real spherical-harmonic constant, 1 / (2 sqrt(pi)) (3DGS ``C0``)
SH_C0 = 0.28209479177387814


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _as_array(value, source: str, name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
    """Copy ``value`` to a C-contiguous array of ``dtype``; -1 in ``shape`` is free."""
    try:
        a = np.array(value, dtype=dtype, copy=True, order="C")
    except (TypeError, ValueError) as exc:
        raise InputError(source, name, f"not a numeric array ({exc})") from None
    if a.ndim != len(shape) or any(s != -1 and s != d for s, d in zip(shape, a.shape)):
        want = "[" + ", ".join("N" if s == -1 else str(s) for s in shape) + "]"
        raise InputError(source, name, f"expected shape {want}, got {list(a.shape)}")
    return a


def quat_to_matrix(quats: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions ``quats`` (w, x, y, z), shape [N, 4] -> [N, 3, 3]."""
    q = np.asarray(quats, dtype=np.float64)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = np.empty((q.shape[0], 3, 3), dtype=np.float64)
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - w * z)
    r[:, 0, 2] = 2 * (x * z + w * y)
    r[:, 1, 0] = 2 * (x * y + w * z)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - w * x)
    r[:, 2, 0] = 2 * (x * z - w * y)
    r[:, 2, 1] = 2 * (y * z + w * x)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def matrix_to_quat(mats: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) with ``w >= 0`` of rotation matrices [N, 3, 3] -> [N, 4].

    Shepperd's method: the largest of the four squared components is computed first, so
    the result is accurate for every rotation.
    """
    m = np.asarray(mats, dtype=np.float64)
    t = np.stack([
        1 + m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2],
        1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
        1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2],
        1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2],
    ], axis=1)
    k = np.argmax(t, axis=1)
    s = 2.0 * np.sqrt(np.maximum(t[np.arange(len(k)), k], 1e-300))
    q = np.empty((m.shape[0], 4), dtype=np.float64)
    d21, d02, d10 = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
    s21, s02, s10 = m[:, 2, 1] + m[:, 1, 2], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 0] + m[:, 0, 1]
    for idx, cols in (
        (0, (s / 4, d21 / s, d02 / s, d10 / s)),
        (1, (d21 / s, s / 4, s10 / s, s02 / s)),
        (2, (d02 / s, s10 / s, s / 4, s21 / s)),
        (3, (d10 / s, s02 / s, s21 / s, s / 4)),
    ):
        sel = k == idx
        for j in range(4):
            q[sel, j] = cols[j][sel]
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of quaternions (w, x, y, z); shapes broadcast over [.., 4]."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


@dataclass(frozen=True, eq=False)
class GaussianSet:
    """A set of N 3D Gaussians with *activated* parameters (3DGS conventions).

    Attributes
    ----------
    means: [N, 3] float32
        Centres.
    scales: [N, 3] float32
        Standard deviations along the local axes (``exp`` of the PLY's ``scale_*``), > 0.
    quats: [N, 4] float32
        Unit rotation quaternions (w, x, y, z) (the PLY's ``rot_0..3``, normalized).
    opacities: [N] float32
        In (0, 1) (``sigmoid`` of the PLY's ``opacity``).
    sh_dc: [N, 3] float32
        Degree-0 spherical-harmonic coefficients per RGB channel.
    sh_rest: [N, K, 3] float32
        Higher-order coefficients, K in {0, 3, 8, 15} for degrees 0..3.

    Arrays are copied on construction and read-only afterwards.
    """

    means: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    opacities: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray | None = None

    def __post_init__(self):
        src = "GaussianSet"
        means = _as_array(self.means, src, "means", (-1, 3), np.float32)
        n = means.shape[0]
        scales = _as_array(self.scales, src, "scales", (n, 3), np.float32)
        quats = _as_array(self.quats, src, "quats", (n, 4), np.float64)
        opac = _as_array(self.opacities, src, "opacities", (n,), np.float32)
        dc = _as_array(self.sh_dc, src, "sh_dc", (n, 3), np.float32)
        rest = np.zeros((n, 0, 3), np.float32) if self.sh_rest is None else \
            _as_array(self.sh_rest, src, "sh_rest", (n, -1, 3), np.float32)
        norms = np.linalg.norm(quats, axis=1, keepdims=True)
        if np.any(~(norms > 0)):
            raise InputError(src, "quats", "zero or non-finite quaternion")
        quats = (quats / norms).astype(np.float32)
        for name, arr in (("means", means), ("scales", scales), ("opacities", opac),
                          ("sh_dc", dc), ("sh_rest", rest)):
            if not np.all(np.isfinite(arr)):
                raise InputError(src, name, "contains non-finite values")
        if np.any(scales <= 0):
            raise InputError(src, "scales", "must be > 0")
        for name, arr in (("means", means), ("scales", scales), ("quats", quats),
                          ("opacities", opac), ("sh_dc", dc), ("sh_rest", rest)):
            object.__setattr__(self, name, _readonly(arr))

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        """Spherical-harmonic degree implied by ``sh_rest`` (K = (d + 1)^2 - 1)."""
        return int(round(np.sqrt(self.sh_rest.shape[1] + 1))) - 1

    def rotations(self) -> np.ndarray:
        """Rotation matrices of ``quats``, [N, 3, 3] float64."""
        return quat_to_matrix(self.quats)

    def covariances(self) -> np.ndarray:
        """Covariances ``R S S^T R^T`` with ``S = diag(scales)``, [N, 3, 3] float32."""
        r = self.rotations()
        m = r * self.scales.astype(np.float64)[:, None, :]
        cov = m @ np.swapaxes(m, 1, 2)
        return (0.5 * (cov + np.swapaxes(cov, 1, 2))).astype(np.float32)

    def colors(self) -> np.ndarray:
        """View-independent RGB colours ``clip(0.5 + C0 * sh_dc, 0, 1)``, [N, 3] float32."""
        return np.clip(0.5 + SH_C0 * self.sh_dc, 0.0, 1.0).astype(np.float32)

    def subset(self, mask) -> "GaussianSet":
        """The Gaussians selected by a boolean mask or an index array."""
        sel = np.asarray(mask)
        if sel.dtype == bool and sel.shape != (len(self),):
            raise InputError("GaussianSet.subset", "mask",
                             f"expected a bool array of shape [{len(self)}], got {list(sel.shape)}")
        return GaussianSet(self.means[sel], self.scales[sel], self.quats[sel],
                           self.opacities[sel], self.sh_dc[sel], self.sh_rest[sel])

    @staticmethod
    def concatenate(sets) -> "GaussianSet":
        """One set holding all Gaussians of ``sets`` in order (same SH degree)."""
        sets = list(sets)
        ks = {s.sh_rest.shape[1] for s in sets}
        if len(ks) != 1:
            raise InputError("GaussianSet.concatenate", "sh_rest", f"mixed SH sizes {sorted(ks)}")
        return GaussianSet(*(np.concatenate([getattr(s, f) for s in sets]) for f in
                             ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")))

    def equals(self, other: "GaussianSet") -> bool:
        """Bitwise equality of every array."""
        return all(np.array_equal(getattr(self, f), getattr(other, f)) for f in
                   ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"))
