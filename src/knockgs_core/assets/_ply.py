"""Standard 3DGS PLY files (the INRIA ``point_cloud.ply`` layout) (private).

One ``vertex`` element with float properties ``x y z``, optional ``nx ny nz``,
``f_dc_0..2``, ``f_rest_0..3K-1`` (channel-major: ``f_rest_{c*K + k}``), ``opacity``
(a logit), ``scale_0..2`` (logs of the standard deviations) and ``rot_0..3`` (a
quaternion w, x, y, z, not necessarily normalized). Extra properties are ignored.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from knockgs_core.io import atomic_write
from knockgs_core.errors import InputError

from ._gaussians import GaussianSet

__all__ = ["read_ply", "write_ply"]

_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


def _sigmoid(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.float64)
    return np.where(x >= 0, 1.0 / (1.0 + np.exp(-np.abs(x))),
                    np.exp(-np.abs(x)) / (1.0 + np.exp(-np.abs(x))))


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p.astype(np.float64), 1e-7, 1.0 - 1e-7)
    return np.log(p) - np.log1p(-p)


def read_ply(path: str | os.PathLike) -> GaussianSet:
    """Read a 3DGS PLY file into a :class:`GaussianSet` (activations applied).

    Raises :class:`~knockgs_core.errors.InputError` naming the file and the property for
    a missing property, a non-finite value, an ``f_rest_*`` count that is not 3K with
    K in {0, 3, 8, 15}, a zero quaternion or a file without Gaussians.
    """
    from plyfile import PlyData

    path = Path(path)
    try:
        # memory-mapped (copy on write; the columns are copied out below): plyfile reads a
        # binary file without a mapping row by row and property by property, ~1 min for the
        # paper-scale Pillow's 1.3 M Gaussians against ~0.1 s mapped
        ply = PlyData.read(str(path), mmap="c")
    except FileNotFoundError:
        raise InputError(path, "file", "does not exist") from None
    except Exception as exc:  # plyfile raises several exception types for bad files
        raise InputError(path, "file", f"not a readable PLY file ({exc})") from None
    if "vertex" not in [e.name for e in ply.elements]:
        raise InputError(path, "vertex", "PLY has no 'vertex' element")
    v = ply["vertex"].data
    names = set(v.dtype.names or ())
    for name in _REQUIRED:
        if name not in names:
            raise InputError(path, name, "required 3DGS property is missing")
    rest_names = sorted((n for n in names if n.startswith("f_rest_")), key=lambda s: int(s[7:])
                        if s[7:].isdigit() else -1)
    n_rest = len(rest_names)
    if n_rest not in (0, 9, 24, 45) or rest_names != [f"f_rest_{i}" for i in range(n_rest)]:
        raise InputError(path, "f_rest_*", f"expected f_rest_0..f_rest_(3K-1) with K in "
                         f"{{0, 3, 8, 15}}, got {n_rest} properties")
    n = len(v)
    if n == 0:
        raise InputError(path, "vertex", "the PLY holds no Gaussians")

    def col(name: str) -> np.ndarray:
        a = np.asarray(v[name], dtype=np.float64)
        if not np.all(np.isfinite(a)):
            bad = int(np.count_nonzero(~np.isfinite(a)))
            raise InputError(path, name, f"{bad} non-finite value(s)")
        return a

    means = np.stack([col("x"), col("y"), col("z")], axis=1)
    dc = np.stack([col(f"f_dc_{i}") for i in range(3)], axis=1)
    k = n_rest // 3
    if k:
        flat = np.stack([col(nm) for nm in rest_names], axis=1)
        rest = flat.reshape(n, 3, k).transpose(0, 2, 1)
    else:
        rest = np.zeros((n, 0, 3))
    opac = _sigmoid(col("opacity"))
    log_scales = np.stack([col(f"scale_{i}") for i in range(3)], axis=1)
    with np.errstate(over="ignore"):
        scales = np.exp(log_scales)
    if not np.all(np.isfinite(scales)) or np.any(scales.astype(np.float32) <= 0):
        raise InputError(path, "scale_*", "log-scales out of range (exp overflows or underflows)")
    quats = np.stack([col(f"rot_{i}") for i in range(4)], axis=1)
    if np.any(np.linalg.norm(quats, axis=1) == 0):
        raise InputError(path, "rot_*", "zero quaternion")
    return GaussianSet(means, scales, quats, opac, dc, rest)


def write_ply(gs: GaussianSet, path: str | os.PathLike) -> None:
    """Write ``gs`` as a binary little-endian 3DGS PLY (INRIA layout, normals zero).

    Inverse activations: ``scale_* = log(scales)``, ``opacity = logit(opacities)``
    (opacities clipped to [1e-7, 1 - 1e-7]); quaternions are written normalized.
    The bytes depend only on ``gs``; the file is written atomically (:mod:`knockgs_core.io`).
    """
    from plyfile import PlyData, PlyElement

    n = len(gs)
    k = gs.sh_rest.shape[1]
    props = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    props += [f"f_rest_{i}" for i in range(3 * k)]
    props += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    cols = [gs.means, np.zeros((n, 3)), gs.sh_dc,
            gs.sh_rest.transpose(0, 2, 1).reshape(n, 3 * k),
            _logit(gs.opacities)[:, None], np.log(gs.scales.astype(np.float64)), gs.quats]
    table = np.concatenate([np.asarray(c, dtype=np.float32).reshape(n, -1) for c in cols], axis=1)
    rec = np.empty(n, dtype=[(p, "<f4") for p in props])
    for i, p in enumerate(props):
        rec[p] = table[:, i]
    with atomic_write(path, mode="wb") as fh:
        PlyData([PlyElement.describe(rec, "vertex")], text=False, byte_order="<").write(fh)
