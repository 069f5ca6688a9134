"""Pinhole camera (OpenCV convention) and the containers of the pipeline's stages and output:
:class:`Projection`, :class:`TileBins`, :class:`RenderOutput` (private)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from knockgs_core.errors import InputError

from ._checks import as_float_array


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera in the OpenCV convention: x right, y down, z forward.

    Parameters
    ----------
    width, height:
        Image size in pixels.
    fx, fy:
        Focal lengths in pixels.
    cx, cy:
        Principal point in pixels. Pixel ``(row, col)`` has its centre at image
        coordinates ``(u, v) = (col + 0.5, row + 0.5)`` (as in gsplat), so a centred
        camera has ``cx = width / 2``, ``cy = height / 2``.
    world_to_camera:
        ``[4, 4]`` rigid transform taking world points to camera coordinates
        (``x_cam = R @ x_world + t``); stored as a read-only float64 array.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_to_camera: np.ndarray

    def __post_init__(self):
        src = "Camera"
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or int(v) < 1:
                raise InputError(src, name, f"must be a positive integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        for name in ("fx", "fy", "cx", "cy"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise InputError(src, name, f"must be finite, got {v!r}")
            object.__setattr__(self, name, v)
        for name in ("fx", "fy"):
            if getattr(self, name) <= 0:
                raise InputError(src, name, f"must be > 0, got {getattr(self, name)!r}")
        m = as_float_array(self.world_to_camera, src, "world_to_camera", (4, 4)).copy()
        if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0]):
            raise InputError(src, "world_to_camera", f"last row must be [0, 0, 0, 1], got {m[3]}")
        m.setflags(write=False)
        object.__setattr__(self, "world_to_camera", m)

    def __eq__(self, other):
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            (self.width, self.height, self.fx, self.fy, self.cx, self.cy)
            == (other.width, other.height, other.fx, other.fy, other.cx, other.cy)
            and np.array_equal(self.world_to_camera, other.world_to_camera)
        )

    def __hash__(self):
        return hash((self.width, self.height, self.fx, self.fy, self.cx, self.cy,
                     self.world_to_camera.tobytes()))

    @property
    def rotation(self) -> np.ndarray:
        """World-to-camera rotation ``R``, shape [3, 3]."""
        return self.world_to_camera[:3, :3]

    @property
    def translation(self) -> np.ndarray:
        """World-to-camera translation ``t``, shape [3]."""
        return self.world_to_camera[:3, 3]

    @classmethod
    def look_at(cls, eye, target, up, *, fov_deg: float, width: int, height: int) -> "Camera":
        """A centred camera at ``eye`` looking at ``target``.

        ``eye``, ``target``, ``up``: [3] world points / direction. ``fov_deg`` is the
        *vertical* field of view in degrees; pixels are square (``fx = fy``) and the
        principal point is the image centre. Image "up" follows the projection of
        ``up`` (camera y points along ``-up``).
        """
        src = "Camera.look_at"
        eye = as_float_array(eye, src, "eye", (3,))
        target = as_float_array(target, src, "target", (3,))
        up = as_float_array(up, src, "up", (3,))
        if not (0.0 < float(fov_deg) < 180.0):
            raise InputError(src, "fov_deg", f"must lie in (0, 180), got {fov_deg!r}")
        forward = target - eye
        if np.linalg.norm(forward) == 0.0:
            raise InputError(src, "target", "coincides with eye")
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, up)
        if np.linalg.norm(right) < 1e-9 * max(np.linalg.norm(up), 1e-300):
            raise InputError(src, "up", "is zero or parallel to the viewing direction")
        right = right / np.linalg.norm(right)
        down = np.cross(forward, right)
        m = np.eye(4)
        m[:3, :3] = np.stack([right, down, forward])
        m[:3, 3] = -m[:3, :3] @ eye
        f = 0.5 * height / math.tan(math.radians(float(fov_deg)) / 2.0)
        return cls(width=width, height=height, fx=f, fy=f, cx=width / 2.0, cy=height / 2.0,
                   world_to_camera=m)


@dataclass(frozen=True, eq=False)
class RenderOutput:
    """A rendered frame.

    ``rgb``: [H, W, 3] float32, composited over the background.
    ``depth``: [H, W] float32, alpha-weighted camera depth ``sum_i w_i z_i`` with
    compositing weights ``w_i = alpha_i T_i`` -- *not* normalized by the pixel alpha
    (divide by ``alpha`` for the expected depth of the covered part); 0 where empty.
    ``alpha``: [H, W] float32, accumulated opacity ``1 - T_final``.
    """

    rgb: np.ndarray
    depth: np.ndarray
    alpha: np.ndarray


@dataclass(frozen=True, eq=False)
class Projection:
    """Per-Gaussian screen-space quantities (host arrays, N = number of Gaussians).

    ``means2d: [N, 2]`` image coordinates (u, v) [px]; ``conics: [N, 3]`` the upper
    triangle (a, b, c) of the inverse 2D covariance; ``covs2d: [N, 3]`` the upper
    triangle of the 2D covariance including the 0.3 px^2 low-pass term;
    ``depths: [N]`` camera z; ``radii: [N, 2]`` half-extents [px] of the box outside
    which the Gaussian's alpha is below 1/255, ``(0, 0)`` when the Gaussian is culled
    (behind the near plane, degenerate, or opacity below 1/255). Entries of culled
    Gaussians other than ``depths`` and ``radii`` are unspecified.
    """

    means2d: np.ndarray
    conics: np.ndarray
    covs2d: np.ndarray
    depths: np.ndarray
    radii: np.ndarray

    @property
    def visible(self) -> np.ndarray:
        """``[N]`` bool: not culled."""
        return np.all(self.radii > 0, axis=1)


@dataclass(frozen=True, eq=False)
class TileBins:
    """Gaussian lists per tile, each sorted front to back.

    ``gaussian_ids: [M]`` int32 Gaussian indices of all (tile, Gaussian) pairs, sorted
    by tile, then depth, then index; ``tile_ranges: [tiles_y * tiles_x, 2]`` int32
    ``[start, end)`` into ``gaussian_ids`` per tile (row-major tile order).
    """

    gaussian_ids: np.ndarray
    tile_ranges: np.ndarray
    width: int
    height: int
    tile_size: int

    @property
    def tiles_x(self) -> int:
        return -(-self.width // self.tile_size)

    @property
    def tiles_y(self) -> int:
        return -(-self.height // self.tile_size)


def camera_from_contract(camera, *, width: int | None = None, height: int | None = None) -> Camera:
    """The contract's look-at camera (its ``camera`` mapping: eye, target, up, fov_deg, width,
    height), optionally at another image size (same field of view)."""
    return Camera.look_at(camera["eye"], camera["target"], camera["up"], fov_deg=camera["fov_deg"],
                          width=int(width or camera["width"]), height=int(height or camera["height"]))
