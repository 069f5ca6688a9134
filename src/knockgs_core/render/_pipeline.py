"""The Warp rasterizer: ``project`` -> ``bin_tiles`` -> ``rasterize``, and ``render``."""

from __future__ import annotations

import numpy as np
import warp as wp

from knockgs_core._warp import warp_device
from knockgs_core.errors import InputError

from . import _constants as C
from ._camera import Camera, Projection, RenderOutput, TileBins
from ._checks import as_float_array, check_background, check_count, check_range, check_scene
from ._frame import DeviceFrames, resident_default
from ._kernels import project_kernel, rasterize_kernel, tile_count_kernel, tile_emit_kernel, tile_ranges_kernel


def _device(device):
    """The Warp device (Warp started quietly by :func:`knockgs_core._warp.warp_device`)."""
    return warp_device(device)


def project(means, covariances, opacities, camera: Camera, *, device: str = "cpu") -> Projection:
    """Project 3D Gaussians to the image plane (EWA splatting, as in 3DGS).

    Parameters
    ----------
    means: [N, 3]
        Gaussian centres in world coordinates.
    covariances: [N, 3, 3]
        World-space covariances ``Sigma``.
    opacities: [N]
        Opacities in [0, 1]; they set the screen-space extent used for tile binning.
    camera:
        The :class:`Camera`.
    device:
        Warp device, e.g. ``"cpu"`` or ``"cuda:0"``.

    Returns
    -------
    Projection
        With ``Sigma_2D = J W Sigma W^T J^T + 0.3 I`` (``W`` the camera rotation, ``J``
        the perspective Jacobian at the view direction clamped to 1.3x the half field
        of view) and culling of ``z <= 0.01``.
    """
    src = "render.project"
    means = as_float_array(means, src, "means", (-1, 3))
    n = means.shape[0]
    covariances = as_float_array(covariances, src, "covariances", (-1, 3, 3))
    check_count(covariances, n, src, "covariances", "means")
    covariances = 0.5 * (covariances + np.swapaxes(covariances, 1, 2))
    opacities = as_float_array(opacities, src, "opacities", (-1,))
    check_count(opacities, n, src, "opacities", "means")
    check_range(opacities, 0.0, 1.0, src, "opacities")
    if not isinstance(camera, Camera):
        raise InputError(src, "camera", f"expected a Camera, got {type(camera).__name__}")
    return _project(means, covariances, opacities, camera, _device(device))


def _project(means: np.ndarray, covariances: np.ndarray, opacities: np.ndarray, camera: Camera, dev) -> Projection:
    """:func:`project` of checked float arrays (``means [N, 3]``, symmetric ``covariances
    [N, 3, 3]``, ``opacities [N]``) on the Warp device ``dev``."""
    n = means.shape[0]
    if n == 0:
        z2, z3 = np.zeros((0, 2), np.float32), np.zeros((0, 3), np.float32)
        return Projection(z2, z3, z3.copy(), np.zeros(0, np.float32), z2.copy())

    f32 = np.float32
    w_means = wp.array(means.astype(f32), dtype=wp.vec3f, device=dev)
    w_covs = wp.array(covariances.astype(f32), dtype=wp.mat33f, device=dev)
    w_opac = wp.array(opacities.astype(f32), dtype=wp.float32, device=dev)
    return _project_arrays(w_means, w_covs, w_opac, camera, dev)


def _project_arrays(w_means, w_covs, w_opac, camera: Camera, dev) -> Projection:
    """:func:`_project` of a scene already in Warp arrays on ``dev`` (N > 0): ``w_means [N]``
    vec3f, symmetric ``w_covs [N]`` mat33f, ``w_opac [N]`` float32."""
    f32 = np.float32
    n = w_means.shape[0]
    means2d = wp.zeros(n, dtype=wp.vec2f, device=dev)
    conics = wp.zeros(n, dtype=wp.vec3f, device=dev)
    covs2d = wp.zeros(n, dtype=wp.vec3f, device=dev)
    depths = wp.zeros(n, dtype=wp.float32, device=dev)
    radii = wp.zeros(n, dtype=wp.vec2f, device=dev)
    lims = C.jacobian_limits(camera)
    wp.launch(
        project_kernel,
        dim=n,
        inputs=[
            w_means, w_covs, w_opac,
            wp.mat33f(*camera.rotation.astype(f32).ravel()),
            wp.vec3f(*camera.translation.astype(f32)),
            camera.fx, camera.fy, camera.cx, camera.cy, *lims,
            C.NEAR_PLANE, C.LOW_PASS, C.ALPHA_MIN,
        ],
        outputs=[means2d, conics, covs2d, depths, radii],
        device=dev,
    )
    return Projection(
        means2d=means2d.numpy(),
        conics=conics.numpy(),
        covs2d=covs2d.numpy(),
        depths=depths.numpy(),
        radii=radii.numpy(),
    )


