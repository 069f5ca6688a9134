"""SuperSplat / PlayCanvas compressed PLY files (``*.compressed.ply``) (private).

The layout, as SuperSplat writes it: an element ``chunk`` of float bounds, one row per
256 consecutive vertices (``min_x max_x ...`` of the positions, ``min_scale_x ...`` of the
log scales and, from SuperSplat 1.x on, ``min_r ... max_b`` of the colours), an element
``vertex`` of four uint32 words per Gaussian, and an optional element ``sh`` of uint8
``f_rest_0..3K-1`` (K in {3, 8, 15}). Vertex ``i`` belongs to chunk ``i // 256``.

* ``packed_position`` and ``packed_scale``: 11, 10 and 11 bits (x in the top bits), each a
  fraction ``t = q / (2^bits - 1)`` of the chunk's interval: ``value = min + t (max - min)``
  (the scale's value is a log standard deviation, as ``scale_*`` of the INRIA layout).
* ``packed_rotation``: 2 bits name the largest of the four quaternion components
  (w, x, y, z, the INRIA ``rot_0..3`` order), then the other three in order, 10 bits each,
  ``(q / 1023 - 0.5) sqrt(2)``; the largest is ``sqrt(1 - a^2 - b^2 - c^2)``.
* ``packed_color``: 8 bits each of r, g, b, a (r in the top bits). With colour bounds,
  ``colour = min + (q / 255) (max - min)``, otherwise ``q / 255``; ``f_dc = (colour - 0.5) /
  C0``; the opacity is ``a / 255`` (0 and 1 included: logits of -inf and +inf).
* ``sh``: ``f_rest = (n - 0.5) 8`` with ``n = 0`` for byte 0, 1 for byte 255, else
  ``(byte + 0.5) / 256``.

Quantization steps (what a decoder can reproduce, what it cannot): positions and log
scales ``(max - min) / 2047`` (x, z) and ``/ 1023`` (y) of their chunk; quaternion
components ``sqrt(2) / 1023``; colours ``(max - min) / 255``; opacities ``1 / 255``.
"""

from __future__ import annotations

import numpy as np

from knockgs_core.errors import InputError

__all__ = ["CHUNK_SIZE", "is_compressed", "decode_compressed"]

#: vertices per chunk of bounds
CHUNK_SIZE = 256

_CHUNK_POSITION = ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z")
_CHUNK_SCALE = ("min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z")
_CHUNK_COLOR = ("min_r", "min_g", "min_b", "max_r", "max_g", "max_b")
_PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")


def is_compressed(ply) -> bool:
    """Whether a parsed ``plyfile.PlyData`` is in the compressed layout (a ``chunk`` element
    and a ``vertex`` element with ``packed_*`` properties)."""
    names = [e.name for e in ply.elements]
    if "chunk" not in names or "vertex" not in names:
        return False
    return "packed_position" in set(ply["vertex"].data.dtype.names or ())


def _unorm(words: np.ndarray, shift: int, bits: int) -> np.ndarray:
    """The ``bits``-bit field at ``shift`` of uint32 ``words`` as a fraction in [0, 1]."""
    return ((words >> np.uint32(shift)) & np.uint32((1 << bits) - 1)).astype(np.float64) / ((1 << bits) - 1)


def _unpack_11_10_11(words: np.ndarray) -> np.ndarray:
    """[N] uint32 -> [N, 3] fractions (x: bits 21-31, y: 11-20, z: 0-10)."""
    return np.stack([_unorm(words, 21, 11), _unorm(words, 11, 10), _unorm(words, 0, 11)], axis=1)


def _unpack_rotation(words: np.ndarray) -> np.ndarray:
    """[N] uint32 -> [N, 4] quaternions (w, x, y, z), unit norm up to quantization."""
    abc = np.stack([_unorm(words, 20, 10), _unorm(words, 10, 10), _unorm(words, 0, 10)], axis=1)
    abc = (abc - 0.5) * np.sqrt(2.0)
    largest = np.sqrt(np.maximum(0.0, 1.0 - np.sum(abc * abc, axis=1)))
    which = (words >> np.uint32(30)).astype(np.int64)
    q = np.empty((len(words), 4), dtype=np.float64)
    rows = np.arange(len(words))
    # the three stored components fill the slots other than `which`, in order
    slot = np.arange(3)[None, :] + (np.arange(3)[None, :] >= which[:, None])
    q[rows[:, None], slot] = abc
    q[rows, which] = largest
    return q


