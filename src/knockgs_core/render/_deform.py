"""Moving Gaussians with simulated particles, as in PhysGaussian (private)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from knockgs_core.errors import InputError

from ._checks import as_float_array, check_count, check_scene


class Scene(NamedTuple):
    """Render arguments of a Gaussian scene: ``render(*scene, camera)``.

    ``means: [N, 3]``, ``covariances: [N, 3, 3]``, ``colors: [N, 3]``, ``opacities: [N]``.
    """

    means: np.ndarray
    covariances: np.ndarray
    colors: np.ndarray
    opacities: np.ndarray


def deform_covariances(cov0, F) -> np.ndarray:
    """Deformed covariances ``F cov0 F^T`` (PhysGaussian).

    ``cov0: [N, 3, 3]`` rest covariances, ``F: [N, 3, 3]`` deformation gradients;
    returns ``[N, 3, 3]`` float64.
    """
    src = "render.deform_covariances"
    cov0 = as_float_array(cov0, src, "cov0", (-1, 3, 3))
    F = as_float_array(F, src, "F", (-1, 3, 3))
    check_count(F, cov0.shape[0], src, "F", "cov0")
    return _deform(cov0, F)


def _deform(cov0: np.ndarray, F: np.ndarray) -> np.ndarray:
    """``F cov0 F^T`` of checked float64 arrays [N, 3, 3], returned as [N, 3, 3] float64.

    Elementwise products on the nine entry planes, each entry summed in index order
    (``(p0 + p1) + p2``, no fused multiply-add): the arithmetic of the device kernel of
    :func:`render_frames` (``_kernels.deformed_covariance``), which therefore gives the same
    bits. As fast as the stacked ``(F @ cov0) @ F^T`` (whose rounding follows the BLAS in use)
    and equal to it within 1e-15 of each matrix's largest entry.
    """
    n = F.shape[0]
    f = np.ascontiguousarray(F.reshape(n, 9).T)  # f[3 i + k] = F_ik, [9, N]
    s = np.ascontiguousarray(cov0.reshape(n, 9).T)
    a = np.empty((9, n))
    out = np.empty((n, 9))
    tmp = np.empty(n)
    c = np.empty(n)

    def dot3(dst, x0, y0, x1, y1, x2, y2):
        np.multiply(x0, y0, out=dst)
        np.multiply(x1, y1, out=tmp)
        dst += tmp
        np.multiply(x2, y2, out=tmp)
        dst += tmp

    for i in range(3):
        for j in range(3):  # a = F cov0
            dot3(a[3 * i + j], f[3 * i], s[j], f[3 * i + 1], s[3 + j], f[3 * i + 2], s[6 + j])
    for i in range(3):
        for j in range(3):  # (F cov0) F^T
            dot3(c, a[3 * i], f[3 * j], a[3 * i + 1], f[3 * j + 1], a[3 * i + 2], f[3 * j + 2])
            out[:, 3 * i + j] = c
    return out.reshape(n, 3, 3)


def _check_mask(static_mask, n: int, src: str) -> np.ndarray:
    """``static_mask`` as a bool array [n], or an :class:`InputError` naming ``src``."""
    mask = np.asarray(static_mask)
    if mask.dtype != bool or mask.shape != (n,):
        raise InputError(src, "static_mask", f"expected a bool array of shape [{n}], got "
                         f"{mask.dtype} {list(mask.shape)}")
    return mask


def deformed_scene(gaussians_means0, cov0, colors, opacities, positions_t, F_t, static_mask) -> Scene:
    """The Gaussian scene at one time: simulated Gaussians moved, static ones kept.

    Parameters
    ----------
    gaussians_means0: [N, 3]
        Rest centres of all rendered Gaussians (simulated and static support).
    cov0: [N, 3, 3]
        Rest covariances.
    colors: [N, 3]
        RGB in [0, 1].
    opacities: [N]
        In [0, 1].
    positions_t: [M, 3]
        Particle positions at time t of the simulated Gaussians, i.e. of the rows where
        ``static_mask`` is False, in that order (``M = (~static_mask).sum()``). An
        ``[N, 3]`` array (one row per Gaussian) is accepted too; its static rows are ignored.
    F_t: [M, 3, 3] (or [N, 3, 3])
        Deformation gradients at time t, rows as ``positions_t``.
    static_mask: [N] bool
        True for static support Gaussians, which stay at rest.

    Fill particles are never rendered: pass only Gaussian-associated particles.
    Returns a :class:`Scene`, ready for ``render(*scene, camera)``.
    """
    src = "render.deformed_scene"
    means0, cov0, colors, opacities = check_scene(gaussians_means0, cov0, colors, opacities, src)
    n = means0.shape[0]
    mask = _check_mask(static_mask, n, src)
    dyn = np.flatnonzero(~mask)
    pos = as_float_array(positions_t, src, "positions_t", (-1, 3))
    F = as_float_array(F_t, src, "F_t", (-1, 3, 3))
    if pos.shape[0] not in (dyn.size, n):
        raise InputError(src, "positions_t", f"has {pos.shape[0]} rows; expected {dyn.size} "
                         f"(simulated Gaussians) or {n} (all Gaussians)")
    check_count(F, pos.shape[0], src, "F_t", "positions_t")
    if pos.shape[0] == n and dyn.size != n:
        pos, F = pos[dyn], F[dyn]
    means = means0.copy()
    covs = cov0.copy()
    means[dyn] = pos
    covs[dyn] = _deform(cov0[dyn], F)
    return Scene(means, covs, colors, opacities)


def render_frames(gaussians_means0, cov0, colors, opacities, static_mask, positions, F, camera, *,
                  background=(1.0, 1.0, 1.0), device: str = "cpu") -> list:
    """Render every frame of a motion: ``render(*deformed_scene(..., positions[t], F[t], ...),
    camera)`` for each t, with the rest scene checked once rather than per frame.

    ``gaussians_means0 [N, 3]``, ``cov0 [N, 3, 3]``, ``colors [N, 3]``, ``opacities [N]``
    and ``static_mask [N]`` as in :func:`deformed_scene`; ``positions [T, M, 3]`` and
    ``F [T, M, 3, 3]``: the simulated Gaussians' positions and deformation gradients at each
    frame (M = the simulated Gaussians, or N with the static rows ignored; any float dtype,
    each frame checked for finite values as it is rendered). Returns a list of T
    :class:`~knockgs_core.render.RenderOutput`.

    The scene lives in float32 buffers on the Warp ``device``: the static rows (and every
    colour and opacity) are uploaded once per motion; per frame, the simulated rows'
    positions and ``F`` go over in one copy (float32, or float64 when ``F`` is float64) and a
    kernel writes their centres and symmetrized ``F Sigma_0 F^T`` (float64, rounded as the
    host path rounds: the same pixels as :func:`render` of :func:`deformed_scene`). On CUDA the
    projection, tile bins and rasterizer inputs stay on the device too, in buffers allocated
    once per motion (``_frame.DeviceFrames``), and only the image comes back; on the CPU each
    frame is projected and binned through host arrays, as :func:`render` does there.
    """
    return _render_frames(gaussians_means0, cov0, colors, opacities, static_mask, positions, F, camera,
                          background=background, device=device, resident=None)


def _render_frames(gaussians_means0, cov0, colors, opacities, static_mask, positions, F, camera, *,
                   background, device: str, resident: bool | None) -> list:
    """:func:`render_frames` (arguments as there), its frames rendered by ``_frame.DeviceFrames``
    when ``resident`` is True, through ``_pipeline._render_arrays`` when False, and when None
    by the device's default (``_frame.resident_default``: resident on CUDA)."""
    from ._camera import Camera
    from ._checks import check_background
    from ._frame import DeviceFrames, resident_default
    from ._pipeline import _device, _render, _render_arrays

    src = "render.render_frames"
    means0, cov0, colors, opacities = check_scene(gaussians_means0, cov0, colors, opacities, src)
    n = means0.shape[0]
    mask = _check_mask(static_mask, n, src)
    if not isinstance(camera, Camera):
        raise InputError(src, "camera", f"expected a Camera, got {type(camera).__name__}")
    bg = check_background(background, src)
    dyn = np.flatnonzero(~mask)
    P, G = np.asarray(positions), np.asarray(F)
    if P.ndim != 3 or P.shape[1:] not in ((dyn.size, 3), (n, 3)):
        raise InputError(src, "positions", f"expected shape [T, {dyn.size}, 3] (simulated Gaussians) or "
                         f"[T, {n}, 3] (all Gaussians), got {list(P.shape)}")
    if G.shape != P.shape[:2] + (3, 3):
        raise InputError(src, "F", f"expected shape {list(P.shape[:2]) + [3, 3]} (as positions), got {list(G.shape)}")
    rows = dyn if P.shape[1] == n and dyn.size != n else slice(None)
    dev = _device(device)
    if n == 0:  # nothing on the device to keep: the background, frame by frame
        for t in range(P.shape[0]):
            _frame_rows(P, t, rows, src, "positions")
            _frame_rows(G, t, rows, src, "F")
        return [_render(means0, cov0, colors, opacities, camera, bg, device) for _ in range(P.shape[0])]
    scene = _DeviceScene(means0, cov0, colors, opacities, dyn, wide=_frame_dtype(G) == np.float64, dev=dev)
    if resident is None:
        resident = resident_default(dev)
    frames = DeviceFrames(n, camera, bg, dev) if resident else None  # buffers for the whole motion
    out = []
    for t in range(P.shape[0]):
        scene.set_frame(_frame_rows(P, t, rows, src, "positions"), _frame_rows(G, t, rows, src, "F"))
        arrays = (scene.means, scene.covariances, scene.colors, scene.opacities)
        out.append(frames.render(*arrays) if frames is not None else _render_arrays(*arrays, camera, bg, dev))
    return out


