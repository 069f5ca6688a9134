"""The five-dimensional Probe-A response descriptor (SPEC §5).

All arithmetic on positions is float32, as in the authors' release; the returned
descriptor holds those float32 values promoted to float64 so downstream tables
and estimators work in double precision without re-rounding.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from typing import Union

import numpy as np

from ..io import read_positions
from ..errors import InputError

__all__ = [
    "FEATURE_NAMES",
    "rms_curves",
    "descriptor",
    "curve_descriptor",
    "read_positions",
    "descriptor_from_rollout",
    "descriptor_table",
]

#: descriptor column names, spelled as in the authors' released tables
FEATURE_NAMES: tuple[str, ...] = (
    "norm_auc_rms_disp",
    "norm_initial_slope_rms_0_5",
    "norm_peak_rms_velocity_proxy",
    "norm_auc_rms_velocity_proxy",
    "early_velocity_ratio",
)

#: frames needed to form the initial slope (r^5 - r^0) / 5
_MIN_FRAMES = 6
#: the early window of the velocity ratio: frames 1..5
_EARLY = 5

_F32 = np.float32
_EPS32 = float(np.finfo(np.float32).eps)
_TINY32 = float(np.finfo(np.float32).tiny)

PathLike = Union[str, "os.PathLike[str]"]


def _checked_positions(positions, source: object, n_frames: int | None = None) -> np.ndarray:
    """Positions as a float32 array [T, N, 3], or an InputError naming ``source``."""
    try:
        x = np.asarray(positions)
    except Exception as exc:  # ragged nested lists and the like
        raise InputError(source, "positions", f"not an array: {exc}") from None
    if x.ndim != 3 or x.shape[2] != 3:
        raise InputError(source, "positions", f"expected shape [T, N, 3], got {list(x.shape)}")
    if n_frames is not None and x.shape[0] != n_frames:
        raise InputError(source, "frame", f"expected {n_frames} frames, got {x.shape[0]}")
    if x.shape[0] < _MIN_FRAMES:
        raise InputError(
            source, "frame", f"need at least {_MIN_FRAMES} frames (t = 0..5), got {x.shape[0]}"
        )
    if x.shape[1] < 1:
        raise InputError(source, "particle", "no particles")
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise InputError(source, "positions", f"expected real numbers, got dtype {x.dtype}")
    x = x.astype(_F32, copy=False)
    finite = np.isfinite(x)
    if not finite.all():
        t, i, _ = np.argwhere(~finite)[0]
        raise InputError(
            source, "positions", f"non-finite value (first at frame {int(t)}, particle {int(i)})"
        )
    return x


def _bbox_diagonal(x0: np.ndarray, source: object) -> np.float32:
    """D = ||max_i x_i^0 - min_i x_i^0||, rejected when not resolvable in float32."""
    d = np.float32(np.linalg.norm(x0.max(axis=0) - x0.min(axis=0)))
    scale = float(np.abs(x0).max())
    if not d > max(_TINY32, 4.0 * _EPS32 * scale):
        raise InputError(
            source,
            "positions",
            f"degenerate frame-0 bounding box (diagonal {float(d):.3g}); "
            "the descriptor is normalized by it",
        )
    return d


def _curves(x: np.ndarray, d: np.float32) -> tuple[np.ndarray, np.ndarray]:
    disp = x - x[0]
    r = np.sqrt(np.mean(np.sum(disp * disp, axis=2, dtype=_F32), axis=1, dtype=_F32)) / d
    step = x[1:] - x[:-1]
    v = np.zeros(x.shape[0], dtype=_F32)
    v[1:] = np.sqrt(np.mean(np.sum(step * step, axis=2, dtype=_F32), axis=1, dtype=_F32)) / d
    return r.astype(_F32, copy=False), v


def rms_curves(positions, *, source: object = "positions") -> tuple[np.ndarray, np.ndarray]:
    """Normalized RMS displacement and RMS velocity-proxy curves.

    Parameters
    ----------
    positions:
        Particle positions [m], shape (T, N, 3), frame 0 being the rest state.
    source:
        Named in errors (a file path or a short description).

    Returns
    -------
    r, v:
        float32 arrays of shape (T,): ``r[t] = sqrt(mean_i |x_i^t - x_i^0|^2) / D`` and
        ``v[t] = sqrt(mean_i |x_i^t - x_i^{t-1}|^2) / D`` with ``v[0] = 0``, where ``D`` is
        the diagonal of the frame-0 bounding box.

    Raises
    ------
    InputError
        Wrong shape, fewer than 6 frames, non-finite values, degenerate bounding box.
    """
    x = _checked_positions(positions, source)
    return _curves(x, _bbox_diagonal(x[0], source))


def descriptor(positions, *, n_frames: int | None = 31, source: object = "positions") -> np.ndarray:
    """The five-dimensional response descriptor phi of SPEC §5.

    ``phi = [sum_t r^t, (r^5 - r^0)/5, max_t v^t, sum_t v^t, sum_{t=1..5} v^t / sum_t v^t]``
    in the order of :data:`FEATURE_NAMES`, computed in float32 from all supplied particles.

    Parameters
    ----------
    positions:
        Particle positions [m], shape (T, N, 3), frame 0 being the rest state.
    n_frames:
        Required frame count T (31 exported frames including t = 0); ``None`` accepts any
        T >= 6.
    source:
        Named in errors (a file path or a short description).

    Returns
    -------
    numpy.ndarray
        Shape (5,), float64 holding the float32 results.

    Raises
    ------
    InputError
        Wrong shape or frame count, non-finite values, degenerate bounding box, or no motion
        at all (the early-velocity ratio would be 0/0).
    """
    x = _checked_positions(positions, source, n_frames)
    r, v = _curves(x, _bbox_diagonal(x[0], source))
    return curve_descriptor(r, v, source=source)


def curve_descriptor(r, v, *, source: object = "curves") -> np.ndarray:
    """phi from the normalized curves ``r`` and ``v`` (shape (T,), T >= 6, ``v[0] = 0``): the
    last step of :func:`descriptor`, shared with descriptors of point sets without
    correspondence (:func:`knockgs_core.observe.pointset_descriptor`)."""
    r = np.asarray(r, dtype=_F32)
    v = np.asarray(v, dtype=_F32)
    if r.shape != v.shape or r.ndim != 1 or r.size < _MIN_FRAMES:
        raise InputError(source, "frame", f"need two curves of the same length >= {_MIN_FRAMES}, got {r.shape}, {v.shape}")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(v))):
        raise InputError(source, "positions", "non-finite displacement curve")
    v_sum = np.sum(v, dtype=_F32)
    if not v_sum > 0:
        raise InputError(
            source,
            "positions",
            "no motion: every frame equals frame 0, the descriptor is undefined",
        )
    phi = np.array(
        [
            np.sum(r, dtype=_F32),
            (r[_EARLY] - r[0]) / _F32(_EARLY),
            np.max(v),
            v_sum,
            np.sum(v[1 : _EARLY + 1], dtype=_F32) / v_sum,
        ],
        dtype=_F32,
    )
    return phi.astype(np.float64)


def descriptor_from_rollout(
    path: PathLike, *, particles: Iterable[int] | None = None, n_frames: int | None = 31
) -> np.ndarray:
    """Descriptor of a rollout Parquet file (see :func:`read_positions` and :func:`descriptor`).

    ``particles`` optionally restricts the descriptor to a subset of particle ids (for
    example the Gaussian-associated particles); errors name the file.
    """
    positions = read_positions(path, particles=particles)
    return descriptor(positions, n_frames=n_frames, source=os.fspath(path))


def descriptor_table(named_positions_or_paths, *, n_frames: int | None = 31):
    """A tidy table: one row per case, columns ``case_name`` + :data:`FEATURE_NAMES`.

    Parameters
    ----------
    named_positions_or_paths:
        A mapping ``case_name -> positions [T, N, 3] or rollout Parquet path``, or an
        iterable of ``(case_name, item)`` pairs. Row order follows the input.
    n_frames:
        Required frame count, as in :func:`descriptor`.
    """
    import pandas as pd

    items = (
        named_positions_or_paths.items()
        if isinstance(named_positions_or_paths, Mapping)
        else named_positions_or_paths
    )
    names, rows = [], []
    for name, item in items:
        if isinstance(item, (str, os.PathLike)):
            phi = descriptor_from_rollout(item, n_frames=n_frames)
        else:
            phi = descriptor(item, n_frames=n_frames, source=f"case {name!r}")
        names.append(str(name))
        rows.append(phi)
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise InputError("descriptor table", "case_name", f"duplicate case names {dup}")
    table = pd.DataFrame(np.reshape(rows, (len(rows), len(FEATURE_NAMES))), columns=FEATURE_NAMES)
    table.insert(0, "case_name", names)
    return table