def _float_columns(path, element, names) -> np.ndarray:
    """Columns ``names`` of a chunk element as [n_chunks, len(names)] float64 (finite)."""
    have = set(element.data.dtype.names or ())
    for name in names:
        if name not in have:
            raise InputError(path, f"chunk.{name}", "required property of a compressed PLY is missing")
    out = np.stack([np.asarray(element.data[n], dtype=np.float64) for n in names], axis=1)
    bad = ~np.isfinite(out)
    if np.any(bad):
        j = int(np.flatnonzero(bad.any(axis=0))[0])
        raise InputError(path, f"chunk.{names[j]}", f"{int(bad[:, j].sum())} non-finite value(s)")
    return out


def decode_compressed(ply, path) -> dict[str, np.ndarray]:
    """Decode a compressed PLY (``plyfile.PlyData``) to INRIA-layout arrays (float64).

    Returns ``{"means": [N, 3], "log_scales": [N, 3], "quats": [N, 4] (w, x, y, z),
    "opacities": [N] in [0, 1], "sh_dc": [N, 3], "sh_rest": [N, K, 3]}``. Raises
    :class:`InputError` naming ``path`` and the element or property for a missing or
    mistyped property, too few chunks for the vertices, inverted bounds or an ``sh``
    element of another length or width.
    """
    chunk = ply["chunk"]
    vertex = ply["vertex"].data
    have = set(vertex.dtype.names or ())
    for name in _PACKED:
        if name not in have:
            raise InputError(path, f"vertex.{name}", "required property of a compressed PLY is missing")
        if vertex.dtype[name].kind not in "ui" or vertex.dtype[name].itemsize != 4:
            raise InputError(path, f"vertex.{name}", f"expected a uint32 property, got {vertex.dtype[name]}")
    n = len(vertex)
    if n == 0:
        raise InputError(path, "vertex", "the PLY holds no Gaussians")
    n_chunks = len(chunk.data)
    need = -(-n // CHUNK_SIZE)
    if n_chunks < need:
        raise InputError(path, "chunk", f"{n_chunks} chunks of {CHUNK_SIZE} cannot hold {n} vertices "
                         f"(need {need})")
    pos_b = _float_columns(path, chunk, _CHUNK_POSITION)
    scl_b = _float_columns(path, chunk, _CHUNK_SCALE)
    has_color = "min_r" in set(chunk.data.dtype.names or ())
    col_b = _float_columns(path, chunk, _CHUNK_COLOR) if has_color else None
    for bounds, names in ((pos_b, _CHUNK_POSITION), (scl_b, _CHUNK_SCALE), (col_b, _CHUNK_COLOR)):
        if bounds is not None and np.any(bounds[:need, 3:] < bounds[:need, :3]):
            j = int(np.flatnonzero(np.any(bounds[:need, 3:] < bounds[:need, :3], axis=0))[0])
            raise InputError(path, f"chunk.{names[3 + j]}", f"below {names[j]} in "
                             f"{int(np.sum(bounds[:need, 3 + j] < bounds[:need, j]))} chunk(s)")
    ci = np.arange(n) // CHUNK_SIZE
    words = {k: np.asarray(vertex[k]).astype(np.uint32) for k in _PACKED}

    def lerp(bounds, t):
        lo, hi = bounds[ci, :3], bounds[ci, 3:]
        return lo * (1.0 - t) + hi * t

    means = lerp(pos_b, _unpack_11_10_11(words["packed_position"]))
    log_scales = lerp(scl_b, _unpack_11_10_11(words["packed_scale"]))
    quats = _unpack_rotation(words["packed_rotation"])
    c = words["packed_color"]
    rgba = np.stack([_unorm(c, 24, 8), _unorm(c, 16, 8), _unorm(c, 8, 8), _unorm(c, 0, 8)], axis=1)
    rgb = lerp(col_b, rgba[:, :3]) if has_color else rgba[:, :3]
    from ._gaussians import SH_C0

    sh_dc = (rgb - 0.5) / SH_C0
    rest = np.zeros((n, 0, 3))
    if "sh" in [e.name for e in ply.elements]:
        sh = ply["sh"].data
        names = list(sh.dtype.names or ())
        if len(names) not in (9, 24, 45) or names != [f"f_rest_{i}" for i in range(len(names))]:
            raise InputError(path, "sh", f"expected f_rest_0..f_rest_(3K-1) with K in {{3, 8, 15}}, "
                             f"got {len(names)} properties")
        if len(sh) != n:
            raise InputError(path, "sh", f"{len(sh)} rows for {n} vertices")
        b = np.stack([np.asarray(sh[nm]).astype(np.float64) for nm in names], axis=1)
        frac = np.where(b == 0, 0.0, np.where(b == 255, 1.0, (b + 0.5) / 256.0))
        k = len(names) // 3
        rest = ((frac - 0.5) * 8.0).reshape(n, 3, k).transpose(0, 2, 1)
    return {"means": means, "log_scales": log_scales, "quats": quats, "opacities": rgba[:, 3],
            "sh_dc": sh_dc, "sh_rest": rest}