def _frame_dtype(a: np.ndarray):
    """The float dtype a frame of ``a`` is checked and copied in: its own float16/32/64, else float64."""
    return a.dtype if a.dtype in (np.float16, np.float32, np.float64) else np.dtype(np.float64)


def _frame_rows(a: np.ndarray, t: int, rows, src: str, field: str) -> np.ndarray:
    """Frame ``t`` of ``a`` (positions ``[T, *, 3]`` or F ``[T, *, 3, 3]``) at ``rows``, checked finite.

    Float16/32/64 frames are checked in their own dtype (no float64 copy of the whole frame);
    any other dtype goes through :func:`as_float_array` (float64, with its errors). Raises an
    :class:`InputError` naming ``field[t]`` on NaN or infinite entries.
    """
    x = a[t][rows]
    if _frame_dtype(a) != a.dtype:
        return as_float_array(x, src, f"{field}[{t}]", (-1,) + a.shape[2:])
    if not np.isfinite(x).all():
        raise InputError(src, f"{field}[{t}]", "contains NaN or infinite values")
    return x


class _DeviceScene:
    """A motion's scene in float32 render buffers on a Warp device (N > 0 Gaussians).

    ``means [N]`` vec3f, ``covariances [N]`` mat33f (symmetrized), ``colors [N]`` vec3f and
    ``opacities [N]`` float32, uploaded once; :meth:`set_frame` rewrites the simulated rows
    ``dyn [M]`` from their rest covariances (``cov0[dyn]``, float64 on the device). ``wide``:
    frames copied as float64 (F given in float64, so that no rounding is added), else float32.
    """

    def __init__(self, means0, cov0, colors, opacities, dyn, *, wide: bool, dev):
        import warp as wp

        f32 = np.float32
        self.dev = dev
        self.m = int(dyn.size)
        self.means = wp.array(means0.astype(f32), dtype=wp.vec3f, device=dev)
        self.covariances = wp.array((0.5 * (cov0 + np.swapaxes(cov0, 1, 2))).astype(f32), dtype=wp.mat33f, device=dev)
        self.colors = wp.array(colors.astype(f32), dtype=wp.vec3f, device=dev)
        self.opacities = wp.array(opacities.astype(f32), dtype=wp.float32, device=dev)
        if self.m == 0:
            return
        self.rows = wp.array(dyn.astype(np.int32), dtype=wp.int32, device=dev)
        self.cov0 = wp.array(np.ascontiguousarray(cov0[dyn]), dtype=wp.mat33d, device=dev)
        dtype = wp.float64 if wide else wp.float32
        # one host staging buffer per motion (page-locked for CUDA), one copy per frame
        self.staging = wp.empty((self.m, 12), dtype=dtype, device="cpu", pinned=dev.is_cuda)
        self.frame = self.staging if dev.is_cpu else wp.empty((self.m, 12), dtype=dtype, device=dev)

    def set_frame(self, positions: np.ndarray, F: np.ndarray) -> None:
        """Move the simulated rows: ``positions [M, 3]`` and ``F [M, 3, 3]`` (checked, finite)."""
        import warp as wp

        from ._kernels import deform_rows_kernel

        if self.m == 0:
            return
        if self.dev.is_cuda:  # the previous frame's copy out of the staging buffer is done
            wp.synchronize_device(self.dev)
        host = self.staging.numpy()  # a view of the staging buffer
        host[:, :3] = positions
        host[:, 3:] = F.reshape(self.m, 9)
        if self.frame is not self.staging:
            wp.copy(self.frame, self.staging)
        wp.launch(deform_rows_kernel, dim=self.m, inputs=[self.frame, self.rows, self.cov0],
                  outputs=[self.means, self.covariances], device=self.dev)


