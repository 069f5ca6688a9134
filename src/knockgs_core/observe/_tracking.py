"""ID-free observations from RGB-D frames: optical-flow tracks, depth point sets, and the
Gaussian particles a camera sees (private).

``track_points``: seeds on frame-0 corners (Harris, inside the object's segmentation), followed
through the frames, lifted to 3-D by the rendered depth, optionally with Gaussian depth noise.
Two ways to follow them:

- ``lk``: sparse pyramidal Lucas-Kanade with sub-pixel refinement (``_lucas_kanade``): each
  seed's frame-0 window (its pixels inside the object's segmentation) is found in every frame
  directly, started from the previous frame's solution, so no error accumulates from frame to
  frame; a solution that does not track back onto its seed within ``fb_max`` px
  (forward-backward check) drops the track; the depth is frame 0's at the seed plus the
  rendered depth's change over a window of ``depth_radius`` px;
- ``ilk`` / ``tvl1``: dense optical flow between consecutive frames (scikit-image's
  ``optical_flow_ilk`` or ``optical_flow_tvl1``) added up along each track, lifted by the
  depth at the tracked pixel (bilinear).

A track that leaves the image or the object's coverage, or whose depth jumps across a depth
edge, is dropped; the tracks kept follow one image feature each, not a material particle.
:func:`tracking_error` estimates their error from their scatter about a smooth motion field.
``depth_point_sets``: every covered pixel back-projected, per frame, without any
correspondence. ``visible_particles``: the particles a camera sees in every frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ._rgbd import RGBDFrames, project, unproject

__all__ = ["TrackSettings", "PixelTracks", "track_pixels", "track_points", "tracking_error",
           "depth_point_sets", "visible_particles", "pointset_descriptor"]

#: the flow methods of :class:`TrackSettings`
TRACK_METHODS = ("lk", "ilk", "tvl1")


@dataclass(frozen=True)
class TrackSettings:
    """``max_seeds`` strongest Harris corners of frame 0 at least ``min_distance`` px apart
    where the coverage is at least ``alpha_min``; flow ``method`` (module docs; ``lk`` and
    ``ilk``: window radius ``radius`` px; ``lk``: ``levels`` pyramid levels, forward-backward
    tolerance ``fb_max`` [px], depth change over a window of ``depth_radius`` px; ``tvl1``);
    Gaussian depth noise of std ``depth_noise`` [m] (seeded by ``seed``); at least
    ``min_tracks`` must survive every frame; seeds stay ``edge_margin`` px from the silhouette
    and off depth edges (a depth range above ``depth_edge`` [m] in their window). The
    defaults are the first tracker's (``ilk``, radius 5); ``knockgs observe tracks``, the
    calibration route and the observation ladder use ``lk`` with ``radius`` 7, which follows the
    rendered truth more closely and in less time (docs/discrepancy.md, "Video observations: the
    tracker's error")."""

    max_seeds: int = 400
    min_distance: int = 2
    alpha_min: float = 0.9
    method: str = "ilk"
    radius: int = 5
    depth_noise: float = 0.0
    seed: int = 0
    min_tracks: int = 8
    edge_margin: int = 1
    depth_edge: float = 0.05
    levels: int = 3
    depth_radius: int = 4
    fb_max: float = 0.3

    def __post_init__(self):
        if self.method not in TRACK_METHODS:
            raise InputError("TrackSettings", "method", f"must be one of {', '.join(TRACK_METHODS)}; got {self.method!r}")
        for name in ("radius", "levels", "depth_radius"):
            if getattr(self, name) < 1:
                raise InputError("TrackSettings", name, f"must be >= 1, got {getattr(self, name)!r}")
        if not (self.fb_max > 0):
            raise InputError("TrackSettings", "fb_max", f"must be > 0 px, got {self.fb_max!r}")
        if not (self.depth_noise >= 0):
            raise InputError("TrackSettings", "depth_noise", f"must be >= 0, got {self.depth_noise!r}")
        if self.max_seeds < 1 or self.min_tracks < 1:
            raise InputError("TrackSettings", "max_seeds", "max_seeds and min_tracks must be >= 1")


def _gray(rgb: np.ndarray) -> np.ndarray:
    return (0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]).astype(np.float32)


