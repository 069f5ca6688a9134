"""3DGS PLY files: the INRIA ``point_cloud.ply`` layout (read and written) and SuperSplat's
compressed PLY (read) (private).

One ``vertex`` element with float properties ``x y z``, optional ``nx ny nz``,
``f_dc_0..2``, ``f_rest_0..3K-1`` (channel-major: ``f_rest_{c*K + k}``), ``opacity``
(a logit), ``scale_0..2`` (logs of the standard deviations) and ``rot_0..3`` (a
quaternion w, x, y, z, not necessarily normalized). Extra properties are ignored.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from knockgs_core.io import atomic_write
from knockgs_core.errors import InputError

from ._compressed_ply import decode_compressed, is_compressed
from ._gaussians import GaussianSet

__all__ = ["SplatFile", "SplatRepairs", "read_ply", "read_splat", "write_ply"]

_REQUIRED = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


def _sigmoid(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.float64)
    return np.where(x >= 0, 1.0 / (1.0 + np.exp(-np.abs(x))),
                    np.exp(-np.abs(x)) / (1.0 + np.exp(-np.abs(x))))


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p.astype(np.float64), 1e-7, 1.0 - 1e-7)
    return np.log(p) - np.log1p(-p)


class SplatRepairs(NamedTuple):
    """Gaussians of a splat file changed by the reading rules of :func:`read_splat`.

    ``opacity_saturated``: opacity logit +-inf (or a compressed alpha of 0 or 255), read as
    opacity 1 or 0; ``zero_quaternions``: quaternion of zero norm, read as the identity;
    ``scales_clamped``: a standard deviation outside ``[1e-9 D, D]`` (D the diagonal of the
    centres' bounding box, 1 where they coincide), clamped into it (counts Gaussians, not axes).
    """

    opacity_saturated: int = 0
    zero_quaternions: int = 0
    scales_clamped: int = 0


class SplatFile(NamedTuple):
    """A splat file as read: ``gaussians``, its ``layout`` (``"inria"`` or
    ``"supersplat_compressed"``) and the ``repairs`` its reading rules made."""

    gaussians: GaussianSet
    layout: str
    repairs: SplatRepairs


#: smallest standard deviation kept, as a fraction of the centres' bounding-box diagonal
_MIN_SCALE_FRACTION = 1e-9


def _finite(path, name: str, a: np.ndarray, *, allow_inf: bool = False) -> np.ndarray:
    bad = np.isnan(a) if allow_inf else ~np.isfinite(a)
    if np.any(bad):
        what = "NaN" if allow_inf else "non-finite"
        raise InputError(path, name, f"{int(np.count_nonzero(bad))} {what} value(s)")
    return a


def _gaussians_by_rules(path, *, means, log_scales, quats, opacities, opacity_saturated, sh_dc,
                        sh_rest) -> tuple[GaussianSet, SplatRepairs]:
    """Apply the reading rules (see :func:`read_splat`) to float64 arrays of the file."""
    extent = means.max(axis=0) - means.min(axis=0)
    diag = float(np.linalg.norm(extent)) or 1.0  # all centres coincide: no scene size, file units
    lo, hi = np.log(_MIN_SCALE_FRACTION * diag), np.log(diag)
    clamped = np.any((log_scales < lo) | (log_scales > hi), axis=1)
    scales = np.exp(np.clip(log_scales, lo, hi))
    norms = np.linalg.norm(quats, axis=1)
    zero = ~(norms > 0)
    quats = quats.copy()
    quats[zero] = (1.0, 0.0, 0.0, 0.0)
    gs = GaussianSet(means, scales, quats, opacities, sh_dc, sh_rest)
    return gs, SplatRepairs(int(np.count_nonzero(opacity_saturated)), int(np.count_nonzero(zero)),
                            int(np.count_nonzero(clamped)))


def read_splat(path: str | os.PathLike) -> SplatFile:
    """Read a 3DGS splat file: the INRIA ``point_cloud.ply`` layout or SuperSplat's
    compressed PLY (``*.compressed.ply``, see :mod:`._compressed_ply`), told apart by
    their elements.

    Reading rules for what trained and shared splats contain (each counted in
    :class:`SplatRepairs`):

    * an opacity logit of +inf or -inf (what a decoder writes for opacity 1 or 0) is
      opacity 1 or 0, the sigmoid's limits; a NaN logit is refused;
    * a quaternion of zero norm is the identity (what the INRIA rasterizer's normalized
      zero quaternion gives in its rotation-matrix formula);
    * log scales may be infinite; every standard deviation is clamped to ``[1e-9 D, D]``,
      D the diagonal of the bounding box of the centres (1 where they coincide): a Gaussian wider than the whole
      scene is no surface element, and a zero one has no covariance; a NaN is refused.

    Refused with :class:`~knockgs_core.errors.InputError` naming the file and the
    property: a missing property, any other non-finite value, an ``f_rest_*`` count that
    is not 3K with K in {0, 3, 8, 15}, a file without Gaussians, a truncated or otherwise
    unreadable file (a header that promises more data than the file holds).
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
    except IsADirectoryError:
        raise InputError(path, "file", "is a folder, not a PLY file") from None
    except Exception as exc:  # plyfile raises several exception types for bad files
        raise InputError(path, "file", f"not a readable PLY file ({exc})") from None
    if "vertex" not in [e.name for e in ply.elements]:
        raise InputError(path, "vertex", "PLY has no 'vertex' element")
    if is_compressed(ply):
        d = decode_compressed(ply, path)
        op = d["opacities"]
        gs, repairs = _gaussians_by_rules(path, means=d["means"], log_scales=d["log_scales"],
                                          quats=d["quats"], opacities=op,
                                          opacity_saturated=(op == 0.0) | (op == 1.0),
                                          sh_dc=d["sh_dc"], sh_rest=d["sh_rest"])
        return SplatFile(gs, "supersplat_compressed", repairs)
    v = ply["vertex"].data
    names = set(v.dtype.names or ())
    for name in _REQUIRED:
        if name not in names:
            hint = " (nor is this a SuperSplat compressed PLY)" if name == "x" else ""
            raise InputError(path, name, f"required 3DGS property is missing{hint}")
    rest_names = sorted((n for n in names if n.startswith("f_rest_")), key=lambda s: int(s[7:])
                        if s[7:].isdigit() else -1)
    n_rest = len(rest_names)
    if n_rest not in (0, 9, 24, 45) or rest_names != [f"f_rest_{i}" for i in range(n_rest)]:
        raise InputError(path, "f_rest_*", f"expected f_rest_0..f_rest_(3K-1) with K in "
                         f"{{0, 3, 8, 15}}, got {n_rest} properties")
    n = len(v)
    if n == 0:
        raise InputError(path, "vertex", "the PLY holds no Gaussians")

    def col(name: str, *, allow_inf: bool = False) -> np.ndarray:
        return _finite(path, name, np.asarray(v[name], dtype=np.float64), allow_inf=allow_inf)

    means = np.stack([col("x"), col("y"), col("z")], axis=1)
    dc = np.stack([col(f"f_dc_{i}") for i in range(3)], axis=1)
    k = n_rest // 3
    if k:
        flat = np.stack([col(nm) for nm in rest_names], axis=1)
        rest = flat.reshape(n, 3, k).transpose(0, 2, 1)
    else:
        rest = np.zeros((n, 0, 3))
    logit = col("opacity", allow_inf=True)
    log_scales = np.stack([col(f"scale_{i}", allow_inf=True) for i in range(3)], axis=1)
    quats = np.stack([col(f"rot_{i}") for i in range(4)], axis=1)
    gs, repairs = _gaussians_by_rules(path, means=means, log_scales=log_scales, quats=quats,
                                      opacities=_sigmoid(logit), opacity_saturated=np.isinf(logit),
                                      sh_dc=dc, sh_rest=rest)
    return SplatFile(gs, "inria", repairs)


def read_ply(path: str | os.PathLike) -> GaussianSet:
    """The Gaussians of a splat file (INRIA or SuperSplat compressed layout), activations
    applied: :func:`read_splat` without its report."""
    return read_splat(path).gaussians


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