def bin_tiles(
    projection: Projection, width: int, height: int, *, tile_size: int = C.TILE_SIZE, device: str | None = None
) -> TileBins:
    """Assign visible Gaussians to the ``tile_size`` x ``tile_size`` tiles they overlap.

    A Gaussian goes to every tile that holds a pixel centre inside its box
    ``means2d +- radii`` (widened by half a pixel against rounding). Each tile's list
    is sorted by depth, ties by Gaussian index: a stable host sort on (tile, depth)
    when ``device`` is None, else on that Warp device (a stable radix sort by depth,
    then by tile: the same lists, without the host sort that dominates GPU frames).
    """
    src = "render.bin_tiles"
    for name, v in (("width", width), ("height", height), ("tile_size", tile_size)):
        if isinstance(v, bool) or int(v) != v or int(v) < 1:
            raise InputError(src, name, f"must be a positive integer, got {v!r}")
    width, height, tile_size = int(width), int(height), int(tile_size)
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    n_tiles = tiles_x * tiles_y

    ids = np.flatnonzero(projection.visible)
    if device is not None:
        return _bin_tiles_device(projection, ids, width, height, tile_size, _device(device))
    m = projection.means2d[ids].astype(np.float64)
    r = projection.radii[ids].astype(np.float64) + 0.5
    # Pixel centres c = i + 0.5 inside [m - r, m + r] have i in [m - r - 0.5, m + r - 0.5].
    lo = np.floor((m - r - 0.5) / tile_size)
    hi = np.floor((m + r - 0.5) / tile_size)
    lim = np.array([tiles_x - 1, tiles_y - 1], dtype=np.float64)
    lo = np.clip(lo, 0, lim + 1).astype(np.int64)  # clip in float: boxes may be huge
    hi = np.clip(hi, -1, lim).astype(np.int64)
    span = np.maximum(hi - lo + 1, 0)  # 0 where the box misses the image
    counts = span[:, 0] * span[:, 1]
    total = int(counts.sum())
    owner = np.repeat(np.arange(ids.size), counts)
    local = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    tx = lo[owner, 0] + local % span[owner, 0]
    ty = lo[owner, 1] + local // span[owner, 0]
    tile = ty * tiles_x + tx
    depth = projection.depths[ids][owner]
    order = np.lexsort((depth, tile))  # stable: ties keep increasing Gaussian index
    tile = tile[order]
    gaussian_ids = ids[owner[order]].astype(np.int32)
    starts = np.searchsorted(tile, np.arange(n_tiles), side="left")
    ends = np.searchsorted(tile, np.arange(n_tiles), side="right")
    tile_ranges = np.stack([starts, ends], axis=1).astype(np.int32)
    return TileBins(gaussian_ids=gaussian_ids, tile_ranges=tile_ranges,
                    width=width, height=height, tile_size=tile_size)


def _bin_tiles_device(projection: Projection, ids: np.ndarray, width: int, height: int, tile_size: int, dev) -> TileBins:
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    n_tiles = tiles_x * tiles_y
    n = int(ids.size)
    if n == 0:
        return TileBins(np.zeros(0, np.int32), np.zeros((n_tiles, 2), np.int32), width, height, tile_size)
    # 1. visible Gaussians by depth (stable: ties keep increasing index)
    depth = wp.array(np.concatenate([projection.depths[ids], np.zeros(n)]).astype(np.float32), dtype=wp.float32, device=dev)
    order = wp.array(np.concatenate([ids, np.zeros(n, ids.dtype)]).astype(np.int32), dtype=wp.int32, device=dev)
    wp.utils.radix_sort_pairs(depth, order, n)
    means2d = wp.array(np.ascontiguousarray(projection.means2d, dtype=np.float32), dtype=wp.vec2f, device=dev)
    radii = wp.array(np.ascontiguousarray(projection.radii, dtype=np.float32), dtype=wp.vec2f, device=dev)
    # 2. pairs per Gaussian, offsets, emitted in depth order
    counts = wp.zeros(n, dtype=wp.int32, device=dev)
    wp.launch(tile_count_kernel, dim=n, inputs=[order, means2d, radii, tile_size, tiles_x, tiles_y], outputs=[counts], device=dev)
    offsets = wp.zeros(n, dtype=wp.int32, device=dev)
    wp.utils.array_scan(counts, offsets, inclusive=False)
    total = int(offsets[n - 1 : n].numpy()[0] + counts[n - 1 : n].numpy()[0])
    keys = wp.zeros(max(2 * total, 2), dtype=wp.int32, device=dev)
    gids = wp.zeros(max(2 * total, 2), dtype=wp.int32, device=dev)
    wp.launch(tile_emit_kernel, dim=n, inputs=[order, means2d, radii, offsets, tile_size, tiles_x, tiles_y],
              outputs=[keys, gids], device=dev)
    # 3. stable sort by tile keeps the depth order inside each tile
    if total > 1:
        wp.utils.radix_sort_pairs(keys, gids, total, end_bit=max(1, int(n_tiles).bit_length()))
    starts = wp.zeros(n_tiles, dtype=wp.int32, device=dev)
    ends = wp.zeros(n_tiles, dtype=wp.int32, device=dev)
    wp.launch(tile_ranges_kernel, dim=n_tiles, inputs=[keys, total], outputs=[starts, ends], device=dev)
    ranges = np.stack([starts.numpy(), ends.numpy()], axis=1).astype(np.int32)
    return TileBins(gaussian_ids=gids.numpy()[:total].copy(), tile_ranges=ranges, width=width, height=height, tile_size=tile_size)