def _bilinear(img: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``img`` [H, W] (or [H, W, C]) sampled at fractional pixel coordinates (clamped)."""
    H, W = img.shape[:2]
    r = np.clip(rows, 0.0, H - 1.0)
    c = np.clip(cols, 0.0, W - 1.0)
    r0, c0 = np.floor(r).astype(int), np.floor(c).astype(int)
    r1, c1 = np.minimum(r0 + 1, H - 1), np.minimum(c0 + 1, W - 1)
    fr, fc = r - r0, c - c0
    if img.ndim == 3:
        fr, fc = fr[:, None], fc[:, None]
    return ((1 - fr) * (1 - fc) * img[r0, c0] + (1 - fr) * fc * img[r0, c1]
            + fr * (1 - fc) * img[r1, c0] + fr * fc * img[r1, c1])


def _seeds(frames: RGBDFrames, s: TrackSettings) -> np.ndarray:
    """Harris corners of frame 0 inside the covered region (and the object's segmentation when
    the frames carry one), ``edge_margin`` px inside it and where the depth varies by at most
    ``depth_edge`` over the same window, at least 1 % of the strongest response there."""
    from skimage.feature import corner_harris, corner_peaks

    from scipy.ndimage import binary_erosion, maximum_filter, minimum_filter

    response = corner_harris(_gray(frames.rgb[0]))
    region = frames.alpha[0] >= s.alpha_min
    if frames.mask is not None:
        region &= frames.mask
    # away from the silhouette and from depth edges, where the lifted depth mixes surfaces
    region = binary_erosion(region, iterations=s.edge_margin)
    d0 = frames.depth[0]
    region &= (maximum_filter(d0, size=2 * s.edge_margin + 1) - minimum_filter(d0, size=2 * s.edge_margin + 1)) <= s.depth_edge
    if not region.any():
        raise InputError(frames.source, "mask", "no covered pixel of the object in frame 0 to seed tracks on")
    top = float(response[region].max())
    if not top > 0:
        return np.zeros((0, 2))
    peaks = corner_peaks(np.where(region, response, 0.0), min_distance=s.min_distance, threshold_abs=0.01 * top,
                         exclude_border=2)
    if len(peaks) > s.max_seeds:
        order = np.argsort(-response[peaks[:, 0], peaks[:, 1]], kind="stable")
        peaks = peaks[np.sort(order[: s.max_seeds])]
    return peaks.astype(np.float64)


@dataclass(frozen=True)
class PixelTracks:
    """Tracks in the image: ``rows``, ``cols`` [T, M] (pixel centres at integers) and the
    rendered ``depth`` [T, M] [m] there, seen by ``camera``; ``info`` as :func:`track_points`."""

    rows: np.ndarray
    cols: np.ndarray
    depth: np.ndarray
    camera: object
    info: dict

    def to_world(self, *, depth_noise: float = 0.0, seed: int = 0) -> np.ndarray:
        """World points [T, M, 3] [m], with Gaussian depth noise of std ``depth_noise`` [m]."""
        depth = self.depth
        if depth_noise > 0:
            depth = depth + np.random.default_rng(seed).normal(0.0, depth_noise, size=depth.shape)
        return unproject(self.camera, self.rows, self.cols, depth)


def _chained_flow(frames: RGBDFrames, seeds: np.ndarray, s: TrackSettings):
    """Dense flow between consecutive frames (``ilk`` or ``tvl1``) sampled at each track and
    added up. Returns rows, cols [T, M], depth [T, M] (bilinear at the track), alive [M],
    per-frame motion [px] of the live tracks."""
    from skimage.registration import optical_flow_ilk, optical_flow_tvl1

    T = frames.n_frames
    rows = np.empty((T, len(seeds)))
    cols = np.empty((T, len(seeds)))
    alive = np.ones(len(seeds), dtype=bool)
    rows[0], cols[0] = seeds[:, 0], seeds[:, 1]
    H, W = frames.alpha.shape[1:]
    gray = [_gray(f) for f in frames.rgb]
    flow_px = []
    for t in range(1, T):
        if s.method == "ilk":
            flow = optical_flow_ilk(gray[t - 1], gray[t], radius=s.radius)
        else:
            flow = optical_flow_tvl1(gray[t - 1], gray[t])
        dr = _bilinear(flow[0], rows[t - 1], cols[t - 1])
        dc = _bilinear(flow[1], rows[t - 1], cols[t - 1])
        rows[t], cols[t] = rows[t - 1] + dr, cols[t - 1] + dc
        flow_px.append(np.hypot(dr, dc)[alive])
        inside = (rows[t] >= 0) & (rows[t] <= H - 1) & (cols[t] >= 0) & (cols[t] <= W - 1)
        alive &= inside
        alive &= _bilinear(frames.alpha[t], rows[t], cols[t]) >= 0.5
    depth = np.stack([_bilinear(frames.depth[t], rows[t], cols[t]) for t in range(T)])
    return rows, cols, depth, alive, flow_px, {}


def _window_depth_change(frames: RGBDFrames, t: int, seeds: np.ndarray, pos: np.ndarray, radius: int) -> np.ndarray:
    """[M] the change of rendered depth [m] between frame 0 around ``seeds`` and frame ``t``
    around ``pos`` ([M, 2] pixels), the Gaussian-weighted mean over a window of ``radius`` px
    of the pixels covered (coverage >= 0.5) in both frames."""
    from scipy.ndimage import map_coordinates

    from ._lucas_kanade import window_offsets

    off, w = window_offsets(radius)
    a = seeds[:, None, :] + off[None]
    b = pos[:, None, :] + off[None]

    def at(img, c):
        return map_coordinates(img, c.reshape(-1, 2).T, order=1, mode="nearest").reshape(c.shape[:-1])

    cover = (at(frames.alpha[0], a) >= 0.5) & (at(frames.alpha[t], b) >= 0.5)
    if frames.mask is not None:
        cover &= at(frames.mask.astype(np.float64), a) >= 0.5
    ww = w[None] * cover
    diff = at(frames.depth[t], b) - at(frames.depth[0], a)
    return np.sum(ww * diff, axis=1) / np.maximum(np.sum(ww, axis=1), 1e-12)


def _anchored_lk(frames: RGBDFrames, seeds: np.ndarray, s: TrackSettings):
    """Sparse pyramidal Lucas-Kanade (``_lucas_kanade``): every frame's window matched against
    frame 0's (no drift accumulates), started from the previous frame's solution; each
    solution tracked back into frame 0 (forward-backward error); the depth change over the
    window. Returns as :func:`_chained_flow`, with the forward-backward distances [T, M] [px]
    in the extra dict."""
    from ._lucas_kanade import mask_levels, pyramid, track_windows

    T = frames.n_frames
    M = len(seeds)
    H, W = frames.alpha.shape[1:]
    gray = [_gray(f) for f in frames.rgb]
    ref = pyramid(gray[0], levels=s.levels)
    ref_mask = mask_levels(frames.mask, s.levels) if frames.mask is not None else None
    pos = np.empty((T, M, 2))
    pos[0] = seeds
    fb = np.zeros((T, M))
    alive = np.ones(M, dtype=bool)
    d0 = _bilinear(frames.depth[0], seeds[:, 0], seeds[:, 1])
    depth = np.empty((T, M))
    depth[0] = d0
    flow_px = []
    for t in range(1, T):
        cur = pyramid(gray[t], levels=s.levels)
        p, _, ok = track_windows(ref, cur, seeds, pos[t - 1], radius=s.radius, ref_mask=ref_mask)
        back, _, _ = track_windows(cur, ref, p, seeds, radius=s.radius, ref_mask=ref_mask)
        pos[t] = p
        fb[t] = np.hypot(*(back - seeds).T)
        alive &= ok & (fb[t] <= s.fb_max)
        flow_px.append(np.hypot(*(pos[t] - pos[t - 1]).T)[alive])
        inside = (p[:, 0] >= 0) & (p[:, 0] <= H - 1) & (p[:, 1] >= 0) & (p[:, 1] <= W - 1)
        alive &= inside
        alive &= _bilinear(frames.alpha[t], p[:, 0], p[:, 1]) >= 0.5
        depth[t] = d0 + _window_depth_change(frames, t, seeds, p, s.depth_radius)
    return pos[..., 0], pos[..., 1], depth, alive, flow_px, {"fb_px": fb}


def track_pixels(frames: RGBDFrames, settings: TrackSettings = TrackSettings()) -> PixelTracks:
    """Frame-0 features followed through every frame by optical flow (module docs); the
    tracks alive in every frame. Raises :class:`InputError` (naming the frames' source) when
    fewer than ``min_tracks`` survive."""
    s = settings
    seeds = _seeds(frames, s)
    T = frames.n_frames
    if len(seeds) < s.min_tracks:
        raise InputError(frames.source, "tracks", f"{len(seeds)} of {len(seeds)} tracks survive every frame "
                         f"(need {s.min_tracks}): too few frame-0 corners")
    if s.method == "lk":
        rows, cols, depth, alive, flow_px, extra = _anchored_lk(frames, seeds, s)
    else:
        rows, cols, depth, alive, flow_px, extra = _chained_flow(frames, seeds, s)
    # a track whose lifted depth jumps by more than depth_edge between frames has slipped across
    # a depth edge (onto another surface): dropped
    if T > 1:
        alive &= np.max(np.abs(np.diff(depth, axis=0)), axis=0) <= s.depth_edge
    n = int(alive.sum())
    if n < s.min_tracks:
        raise InputError(frames.source, "tracks", f"{n} of {len(seeds)} tracks survive every frame (need {s.min_tracks})")
    rows, cols, depth = rows[:, alive], cols[:, alive], depth[:, alive]
    fp = np.concatenate(flow_px) if flow_px else np.zeros(0)
    info = {"seeds": int(len(seeds)), "tracks": n, "method": s.method,
            "median_flow_px": float(np.median(fp)) if fp.size else 0.0}
    if "fb_px" in extra:
        info["fb_rms_px"] = float(np.sqrt(np.mean(extra["fb_px"][1:, alive] ** 2))) if T > 1 else 0.0
    return PixelTracks(rows=rows, cols=cols, depth=depth, camera=frames.camera, info=info)


def track_points(frames: RGBDFrames, settings: TrackSettings = TrackSettings()) -> tuple[np.ndarray, dict]:
    """Tracks of frame-0 features through every frame, in world coordinates
    (:func:`track_pixels`, lifted with ``settings.depth_noise``).

    Returns (points [T, M, 3] float64: the M tracks alive in every frame, metres; info: seeds,
    tracks kept, the flow method, the depth noise, median flow magnitude [px], ``error_std``:
    the estimate of their error per coordinate [m], :func:`tracking_error`)."""
    tracks = track_pixels(frames, settings)
    points = tracks.to_world(depth_noise=settings.depth_noise, seed=settings.seed)
    return points, {**tracks.info, "depth_noise": settings.depth_noise, "error_std": tracking_error(points)}


def tracking_error(points) -> float:
    """An estimate of tracks' error per coordinate [m]: their scatter about the affine motion
    field that fits them best, frame by frame.

    ``points`` [T, M, 3] (M >= 5): each frame's displacements from frame 0 are fitted by
    least squares as an affine function of the frame-0 positions (4 coefficients per
    coordinate); the estimate is the RMS of what is left, over frames 1.. and coordinates,
    scaled by ``sqrt(M / (M - 4))`` for the fitted coefficients. A tracker's errors differ
    from track to track (a feature on another layer of Gaussians, a static support seen
    through, a depth blended over edges), the motion of a soft body over a few centimetres
    of its surface is nearly affine: the scatter measures the first and holds little of the
    second (measured against the rendered truth: docs/discrepancy.md, "Video observations:
    the tracker's error")."""
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 3 or P.shape[2] != 3 or P.shape[1] < 5 or P.shape[0] < 2:
        raise InputError("tracks", "points", f"need [T >= 2, M >= 5, 3] tracked points, got {list(P.shape)}")
    D = (P[1:] - P[0]).transpose(1, 0, 2).reshape(P.shape[1], -1)  # [M, (T - 1) * 3]
    A = np.column_stack([np.ones(P.shape[1]), P[0] - P[0].mean(axis=0)])
    resid = D - A @ np.linalg.lstsq(A, D, rcond=None)[0]
    M = P.shape[1]
    return float(np.sqrt(np.mean(resid**2) * M / (M - A.shape[1])))


def depth_point_sets(frames: RGBDFrames, *, alpha_min: float = 0.5, stride: int = 1) -> list[np.ndarray]:
    """Per frame, every ``stride``-th covered pixel (coverage at least ``alpha_min``)
    back-projected to world coordinates: a list of [M_t, 3] arrays, no correspondence."""
    out = []
    for t in range(frames.n_frames):
        r, c = np.nonzero(frames.alpha[t][::stride, ::stride] >= alpha_min)
        r, c = r * stride, c * stride
        if len(r) == 0:
            raise InputError(frames.source, "alpha", f"frame {t} covers no pixel")
        out.append(unproject(frames.camera, r, c, frames.depth[t][r, c]))
    return out


def visible_particles(positions, frames: RGBDFrames, *, alpha_min: float = 0.5, depth_tol: float = 0.02) -> np.ndarray:
    """[N] bool: particles (``positions`` [T, N, 3], the frames' rollout) that the camera sees
    in every frame: in front of the camera, inside the image, on a pixel covered at least
    ``alpha_min``, and no more than ``depth_tol`` [m] behind that pixel's rendered depth."""
    X = np.asarray(positions, dtype=np.float64)
    if X.ndim != 3 or X.shape[0] != frames.n_frames:
        raise InputError(frames.source, "frame", f"{frames.n_frames} frames but positions of shape {list(X.shape)}")
    H, W = frames.alpha.shape[1:]
    vis = np.ones(X.shape[1], dtype=bool)
    for t in range(X.shape[0]):
        r, c, z = project(frames.camera, X[t])
        ri, ci = np.rint(r).astype(np.int64), np.rint(c).astype(np.int64)
        ok = (z > 0) & (ri >= 0) & (ri < H) & (ci >= 0) & (ci < W)
        ri, ci = np.clip(ri, 0, H - 1), np.clip(ci, 0, W - 1)
        ok &= frames.alpha[t][ri, ci] >= alpha_min
        ok &= z <= frames.depth[t][ri, ci] + depth_tol
        vis &= ok
    return vis


def pointset_descriptor(point_sets, *, source: object = "point sets") -> np.ndarray:
    """The descriptor of point sets without correspondence (``point_sets``: T arrays [M_t, 3]).

    The displacement of a point is replaced by its distance to the nearest point of the other
    set, symmetrically: ``r^t = sqrt((mean_{p in S_t} d(p, S_0)^2 + mean_{q in S_0} d(q, S_t)^2) / 2) / D``
    (a root-mean-square chamfer distance) and ``v^t`` the same between ``S_t`` and ``S_{t-1}``;
    ``D`` the diagonal of ``S_0``'s bounding box; then phi as for tracked points
    (:func:`knockgs_core.descriptors.curve_descriptor`). A surface moving along itself is
    invisible to it, as to any observation without identities."""
    from scipy.spatial import cKDTree

    from ..descriptors import curve_descriptor

    sets = [np.asarray(p, dtype=np.float64) for p in point_sets]
    if len(sets) < 6 or any(p.ndim != 2 or p.shape[1] != 3 or len(p) == 0 for p in sets):
        raise InputError(source, "points", "need at least 6 frames of non-empty [M, 3] point sets")
    D = float(np.linalg.norm(sets[0].max(axis=0) - sets[0].min(axis=0)))
    if not D > 0:
        raise InputError(source, "points", "degenerate frame-0 bounding box")
    trees = [cKDTree(p) for p in sets]

    def chamfer(a: int, b: int) -> float:
        dab = trees[b].query(sets[a])[0]
        dba = trees[a].query(sets[b])[0]
        return float(np.sqrt(0.5 * (np.mean(dab**2) + np.mean(dba**2))))

    T = len(sets)
    r = np.array([0.0] + [chamfer(t, 0) for t in range(1, T)]) / D
    v = np.array([0.0] + [chamfer(t, t - 1) for t in range(1, T)]) / D
    return curve_descriptor(r, v, source=source)