def covariance_to_scale_rotation(cov) -> tuple[np.ndarray, np.ndarray]:
    """Standard deviations and unit quaternions ``(w, x, y, z)`` with ``R diag(s)^2 R^T = cov``.

    ``cov: [N, 3, 3]`` symmetric positive semi-definite; returns ``scales [N, 3]`` (eigenvalues
    clipped at 1e-24 before the square root, so a degenerate covariance gives a tiny, valid
    scale) and ``quats [N, 4]``, float64 (3DGS's PLY parametrization).
    """
    from scipy.spatial.transform import Rotation

    src = "render.covariance_to_scale_rotation"
    cov = as_float_array(cov, src, "cov", (-1, 3, 3))
    evals, evecs = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, 1, 2)))
    flip = np.linalg.det(evecs) < 0  # a proper rotation: flip one axis of reflections
    evecs[flip, :, 2] *= -1.0
    scales = np.sqrt(np.clip(evals, 1e-24, None))
    if cov.shape[0] == 0:
        return scales, np.zeros((0, 4))
    xyzw = Rotation.from_matrix(evecs).as_quat()
    return scales, np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)


def deformed_gaussians(gaussians, gaussian_index, positions_t, F_t):
    """The asset's Gaussians at one time, as a :class:`~knockgs_core.assets.GaussianSet` for a
    standard 3DGS PLY (``knockgs_core.assets.write_ply``), so any frame opens in a splat viewer.

    ``gaussian_index [M]``: the Gaussian row of each simulated (Gaussian-associated) particle;
    ``positions_t [>= M, 3]``: particle positions at time t (the first ``M`` rows are used, the
    fill particles after them are not Gaussians); ``F_t [M, 3, 3]``: their deformation
    gradients. Moved Gaussians get ``Sigma_t = F Sigma_0 F^T`` re-expressed as scales and a
    rotation; the other (static) Gaussians and every colour and opacity are unchanged.
    Higher SH coefficients are kept as they are (not rotated with ``F``).
    """
    from knockgs_core.assets import GaussianSet

    src = "render.deformed_gaussians"
    idx = np.asarray(gaussian_index)
    n = len(gaussians)
    if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer) or (idx.size and (idx.min() < 0 or idx.max() >= n)):
        raise InputError(src, "gaussian_index", f"must be integer rows of the {n} Gaussians")
    pos = as_float_array(positions_t, src, "positions_t", (-1, 3))
    if pos.shape[0] < idx.size:
        raise InputError(src, "positions_t", f"has {pos.shape[0]} rows for {idx.size} Gaussian-associated particles")
    F = as_float_array(F_t, src, "F_t", (idx.size, 3, 3))
    means = np.asarray(gaussians.means, dtype=np.float64).copy()
    scales = np.asarray(gaussians.scales, dtype=np.float64).copy()
    quats = np.asarray(gaussians.quats, dtype=np.float64).copy()
    means[idx] = pos[: idx.size]
    cov0 = np.asarray(gaussians.covariances(), dtype=np.float64)[idx]
    scales[idx], quats[idx] = covariance_to_scale_rotation(deform_covariances(cov0, F))
    return GaussianSet(means, scales, quats, gaussians.opacities, gaussians.sh_dc, gaussians.sh_rest)