def rasterize(
    projection: Projection,
    colors,
    opacities,
    bins: TileBins,
    *,
    background=(1.0, 1.0, 1.0),
    device: str = "cpu",
) -> RenderOutput:
    """Composite the binned Gaussians front to back, one Warp thread per pixel.

    Parameters
    ----------
    projection:
        From :func:`project`.
    colors: [N, 3]
        RGB in [0, 1] (DC colour).
    opacities: [N]
        In [0, 1].
    bins:
        From :func:`bin_tiles`; sets the image size.
    background: [3]
        RGB in [0, 1], added with the final transmittance.

    Per pixel, in each tile's depth order: ``alpha = min(0.99, o exp(-0.5 d^T
    Sigma_2D^-1 d))``; Gaussians with ``alpha < 1/255`` are skipped; compositing stops
    before a Gaussian that would take the transmittance ``T`` below 1e-4 (that Gaussian
    is not added), as in 3DGS.
    """
    src = "render.rasterize"
    n = projection.means2d.shape[0]
    colors = as_float_array(colors, src, "colors", (-1, 3))
    check_count(colors, n, src, "colors", "projection.means2d")
    check_range(colors, 0.0, 1.0, src, "colors")
    opacities = as_float_array(opacities, src, "opacities", (-1,))
    check_count(opacities, n, src, "opacities", "projection.means2d")
    check_range(opacities, 0.0, 1.0, src, "opacities")
    bg = check_background(background, src)
    if bins.tile_ranges.shape != (bins.tiles_x * bins.tiles_y, 2):
        raise InputError(src, "bins.tile_ranges", "does not match the bins' image size")
    if bins.gaussian_ids.size and int(bins.gaussian_ids.max()) >= n:
        raise InputError(src, "bins.gaussian_ids", f"refers to Gaussians beyond the {n} projected")
    return _rasterize(projection, colors, opacities, bins, bg, _device(device))


def _rasterize(projection: Projection, colors: np.ndarray, opacities: np.ndarray, bins: TileBins, bg: np.ndarray,
               dev) -> RenderOutput:
    """:func:`rasterize` of checked inputs (``bg`` the background [3]) on the Warp device ``dev``;
    ``colors`` and ``opacities`` may be float32 Warp arrays on ``dev`` already (vec3f, float32)."""
    h, w = bins.height, bins.width
    f32 = np.float32

    def arr(a, dtype):
        if isinstance(a, wp.array):  # already on the device (render_frames' scene buffers)
            return a
        a = np.ascontiguousarray(a)
        if a.shape[0] == 0:  # Warp needs a valid (non-null) array; pad with one unused entry
            a = np.zeros((1,) + a.shape[1:], dtype=a.dtype)
        return wp.array(a, dtype=dtype, device=dev)

    out_rgb = wp.zeros((h, w), dtype=wp.vec3f, device=dev)
    out_depth = wp.zeros((h, w), dtype=wp.float32, device=dev)
    out_alpha = wp.zeros((h, w), dtype=wp.float32, device=dev)
    wp.launch(
        rasterize_kernel,
        dim=(h, w),
        inputs=[
            arr(projection.means2d.astype(f32), wp.vec2f),
            arr(projection.conics.astype(f32), wp.vec3f),
            arr(_as_f32(colors), wp.vec3f),
            arr(_as_f32(opacities), wp.float32),
            arr(projection.depths.astype(f32), wp.float32),
            arr(bins.gaussian_ids.astype(np.int32), wp.int32),
            arr(bins.tile_ranges[:, 0].astype(np.int32), wp.int32),
            arr(bins.tile_ranges[:, 1].astype(np.int32), wp.int32),
            bins.tiles_x,
            bins.tile_size,
            wp.vec3f(*bg.astype(f32)),
            C.ALPHA_MIN,
            C.ALPHA_MAX,
            C.TRANSMITTANCE_MIN,
        ],
        outputs=[out_rgb, out_depth, out_alpha],
        device=dev,
    )
    return RenderOutput(rgb=out_rgb.numpy(), depth=out_depth.numpy(), alpha=out_alpha.numpy())


