"""Measured point trajectories: files in, correspondence to simulated particles (private).

Long-table files (Parquet or CSV), one row per (frame, point)::

    frame (int) or time (float, s), particle (int) or track (int), x, y, z (float, m)

``particle`` is the identity of the simulated particle (its row in the object's particle
set); ``track`` is an arbitrary point id without that identity. NPZ files hold arrays
``positions`` [T, M, 3], ``frames`` [T] or ``times`` [T], and ``particle`` [M] or
``track`` [M]. Parquet metadata (key ``knockgs_measurement``, JSON) and NPZ array
``meta`` (a JSON string) may carry ``object``, ``profile``, ``probe``, ``noise_std`` (the
noise std per coordinate the user declares), ``tracker_error_std`` (a tracker's estimate of
its own error per coordinate, ``knockgs observe tracks``) and ``noise_source`` (where
``noise_std`` came from). Without a declared ``noise_std``, a ``tracker_error_std`` becomes
the noise (``noise_std``, with ``noise_source`` saying so), which the discrepancy loop then
uses instead of its estimate from the residual.
Every point must be present in every frame; frame 0 (t = 0, the rest state before the
probe acts) must be present. Frames are integers (7.5 is refused, not truncated); the
metadata's ``noise_std`` and ``tracker_error_std`` are finite numbers >= 0 [m] and
``object``, ``profile``, ``probe`` and ``noise_source`` are names. A KnockGS rollout
(metadata key ``knockgs``: a simulation with its theta) is not a measurement and is refused.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io import atomic_write, write_npz, write_parquet
from ..errors import InputError

__all__ = ["Measurement", "read_measured", "write_measured", "Correspondence", "match_points", "MEASUREMENT_META_KEY",
           "MEASUREMENT_META_FIELDS"]

MEASUREMENT_META_KEY = b"knockgs_measurement"
#: the metadata fields a measurement file may carry (anything else is refused, so no
#: label such as a planted effect or a true theta can ride along)
MEASUREMENT_META_FIELDS = ("object", "profile", "probe", "noise_std", "tracker_error_std", "noise_source", "description",
                           "units")

#: ``noise_source`` of a noise taken from the tracker's estimate
TRACKER_NOISE_SOURCE = "the tracker's error estimate (metadata tracker_error_std: knockgs observe tracks)"


@dataclass(frozen=True, eq=False)
class Measurement:
    """Tracked points of one probe response.

    Attributes
    ----------
    points: [T, M, 3] float64
        Measured positions [m] in the normalized domain of the object.
    frames: [T] int64 or None
        Indices into the probe's export schedule (``t = frame * frame_dt``), when given.
    times: [T] float64 or None
        Measurement times [s], when given instead of frames.
    particle: [M] int64 or None
        Identity: the simulated particle of each point; None for tracks without identity.
    track: [M] int64
        Point ids as in the file.
    meta: dict
        ``object``, ``profile``, ``probe``, ``noise_std`` (per-coordinate std [m]) when known
        and ``noise_source``: where it came from (module docs: a tracker's
        ``tracker_error_std`` is the noise when none is declared).
    source: str
        Where it came from.
    """

    points: np.ndarray
    frames: np.ndarray | None
    times: np.ndarray | None
    particle: np.ndarray | None
    track: np.ndarray
    meta: dict = field(default_factory=dict)
    source: str = "measurement"

    def __post_init__(self):
        X = np.asarray(self.points, dtype=np.float64)
        if X.ndim != 3 or X.shape[2] != 3 or X.shape[0] < 2 or X.shape[1] < 1:
            raise InputError(self.source, "x", f"expected positions [T >= 2, M >= 1, 3], got {list(X.shape)}")
        if not np.all(np.isfinite(X)):
            raise InputError(self.source, "x", "non-finite positions")
        if (self.frames is None) == (self.times is None):
            raise InputError(self.source, "frame", "give exactly one of frames or times")
        T, M = X.shape[:2]
        if self.frames is not None:
            f = np.asarray(self.frames, dtype=np.int64)
            if f.shape != (T,) or np.any(np.diff(f) <= 0) or f[0] != 0:
                raise InputError(self.source, "frame", "frames must be increasing, start at 0 and match the positions")
            object.__setattr__(self, "frames", f)
        else:
            t = np.asarray(self.times, dtype=np.float64)
            if t.shape != (T,) or np.any(np.diff(t) <= 0) or abs(t[0]) > 1e-9 or not np.all(np.isfinite(t)):
                raise InputError(self.source, "time", "times must be finite, increasing, start at 0 and match the positions")
            object.__setattr__(self, "times", t)
        if self.particle is not None:
            p = np.asarray(self.particle, dtype=np.int64)
            if p.shape != (M,) or np.any(p < 0):
                raise InputError(self.source, "particle", "particle ids must be >= 0, one per point")
            object.__setattr__(self, "particle", p)
        tr = np.asarray(self.track, dtype=np.int64)
        if tr.shape != (M,) or len(np.unique(tr)) != M:
            raise InputError(self.source, "track", "point ids must be unique, one per point")
        object.__setattr__(self, "points", X)
        object.__setattr__(self, "track", tr)
        bad = set(self.meta) - set(MEASUREMENT_META_FIELDS)
        if bad:
            raise InputError(self.source, "metadata", f"unknown fields {sorted(bad)}; allowed: {list(MEASUREMENT_META_FIELDS)}")
        _check_meta_values(self.meta, self.source)
        meta = dict(self.meta)
        if meta.get("noise_std") is None and meta.get("tracker_error_std") is not None:
            meta["noise_std"] = float(meta["tracker_error_std"])
            meta["noise_source"] = TRACKER_NOISE_SOURCE
        elif meta.get("noise_std") is not None and meta.get("noise_source") is None:
            meta["noise_source"] = "declared (metadata noise_std)"
        object.__setattr__(self, "meta", meta)

    @property
    def has_identity(self) -> bool:
        return self.particle is not None

    @property
    def n_frames(self) -> int:
        return self.points.shape[0]

    @property
    def n_points(self) -> int:
        return self.points.shape[1]

    def frame_indices(self, frame_dt: float, n_frames: int) -> np.ndarray:
        """Indices of the measured frames in an export schedule ``k * frame_dt``,
        ``k < n_frames``; a time off the schedule (by more than 1e-4 frame_dt) is an error."""
        if self.frames is not None:
            idx = self.frames
        else:
            k = np.rint(self.times / frame_dt).astype(np.int64)
            off = np.abs(self.times - k * frame_dt)
            if np.any(off > 1e-4 * frame_dt + 1e-9):
                i = int(np.argmax(off))
                raise InputError(self.source, "time",
                                 f"time {self.times[i]:.6g} s is not on the probe's export schedule (every {frame_dt:g} s)")
            idx = k
        if idx[-1] >= n_frames:
            raise InputError(self.source, "frame", f"frame {int(idx[-1])} is past the probe's {n_frames} exported frames")
        return idx


def _check_meta_values(meta: dict, source) -> None:
    """Metadata values that mean something: names are non-empty strings, the noise std and
    the tracker's error std finite numbers >= 0 (a string, a negative number or NaN is
    refused, naming the field)."""
    for key in ("object", "profile", "probe", "noise_source"):
        v = meta.get(key)
        if v is not None and not (isinstance(v, str) and v.strip()):
            raise InputError(source, f"metadata.{key}", f"must be a name (a non-empty string), got {v!r}")
    for key in ("noise_std", "tracker_error_std"):
        v = meta.get(key)
        if v is not None:
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0
            if not ok:
                raise InputError(source, f"metadata.{key}", f"must be a finite number >= 0 [m], got {v!r}")


def _meta_from_bytes(raw, source) -> dict:
    try:
        meta = json.loads(raw)
    except (TypeError, ValueError) as exc:
        raise InputError(source, "metadata", f"not JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise InputError(source, "metadata", "must be a JSON object")
    return meta


def _from_long(df, source, meta) -> Measurement:
    cols = set(df.columns)
    for c in ("x", "y", "z"):
        if c not in cols:
            raise InputError(source, c, "missing column")
    if ("frame" in cols) == ("time" in cols):
        raise InputError(source, "frame", "need exactly one of the columns 'frame' or 'time'")
    if ("particle" in cols) == ("track" in cols):
        raise InputError(source, "particle", "need exactly one of the columns 'particle' (identity) or 'track' (no identity)")
    tcol = "frame" if "frame" in cols else "time"
    pcol = "particle" if "particle" in cols else "track"
    if len(df) == 0:
        raise InputError(source, tcol, "no rows")

    def numbers(col):
        try:
            v = df[col].to_numpy(dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(source, col, f"expected numbers, got {df[col].dtype} values") from None
        if not np.all(np.isfinite(v)):
            raise InputError(source, col, "empty or non-finite values")
        return v

    tv = numbers(tcol)
    pv = numbers(pcol)
    if tcol == "frame":
        if np.any(tv != np.rint(tv)):
            i = int(np.argmax(tv != np.rint(tv)))
            raise InputError(source, "frame", f"frame indices must be integers, got {tv[i]:g}")
        tv = tv.astype(np.int64)
    if np.any(pv != np.rint(pv)):
        raise InputError(source, pcol, "point ids must be integers")
    pv = pv.astype(np.int64)
    t_u, t_inv = np.unique(tv, return_inverse=True)
    p_u, p_inv = np.unique(pv, return_inverse=True)
    T, M = len(t_u), len(p_u)
    if T * M != len(df):
        raise InputError(source, tcol, f"{len(df)} rows do not form {T} frames x {M} points (every point must be in every frame)")
    X = np.full((T, M, 3), np.nan)
    seen = np.zeros((T, M), dtype=bool)
    seen[t_inv, p_inv] = True
    if not seen.all():
        raise InputError(source, pcol, "duplicate (frame, point) rows")
    X[t_inv, p_inv] = np.stack([numbers(c) for c in ("x", "y", "z")], axis=1)
    return Measurement(
        points=X,
        frames=t_u if tcol == "frame" else None,
        times=t_u if tcol == "time" else None,
        particle=p_u if pcol == "particle" else None,
        track=p_u,
        meta=meta,
        source=source,
    )


def read_measured(path) -> Measurement:
    """Read measured trajectories from ``.parquet``, ``.csv`` or ``.npz`` (module docs)."""
    path = Path(path)
    source = str(path)
    if not path.exists():
        raise InputError(source, "file", "no such file")
    if not path.is_file():
        raise InputError(source, "file", "not a regular file (a folder?)")
    suffix = path.suffix.lower()
    if suffix == ".parquet":
        import pyarrow.parquet as pq

        try:
            table = pq.read_table(path)
        except Exception as exc:  # pyarrow raises several types
            raise InputError(source, "file", f"not a readable Parquet file ({exc})") from None
        md = table.schema.metadata or {}
        if b"knockgs" in md:
            raise InputError(source, "metadata.knockgs", "this is a KnockGS rollout (a simulation with its theta), "
                             "not a measurement")
        meta = _meta_from_bytes(md[MEASUREMENT_META_KEY], source) if MEASUREMENT_META_KEY in md else {}
        return _from_long(table.to_pandas(), source, meta)
    if suffix == ".csv":
        import pandas as pd

        try:
            df = pd.read_csv(path)
        except Exception as exc:
            raise InputError(source, "file", f"not a readable CSV file ({exc})") from None
        return _from_long(df, source, {})
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except Exception as exc:  # BadZipFile, EOFError, ValueError (object arrays), OSError
            raise InputError(source, "file", f"not a readable .npz file ({type(exc).__name__}: {exc})") from None
        if "positions" not in arrays:
            raise InputError(source, "positions", "missing array")
        meta = _meta_from_bytes(str(arrays["meta"]), source) if "meta" in arrays else {}
        X = arrays["positions"]
        if not (np.issubdtype(X.dtype, np.floating) or np.issubdtype(X.dtype, np.integer)):
            raise InputError(source, "positions", f"expected numbers, got {X.dtype}")
        M = X.shape[1] if X.ndim == 3 else 0
        particle = arrays.get("particle")
        track = arrays["track"] if "track" in arrays else (particle if particle is not None else np.arange(M))
        frames = arrays.get("frames")
        if frames is not None and (not np.issubdtype(frames.dtype, np.number) or np.any(frames != np.rint(frames))):
            raise InputError(source, "frames", "frame indices must be integers")
        try:
            return Measurement(points=X, frames=frames, times=arrays.get("times"), particle=particle, track=track,
                               meta=meta, source=source)
        except (TypeError, ValueError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(source, "positions", f"malformed arrays ({exc})") from None
    raise InputError(source, "file", f"unknown format '{suffix}'; use .parquet, .csv or .npz")


def write_measured(path, measurement: Measurement) -> None:
    """Write a measurement (Parquet with metadata, CSV without, or NPZ), atomically."""
    path = Path(path)
    m = measurement
    T, M = m.n_frames, m.n_points
    tname, tvals = ("frame", m.frames) if m.frames is not None else ("time", m.times)
    pname, pvals = ("particle", m.particle) if m.has_identity else ("track", m.track)
    suffix = path.suffix.lower()
    if suffix in (".parquet", ".csv"):
        import pandas as pd

        df = pd.DataFrame({
            tname: np.repeat(tvals, M),
            pname: np.tile(pvals, T),
            "x": m.points[:, :, 0].reshape(-1),
            "y": m.points[:, :, 1].reshape(-1),
            "z": m.points[:, :, 2].reshape(-1),
        })
        if suffix == ".csv":
            with atomic_write(path, mode="w") as fh:
                df.to_csv(fh, index=False, float_format="%.9g")
        else:
            import pyarrow as pa

            table = pa.Table.from_pandas(df, preserve_index=False)
            table = table.replace_schema_metadata({MEASUREMENT_META_KEY: json.dumps(m.meta).encode()})
            write_parquet(path, table, compression="zstd")
    elif suffix == ".npz":
        times_key = tname + "s" if tname == "frame" else "times"
        write_npz(path, positions=m.points, **{times_key: tvals, pname: pvals}, meta=np.array(json.dumps(m.meta)))
    else:
        raise InputError(str(path), "file", f"unknown format '{path.suffix}'; use .parquet, .csv or .npz")


@dataclass(frozen=True, eq=False)
class Correspondence:
    """Which simulated particle each measured point is compared with.

    ``index`` [M]: particle rows; ``identity``: from the file (True) or matched by nearest
    neighbour at frame 0 among the Gaussian-associated particles (False);
    ``match_distance`` [M]: frame-0 distance to the matched particle [m] (0 with identity
    is not assumed: it is the measured frame-0 offset)."""

    index: np.ndarray
    identity: bool
    match_distance: np.ndarray

    def observe(self, simulated: np.ndarray, frames: np.ndarray, measured_frame0: np.ndarray) -> np.ndarray:
        """The simulated counterpart of the measurement: ``simulated`` [T_sim, N, 3] at
        ``frames`` for the matched particles. Without identity, each point's simulated
        displacement is added to its measured frame-0 position (its rest position is not
        known better than that)."""
        Y = np.asarray(simulated, dtype=np.float64)[frames][:, self.index]
        if not self.identity:
            Y = Y - Y[0] + measured_frame0
        return Y


def match_points(measurement: Measurement, rest_positions: np.ndarray, n_gs: int) -> Correspondence:
    """Correspondence of measured points to simulated particles (see :class:`Correspondence`).

    With identity the particle ids must exist (< number of particles). Without it, each
    point is matched to the nearest Gaussian-associated particle (rows ``< n_gs``, the
    surface that a tracker can see) at frame 0; several points may share a particle."""
    rest = np.asarray(rest_positions, dtype=np.float64)
    x0 = measurement.points[0]
    if measurement.has_identity:
        idx = measurement.particle
        if idx.max() >= len(rest):
            raise InputError(measurement.source, "particle",
                             f"particle id {int(idx.max())} >= number of simulated particles {len(rest)}")
        return Correspondence(index=idx, identity=True, match_distance=np.linalg.norm(x0 - rest[idx], axis=1))
    from scipy.spatial import cKDTree

    if n_gs < 1:
        raise InputError(measurement.source, "track", "no Gaussian-associated particles to match against")
    d, idx = cKDTree(rest[:n_gs]).query(x0)
    return Correspondence(index=np.asarray(idx, dtype=np.int64), identity=False, match_distance=np.asarray(d))
