"""Sparse pyramidal Lucas-Kanade with sub-pixel refinement, in NumPy/SciPy (private).

Each point is a square window of ``2 radius + 1`` pixels (Gaussian weights, std ``radius / 2``)
of a reference image, found in another image by the inverse-compositional Gauss-Newton
iteration on a pure translation (Baker and Matthews, "Lucas-Kanade 20 years on", IJCV 2004),
coarse to fine over an image pyramid. Images are sampled by cubic B-splines (SciPy's
``map_coordinates`` on prefiltered coefficients), so the iteration converges to the minimum of
the interpolated sum of squared differences rather than to a bilinear approximation of it.
Pixel coordinates: ``(row, col)``, pixel centres at integers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Pyramid", "pyramid", "mask_levels", "track_windows", "window_offsets"]


@dataclass(frozen=True)
class Pyramid:
    """An image at ``levels`` resolutions, level 0 the finest (smoothed by ``sigma`` px):
    ``coef`` [levels] cubic-spline coefficients of each level [H_l, W_l]; ``grad`` [levels]
    its (d/drow, d/dcol) coefficients, each [H_l, W_l]; ``shape`` [levels] (H_l, W_l).
    Level ``l`` has pixel centres at ``(x + 0.5) / 2**l - 0.5`` of level 0's."""

    coef: list
    grad: list
    shape: list


def pyramid(image, *, levels: int, sigma: float = 0.7) -> Pyramid:
    """The pyramid of ``image`` [H, W] (float): level 0 smoothed by a Gaussian of std ``sigma``
    [px], each coarser level the 2x2 means of the one above (smoothed by std 1 px first);
    stops early where a level would be under 16 px on a side."""
    from scipy.ndimage import gaussian_filter, spline_filter

    img = gaussian_filter(np.asarray(image, dtype=np.float64), sigma) if sigma > 0 else np.asarray(image, np.float64)
    coef, grad, shape = [], [], []
    for level in range(levels):
        gr, gc = np.gradient(img)
        coef.append(spline_filter(img, order=3, mode="nearest"))
        grad.append((spline_filter(gr, order=3, mode="nearest"), spline_filter(gc, order=3, mode="nearest")))
        shape.append(img.shape)
        H2, W2 = img.shape[0] // 2, img.shape[1] // 2
        if level + 1 == levels or min(H2, W2) < 16:
            break
        img = gaussian_filter(img, 1.0)[: 2 * H2, : 2 * W2].reshape(H2, 2, W2, 2).mean(axis=(1, 3))
    return Pyramid(coef=coef, grad=grad, shape=shape)


def mask_levels(mask, levels: int) -> list:
    """A segmentation [H, W] (bool) as weights in [0, 1] at each pyramid level (2x2 means),
    level 0 the mask itself; for :func:`track_windows`' ``ref_mask``."""
    out = [np.asarray(mask, dtype=np.float64)]
    for _ in range(1, levels):
        m = out[-1]
        H2, W2 = m.shape[0] // 2, m.shape[1] // 2
        if min(H2, W2) < 16:
            break
        out.append(m[: 2 * H2, : 2 * W2].reshape(H2, 2, W2, 2).mean(axis=(1, 3)))
    return out


