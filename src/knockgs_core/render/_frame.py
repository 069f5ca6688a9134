"""The device-resident frame path (private): from a scene in Warp arrays to the image, with the
projection, the tile bins and the rasterizer's inputs kept on the render device.

The kernels and the per-tile Gaussian order are those of ``_pipeline._bin_tiles_device`` (so the
pixels are those of :func:`~knockgs_core.render.render`): the visible Gaussians are compacted in
increasing index order by a prefix sum over their flags, sorted by depth with a stable radix
sort, and their (tile, Gaussian) pairs, emitted in that order, sorted stably by tile. Per frame
two things come back to the host: the pair count (4 bytes, to size the pair buffer) and the image.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from knockgs_core.errors import InputError

from . import _constants as C
from ._camera import Camera, RenderOutput, TileBins
from ._kernels import (
    compact_visible_kernel,
    pair_total_kernel,
    project_kernel,
    rasterize_kernel,
    tile_count_kernel,
    tile_emit_kernel,
    tile_ranges_kernel,
    visible_flags_kernel,
)

SENTINEL_CENTRE = -1.0e30
"""Image coordinates (u, v) [px] of the sentinel Gaussian (index N, radii 0): its box, one pixel
wide, misses every tile, so it has no tile pairs."""

PAIR_HEADROOM = 1.25
"""The pair buffer, when a frame outgrows it, is regrown to this many times that frame's pairs."""

_SRC = "render.DeviceFrames"


def resident_default(dev) -> bool:
    """Whether frames on the Warp device ``dev`` take the device-resident path by default: on
    CUDA. The CPU keeps the path of ``_pipeline._bin_and_rasterize`` (host binning)."""
    return bool(dev.is_cuda)