def render_rollout(gaussians, static_mask, gaussian_index, positions, F, camera, *, device: str = "cpu"):
    """Render every frame of a rollout as PhysGaussian does (:func:`knockgs_core.render.deformed_scene`):
    Gaussian-associated particles move the means of their Gaussians, covariances become
    F Sigma_0 F^T, static support Gaussians stay, fill particles are not rendered.

    ``static_mask`` [G] bool and ``gaussian_index`` [n_gs] (which must equal
    ``flatnonzero(~static_mask)``) come from the asset's scene file; ``positions`` (T, N, 3)
    (the first ``n_gs`` rows are GS particles), ``F`` (T, n_gs, 3, 3).
    Returns ``rgb`` (T, H, W, 3) and ``alpha`` (T, H, W), float32
    (:func:`knockgs_core.observe.render_rgbd` adds the depth).
    """
    outs = render_outputs(gaussians, static_mask, gaussian_index, positions, F, camera, device=device)
    return np.stack([o.rgb for o in outs]), np.stack([o.alpha for o in outs])


def render_outputs(gaussians, static_mask, gaussian_index, positions, F, camera, *, device: str = "cpu") -> list:
    """The :class:`knockgs_core.render.RenderOutput` of every frame of a rollout
    (:func:`render_rollout` says how the scene deforms)."""
    means0 = np.asarray(gaussians.means, dtype=np.float64)
    cov0 = np.asarray(gaussians.covariances(), dtype=np.float64)
    colors = np.asarray(gaussians.colors(), dtype=np.float64)
    opac = np.asarray(gaussians.opacities, dtype=np.float64)
    mask = np.asarray(static_mask)
    idx = np.asarray(gaussian_index)
    n_gs = len(idx)
    if mask.shape != (len(means0),) or not np.array_equal(idx, np.flatnonzero(~mask)):
        raise InputError("scene", "gaussian_index", "must list the rows where static_mask is False, in order")
    if F is None or F.shape[1] != n_gs:
        got = "no deformation gradients" if F is None else f"{F.shape[1]} deformation gradients"
        raise InputError("deformation", "F", f"{got} for {n_gs} Gaussian-associated particles")
    return render_frames(means0, cov0, colors, opac, mask, positions[:, :n_gs], F, camera, device=device)