def window_offsets(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Offsets [K, 2] (row, col) of a ``(2 radius + 1)^2`` window and their Gaussian weights [K]
    (std ``radius / 2``, summing to 1)."""
    r = np.arange(-radius, radius + 1, dtype=np.float64)
    off = np.stack(np.meshgrid(r, r, indexing="ij"), axis=-1).reshape(-1, 2)
    w = np.exp(-0.5 * np.sum(off**2, axis=1) / (0.5 * radius) ** 2)
    return off, w / w.sum()


def _sample(coef: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Cubic-spline values of ``coef`` [H, W] at ``pts`` [..., 2] (row, col)."""
    from scipy.ndimage import map_coordinates

    flat = pts.reshape(-1, 2).T
    return map_coordinates(coef, flat, order=3, mode="nearest", prefilter=False).reshape(pts.shape[:-1])


def _sample_linear(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Bilinear values of ``img`` [H, W] at ``pts`` [..., 2] (row, col)."""
    from scipy.ndimage import map_coordinates

    return map_coordinates(img, pts.reshape(-1, 2).T, order=1, mode="nearest").reshape(pts.shape[:-1])


def _to_level(p: np.ndarray, level: int) -> np.ndarray:
    return (p + 0.5) / 2.0**level - 0.5


def _from_level(p: np.ndarray, level: int) -> np.ndarray:
    return (p + 0.5) * 2.0**level - 0.5


def track_windows(ref: Pyramid, cur: Pyramid, points, guess, *, radius: int, ref_mask: list | None = None,
                  iterations: int = 30, tol: float = 1e-4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the windows of ``ref`` centred on ``points`` [M, 2] (level-0 pixels) lie in
    ``cur``, starting from ``guess`` [M, 2], coarse to fine. ``ref_mask``
    (:func:`mask_levels`): only the window's pixels inside it count (a static background or
    support next to the object does not hold the window back).

    Returns (positions [M, 2] in level-0 pixels; residual [M]: the weighted RMS intensity
    difference of each window at its solution; conditioned [M] bool: the window's structure
    tensor is invertible with a smaller eigenvalue at least 1e-3 of the larger, i.e. it has
    texture in two directions). ``tol`` [px at the level]: the step below which a point
    stops iterating."""
    pts = np.asarray(points, dtype=np.float64)
    pos = np.asarray(guess, dtype=np.float64).copy()
    off, w = window_offsets(radius)
    levels = min(len(ref.coef), len(cur.coef))
    M = len(pts)
    cond = np.ones(M, dtype=bool)
    residual = np.zeros(M)
    for level in range(levels - 1, -1, -1):
        # at a coarse level the window covers 2**level times the area: the same radius in its pixels
        c = _to_level(pts, level)[:, None, :] + off[None]
        T = _sample(ref.coef[level], c)
        wl = w[None] * (_sample_linear(ref_mask[min(level, len(ref_mask) - 1)], c) if ref_mask is not None
                        else np.ones((M, 1)))
        gr = _sample(ref.grad[level][0], c)
        gc = _sample(ref.grad[level][1], c)
        H = np.empty((M, 2, 2))
        H[:, 0, 0] = np.sum(wl * gr * gr, axis=1)
        H[:, 0, 1] = H[:, 1, 0] = np.sum(wl * gr * gc, axis=1)
        H[:, 1, 1] = np.sum(wl * gc * gc, axis=1)
        tr = H[:, 0, 0] + H[:, 1, 1]
        det = H[:, 0, 0] * H[:, 1, 1] - H[:, 0, 1] ** 2
        disc = np.sqrt(np.maximum(0.25 * tr**2 - det, 0.0))
        lo, hi = 0.5 * tr - disc, 0.5 * tr + disc
        ok = (hi > 0) & (lo >= 1e-3 * hi) & (det > 0)
        if level == 0:
            cond = ok
        Hinv = np.zeros_like(H)
        Hinv[ok, 0, 0] = H[ok, 1, 1] / det[ok]
        Hinv[ok, 1, 1] = H[ok, 0, 0] / det[ok]
        Hinv[ok, 0, 1] = Hinv[ok, 1, 0] = -H[ok, 0, 1] / det[ok]
        p = _to_level(pos, level)
        active = ok.copy()
        for _ in range(iterations):
            if not active.any():
                break
            idx = np.flatnonzero(active)
            e = _sample(cur.coef[level], p[idx, None, :] + off[None]) - T[idx]
            b = np.stack([np.sum(wl[idx] * gr[idx] * e, axis=1), np.sum(wl[idx] * gc[idx] * e, axis=1)], axis=1)
            step = np.einsum("mij,mj->mi", Hinv[idx], b)
            p[idx] -= step
            active[idx[np.max(np.abs(step), axis=1) < tol]] = False
        pos = _from_level(p, level)
        if level == 0:
            e = _sample(cur.coef[0], p[:, None, :] + off[None]) - T
            residual = np.sqrt(np.sum(wl * e**2, axis=1) / np.maximum(np.sum(wl, axis=1), 1e-12))
    return pos, residual, cond