class DeviceFrames:
    """Reusable device buffers for the frames of one N-Gaussian scene (N > 0) seen by one camera.

    Allocated once (per motion) and reused by every :meth:`render`, all on the Warp device
    ``dev``: the projection ``means2d [N + 1]`` vec2f (u, v) [px], ``conics, covs2d [N + 1]``
    vec3f, ``depths [N + 1]`` float32 camera z, ``radii [N + 1]`` vec2f [px], where index N is
    a sentinel Gaussian (centre :data:`SENTINEL_CENTRE`, radii 0); the visibility ``flags,
    slots [N]`` int32; the depth sort's ``depth_keys [2 N]`` float32 and ``order [2 N]`` int32
    (second halves: the radix sort's scratch); ``counts, offsets [N]`` int32; the (tile,
    Gaussian) pairs ``pair_keys, pair_ids [2 capacity]`` int32, regrown when a frame has more
    pairs; ``tile_starts, tile_ends [tiles_y * tiles_x]`` int32; the image ``rgb [H, W]``
    vec3f and ``depth, alpha [H, W]`` float32, with page-locked host copies on CUDA.

    ``background [3]``: RGB in [0, 1]; ``tile_size`` [px]: the tile edge (default: the one
    ``render`` uses on ``dev`` for N Gaussians; the pixels do not depend on it).
    """

    def __init__(self, n: int, camera: Camera, background, dev, *, tile_size: int | None = None):
        if isinstance(n, bool) or int(n) != n or int(n) < 1:
            raise InputError(_SRC, "n", f"must be a positive Gaussian count, got {n!r}")
        if not isinstance(camera, Camera):
            raise InputError(_SRC, "camera", f"expected a Camera, got {type(camera).__name__}")
        self.n, self.dev, self.camera = int(n), dev, camera
        self.tile_size = C.tile_size_for(dev, self.n) if tile_size is None else int(tile_size)
        self.tiles_x = -(-camera.width // self.tile_size)
        self.tiles_y = -(-camera.height // self.tile_size)
        self.background = wp.vec3f(*np.asarray(background, dtype=np.float32))
        self._alloc_projection()
        self._alloc_bins()
        self._alloc_image()

    # -- allocation (once) ---------------------------------------------------------------
    def _alloc_projection(self) -> None:
        """Projection buffers [N + 1] with the sentinel Gaussian at index N."""
        n, dev = self.n, self.dev
        self.means2d = wp.zeros(n + 1, dtype=wp.vec2f, device=dev)
        self.conics = wp.zeros(n + 1, dtype=wp.vec3f, device=dev)
        self.covs2d = wp.zeros(n + 1, dtype=wp.vec3f, device=dev)
        self.depths = wp.zeros(n + 1, dtype=wp.float32, device=dev)
        self.radii = wp.zeros(n + 1, dtype=wp.vec2f, device=dev)  # radii[N] stays (0, 0)
        self.means2d[n:].fill_(wp.vec2f(SENTINEL_CENTRE, SENTINEL_CENTRE))

    def _alloc_bins(self) -> None:
        """Visibility, depth-sort and per-tile buffers; a first pair buffer of 2 N entries."""
        n, dev = self.n, self.dev
        self.flags = wp.empty(n, dtype=wp.int32, device=dev)
        self.slots = wp.empty(n, dtype=wp.int32, device=dev)
        self.depth_keys = wp.empty(2 * n, dtype=wp.float32, device=dev)
        self.order = wp.empty(2 * n, dtype=wp.int32, device=dev)
        self.counts = wp.empty(n, dtype=wp.int32, device=dev)
        self.offsets = wp.empty(n, dtype=wp.int32, device=dev)
        self.total = wp.zeros(1, dtype=wp.int32, device=dev)
        self.total_host = self._host_twin(self.total)
        self.pair_keys = self.pair_ids = None
        self._ensure_pairs(n)
        tiles = self.tiles_x * self.tiles_y
        self.tile_starts = wp.empty(tiles, dtype=wp.int32, device=dev)
        self.tile_ends = wp.empty(tiles, dtype=wp.int32, device=dev)
        self.pairs = 0

    def _alloc_image(self) -> None:
        """The image buffers [H, W] and their host copies."""
        shape, dev = (self.camera.height, self.camera.width), self.dev
        self.images = (wp.empty(shape, dtype=wp.vec3f, device=dev), wp.empty(shape, dtype=wp.float32, device=dev),
                       wp.empty(shape, dtype=wp.float32, device=dev))
        self.images_host = tuple(self._host_twin(a) for a in self.images)

    def _host_twin(self, a):
        """A host array for read-backs of the device array ``a``: ``a`` itself on the CPU, else a
        page-locked array of its shape and dtype."""
        return a if self.dev.is_cpu else wp.empty(a.shape, dtype=a.dtype, device="cpu", pinned=True)

    def _ensure_pairs(self, pairs: int) -> None:
        """Room for ``pairs`` (tile, Gaussian) pairs and the radix sort's scratch (2x)."""
        if self.pair_keys is not None and self.pair_keys.shape[0] >= 2 * pairs:
            return
        size = max(2 * int(PAIR_HEADROOM * pairs), 2 * pairs, 2)
        self.pair_keys = wp.empty(size, dtype=wp.int32, device=self.dev)
        self.pair_ids = wp.empty(size, dtype=wp.int32, device=self.dev)

    # -- one frame ------------------------------------------------------------------------
    def render(self, means, covariances, colors, opacities) -> RenderOutput:
        """The frame of a scene in float32 Warp arrays on the device, all [N]: ``means`` vec3f
        (world coordinates), symmetric ``covariances`` mat33f, ``colors`` vec3f RGB in [0, 1],
        ``opacities`` float32 in [0, 1]. Returns a :class:`RenderOutput` of new host arrays:
        ``rgb [H, W, 3]``, ``depth [H, W]``, ``alpha [H, W]``, float32."""
        for name, a in (("means", means), ("covariances", covariances), ("colors", colors), ("opacities", opacities)):
            if not isinstance(a, wp.array) or a.shape != (self.n,) or a.device != self.dev:
                raise InputError(_SRC, name, f"expected a Warp array [{self.n}] on {self.dev}")
        self._project(means, covariances, opacities)
        self._order_visible()
        self._bin(self._pair_count())
        self._rasterize(colors, opacities)
        return self._image()

    def _project(self, means, covariances, opacities) -> None:
        """``project_kernel`` into the projection buffers (rows 0..N-1)."""
        cam, f32 = self.camera, np.float32
        wp.launch(
            project_kernel,
            dim=self.n,
            inputs=[
                means, covariances, opacities,
                wp.mat33f(*cam.rotation.astype(f32).ravel()),
                wp.vec3f(*cam.translation.astype(f32)),
                cam.fx, cam.fy, cam.cx, cam.cy, *C.jacobian_limits(cam),
                C.NEAR_PLANE, C.LOW_PASS, C.ALPHA_MIN,
            ],
            outputs=[self.means2d, self.conics, self.covs2d, self.depths, self.radii],
            device=self.dev,
        )

    def _order_visible(self) -> None:
        """``order[:N]``: the visible Gaussians by depth, ties in increasing index (a stable
        sort of the compacted list), then the sentinel N in every remaining slot."""
        n, dev = self.n, self.dev
        wp.launch(visible_flags_kernel, dim=n, inputs=[self.radii], outputs=[self.flags], device=dev)
        wp.utils.array_scan(self.flags, self.slots, inclusive=False)
        wp.launch(compact_visible_kernel, dim=n, inputs=[self.flags, self.slots, self.depths, n],
                  outputs=[self.depth_keys, self.order], device=dev)
        wp.utils.radix_sort_pairs(self.depth_keys, self.order, n)

    def _pair_count(self) -> int:
        """Tile pairs per Gaussian (``counts``, in depth order), their exclusive offsets, and
        their total, read back: the frame's one host synchronization before the image."""
        n, dev = self.n, self.dev
        wp.launch(tile_count_kernel, dim=n, inputs=[self.order, self.means2d, self.radii, self.tile_size,
                                                   self.tiles_x, self.tiles_y], outputs=[self.counts], device=dev)
        wp.utils.array_scan(self.counts, self.offsets, inclusive=False)
        wp.launch(pair_total_kernel, dim=1, inputs=[self.counts, self.offsets], outputs=[self.total], device=dev)
        return int(self._read(((self.total, self.total_host),))[0][0])

    def _bin(self, pairs: int) -> None:
        """The ``pairs`` (tile, Gaussian) pairs emitted in depth order, sorted stably by tile,
        and each tile's ``[start, end)``."""
        dev = self.dev
        self._ensure_pairs(pairs)
        self.pairs = pairs
        wp.launch(tile_emit_kernel, dim=self.n, inputs=[self.order, self.means2d, self.radii, self.offsets,
                                                       self.tile_size, self.tiles_x, self.tiles_y],
                  outputs=[self.pair_keys, self.pair_ids], device=dev)
        tiles = self.tiles_x * self.tiles_y
        if pairs > 1:
            wp.utils.radix_sort_pairs(self.pair_keys, self.pair_ids, pairs, end_bit=max(1, int(tiles).bit_length()))
        wp.launch(tile_ranges_kernel, dim=tiles, inputs=[self.pair_keys, pairs],
                  outputs=[self.tile_starts, self.tile_ends], device=dev)

    def _rasterize(self, colors, opacities) -> None:
        """``rasterize_kernel`` over the image from the device-resident projection and bins."""
        wp.launch(
            rasterize_kernel,
            dim=(self.camera.height, self.camera.width),
            inputs=[
                self.means2d, self.conics, colors, opacities, self.depths,
                self.pair_ids, self.tile_starts, self.tile_ends, self.tiles_x, self.tile_size,
                self.background, C.ALPHA_MIN, C.ALPHA_MAX, C.TRANSMITTANCE_MIN,
            ],
            outputs=list(self.images),
            device=self.dev,
        )

    def _image(self) -> RenderOutput:
        """The image, copied to new host arrays."""
        rgb, depth, alpha = self._read(zip(self.images, self.images_host))
        return RenderOutput(rgb=rgb.copy(), depth=depth.copy(), alpha=alpha.copy())

    def _read(self, pairs) -> list:
        """NumPy views of the host twins after copying each ``(device, host)`` pair, with one
        synchronization (none on the CPU, where they are the same arrays)."""
        views = []
        for src, dst in pairs:
            if dst is not src:
                wp.copy(dst, src)
            views.append(dst)
        if not self.dev.is_cpu:
            wp.synchronize_device(self.dev)
        return [v.numpy() for v in views]

    def tile_bins(self):
        """The last frame's bins as a host :class:`~knockgs_core.render.TileBins` (for tests and
        comparisons): the pair's Gaussian ids [M] and each tile's ``[start, end)``."""
        ids, starts, ends = (a.numpy().copy() for a in (self.pair_ids, self.tile_starts, self.tile_ends))
        return TileBins(gaussian_ids=ids[: self.pairs], tile_ranges=np.stack([starts, ends], axis=1),
                        width=self.camera.width, height=self.camera.height, tile_size=self.tile_size)