def render(
    means,
    covariances,
    colors,
    opacities,
    camera: Camera,
    *,
    background=(1.0, 1.0, 1.0),
    device: str = "cpu",
) -> RenderOutput:
    """Render 3D Gaussians with ``camera``: :func:`project`, :func:`bin_tiles`, :func:`rasterize`.

    Parameters
    ----------
    means: [N, 3]
        Centres (world coordinates).
    covariances: [N, 3, 3]
        World-space covariances (symmetrized on input).
    colors: [N, 3]
        RGB in [0, 1].
    opacities: [N]
        In [0, 1].
    camera:
        The :class:`Camera`; sets the image size H x W.
    background: [3]
        RGB in [0, 1].
    device:
        Warp device (``"cpu"`` by default, ``"cuda:0"`` on a GPU).

    Returns
    -------
    RenderOutput
        ``rgb [H, W, 3]``, ``depth [H, W]`` (alpha-weighted, not normalized),
        ``alpha [H, W]``, all float32.
    """
    src = "render.render"
    means, covariances, colors, opacities = check_scene(means, covariances, colors, opacities, src)
    if not isinstance(camera, Camera):
        raise InputError(src, "camera", f"expected a Camera, got {type(camera).__name__}")
    bg = check_background(background, src)
    return _render(means, 0.5 * (covariances + np.swapaxes(covariances, 1, 2)), colors, opacities, camera, bg, device)


def _render(means: np.ndarray, covariances: np.ndarray, colors: np.ndarray, opacities: np.ndarray, camera: Camera,
            bg: np.ndarray, device: str) -> RenderOutput:
    """:func:`render` of checked float arrays (``covariances`` symmetric, ``bg`` the background
    [3]); :func:`render_frames` keeps its scene on the device instead (:func:`_render_arrays`).
    On CUDA the frame takes the device-resident path (``_frame.DeviceFrames``: the same pixels)."""
    dev = _device(device)
    if resident_default(dev) and means.shape[0] > 0:
        f32 = np.float32
        scene = (wp.array(means.astype(f32), dtype=wp.vec3f, device=dev),
                 wp.array(covariances.astype(f32), dtype=wp.mat33f, device=dev),
                 wp.array(colors.astype(f32), dtype=wp.vec3f, device=dev),
                 wp.array(opacities.astype(f32), dtype=wp.float32, device=dev))
        return DeviceFrames(means.shape[0], camera, bg, dev).render(*scene)
    proj = _project(means, covariances, opacities, camera, dev)
    return _bin_and_rasterize(proj, colors, opacities, camera, bg, dev)


def _render_arrays(means, covariances, colors, opacities, camera: Camera, bg: np.ndarray, dev) -> RenderOutput:
    """:func:`_render` of a scene already in float32 Warp arrays on ``dev`` (N > 0): ``means
    [N]`` vec3f, symmetric ``covariances [N]`` mat33f, ``colors [N]`` vec3f, ``opacities [N]``
    float32, through the host-side projection and binning (:func:`_bin_and_rasterize`): the
    path of :func:`render_frames` on the CPU; CUDA renders with ``_frame.DeviceFrames``."""
    proj = _project_arrays(means, covariances, opacities, camera, dev)
    return _bin_and_rasterize(proj, colors, opacities, camera, bg, dev)


def _bin_and_rasterize(proj: Projection, colors, opacities, camera: Camera, bg: np.ndarray, dev) -> RenderOutput:
    """:func:`bin_tiles` and :func:`_rasterize` of a projected scene on the Warp device ``dev``."""
    # CUDA bins on the device; on the CPU the host sort is as fast and Warp runs one thread
    bins = bin_tiles(proj, camera.width, camera.height, tile_size=C.tile_size_for(dev, proj.depths.shape[0]),
                     device=None if dev.is_cpu else dev.alias)
    return _rasterize(proj, colors, opacities, bins, bg, dev)


def _as_f32(a):
    """A host array as float32; a Warp array (already float32 on the device) as it is."""
    return a if isinstance(a, wp.array) else a.astype(np.float32)
