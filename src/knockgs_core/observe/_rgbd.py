"""RGB-D frame sequences: rendered from a rollout, stored, and read back (private).

A sequence is what a calibrated RGB-D camera gives: colour, coverage and depth per pixel,
the camera's intrinsics and pose, and the frame interval. No particle identity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..render import Camera, render_outputs

__all__ = ["RGBDFrames", "render_rgbd", "write_rgbd", "read_rgbd", "project", "unproject"]


@dataclass(frozen=True)
class RGBDFrames:
    """``rgb`` [T, H, W, 3] in [0, 1]; ``alpha`` [T, H, W] coverage in [0, 1]; ``depth``
    [T, H, W] the expected camera depth [m] of the covered part (0 where ``alpha`` is 0);
    ``camera`` the :class:`~knockgs_core.render.Camera` (same for every frame); ``frame_dt``
    [s] between frames; ``mask`` [H, W] bool, optional: the object's segmentation in frame 0
    (the pixels that show the object: a rendered sequence has it, where the object makes at
    least ``MASK_SHARE`` of the pixel's compositing weight, so not where a static support hides
    it, even partly; a capture may bring one).
    Arrays are float32."""

    rgb: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    camera: Camera
    frame_dt: float
    source: str = "frames"
    mask: np.ndarray | None = None

    def __post_init__(self):
        src = self.source
        rgb = np.asarray(self.rgb, dtype=np.float32)
        alpha = np.asarray(self.alpha, dtype=np.float32)
        depth = np.asarray(self.depth, dtype=np.float32)
        if rgb.ndim != 4 or rgb.shape[-1] != 3:
            raise InputError(src, "rgb", f"expected [T, H, W, 3], got {list(rgb.shape)}")
        T, H, W = rgb.shape[:3]
        for name, a in (("alpha", alpha), ("depth", depth)):
            if a.shape != (T, H, W):
                raise InputError(src, name, f"expected [{T}, {H}, {W}], got {list(a.shape)}")
            if not np.all(np.isfinite(a)):
                raise InputError(src, name, "non-finite values")
        if not np.all(np.isfinite(rgb)):
            raise InputError(src, "rgb", "non-finite values")
        if (H, W) != (self.camera.height, self.camera.width):
            raise InputError(src, "camera", f"image {W}x{H} but camera {self.camera.width}x{self.camera.height}")
        if T < 2:
            raise InputError(src, "frame", f"need at least 2 frames, got {T}")
        if not (math.isfinite(float(self.frame_dt)) and float(self.frame_dt) > 0):
            raise InputError(src, "frame_dt", f"must be a positive number of seconds, got {self.frame_dt!r}")
        if self.mask is not None:
            mask = np.asarray(self.mask)
            if mask.shape != (H, W):
                raise InputError(src, "mask", f"expected [{H}, {W}], got {list(mask.shape)}")
            object.__setattr__(self, "mask", mask.astype(bool))
        object.__setattr__(self, "rgb", rgb)
        object.__setattr__(self, "alpha", alpha)
        object.__setattr__(self, "depth", depth)
        object.__setattr__(self, "frame_dt", float(self.frame_dt))

    @property
    def n_frames(self) -> int:
        return self.rgb.shape[0]


def render_rgbd(gaussians, static_mask, gaussian_index, positions, F, camera: Camera, *, frame_dt: float,
                device: str = "cpu") -> RGBDFrames:
    """Render every frame of a rollout with depth (as
    :func:`knockgs_core.render.render_rollout`, which returns the same colour and
    coverage): ``positions`` (T, N, 3), ``F`` (T, n_gs, 3, 3)."""
    outs = render_outputs(gaussians, static_mask, gaussian_index, positions, F, camera, device=device)
    rgb = np.stack([o.rgb for o in outs])
    alpha = np.stack([o.alpha for o in outs])
    wdepth = np.stack([o.depth for o in outs])
    depth = np.where(alpha > 1e-6, wdepth / np.maximum(alpha, 1e-6), 0.0).astype(np.float32)
    return RGBDFrames(rgb=rgb, alpha=alpha, depth=depth, camera=camera, frame_dt=frame_dt, source="render",
                      mask=object_share(gaussians, static_mask, positions[0, : len(gaussian_index)], F[0], camera,
                                        device=device) >= MASK_SHARE)


#: a pixel belongs to the object's frame-0 segmentation where the object makes at least this
#: share of what the pixel shows (its compositing weight over the pixel's whole coverage)
MASK_SHARE = 0.95


def object_share(gaussians, static_mask, positions0, F0, camera: Camera, *, device: str = "cpu") -> np.ndarray:
    """[H, W] the object's share of each pixel's compositing weight at frame 0 (``positions0``
    [n_gs, 3], ``F0`` [n_gs, 3, 3]): 1 where only its Gaussians make the pixel, less where a
    static support in front of it (or seen through it) takes part, 0 where it is absent."""
    from ..render import deformed_scene, render  # Warp: imported where it runs

    mask = np.asarray(static_mask, dtype=bool)
    colors = np.where(mask[:, None], 0.0, 1.0) * np.ones((1, 3))
    scene = deformed_scene(np.asarray(gaussians.means, dtype=np.float64), np.asarray(gaussians.covariances(), dtype=np.float64),
                           colors, np.asarray(gaussians.opacities, dtype=np.float64), positions0, F0, mask)
    o = render(*scene, camera, background=(0.0, 0.0, 0.0), device=device)
    return np.where(o.alpha > 1e-6, o.rgb[..., 0] / np.maximum(o.alpha, 1e-6), 0.0)


def write_rgbd(path, frames: RGBDFrames) -> None:
    """Store a sequence as ``.npz`` (colour and coverage float16, depth float32, the camera's
    intrinsics and pose, the frame interval), atomically."""
    from ..io import write_npz

    c = frames.camera
    extra = {} if frames.mask is None else {"mask": frames.mask}
    write_npz(path, rgb=frames.rgb.astype(np.float16), alpha=frames.alpha.astype(np.float16), depth=frames.depth,
              intrinsics=np.array([c.width, c.height, c.fx, c.fy, c.cx, c.cy], dtype=np.float64),
              world_to_camera=np.asarray(c.world_to_camera, dtype=np.float64), frame_dt=np.float64(frames.frame_dt), **extra)


def read_rgbd(path) -> RGBDFrames:
    """Read a sequence written by :func:`write_rgbd` (or any ``.npz`` with the same fields:
    ``rgb`` [T, H, W, 3], ``alpha`` and ``depth`` [T, H, W], ``intrinsics`` [width, height, fx,
    fy, cx, cy], ``world_to_camera`` [4, 4], ``frame_dt``); errors name the file and field.

    Plausibility, not only syntax: the intrinsics finite, the image 1 .. 8192 pixels a side and
    the focal lengths > 0; ``world_to_camera`` a rigid transform (its rotation orthonormal with
    determinant +1); ``frame_dt`` one finite number of seconds > 0.
    """
    import zipfile

    from ..io import input_problem

    src = str(path)
    problem = input_problem(src)  # a FIFO would block np.load, a device never end it
    if problem is not None:
        raise InputError(src, "file", problem)
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(src, "file", f"not a readable .npz ({exc})") from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise InputError(src, "file", "a single .npy array, not an .npz archive of named arrays")
    with data:
        try:
            return _frames_of(src, data)
        except InputError:
            raise
        except (OSError, ValueError, TypeError, EOFError, zipfile.BadZipFile) as exc:  # a damaged member
            raise InputError(src, "file", f"not a readable .npz ({type(exc).__name__}: {exc})") from None


def _frames_of(src: str, data) -> RGBDFrames:
    for name in ("rgb", "alpha", "depth", "intrinsics", "world_to_camera", "frame_dt"):
        if name not in data.files:
            raise InputError(src, name, "missing")
    k = np.asarray(data["intrinsics"])
    if k.shape != (6,) or not np.issubdtype(k.dtype, np.number):
        raise InputError(src, "intrinsics", f"expected 6 numbers [width, height, fx, fy, cx, cy], got "
                         f"{k.dtype} of shape {list(k.shape)}")
    k = k.astype(np.float64)
    if not np.all(np.isfinite(k)):
        raise InputError(src, "intrinsics", f"non-finite values {k.tolist()}")
    if not all(float(v).is_integer() and 1 <= v <= 8192 for v in k[:2]):
        raise InputError(src, "intrinsics", f"width and height must be integers 1 .. 8192 pixels, got {k[:2].tolist()}")
    if not (k[2] > 0 and k[3] > 0):
        raise InputError(src, "intrinsics", f"focal lengths fx, fy must be > 0 pixels, got {k[2:4].tolist()}")
    m = np.asarray(data["world_to_camera"])
    if m.shape != (4, 4) or not np.issubdtype(m.dtype, np.number) or not np.all(np.isfinite(m)):
        raise InputError(src, "world_to_camera", f"expected a finite [4, 4] transform, got {m.dtype} of shape "
                         f"{list(m.shape)}")
    m = m.astype(np.float64)
    r = m[:3, :3]
    if not (np.allclose(r @ r.T, np.eye(3), atol=1e-5) and np.linalg.det(r) > 0):
        raise InputError(src, "world_to_camera", "its rotation part is not a rotation (orthonormal, determinant +1)")
    dt = np.asarray(data["frame_dt"])
    if dt.shape != () or not np.issubdtype(dt.dtype, np.number) or not (np.isfinite(dt) and dt > 0):
        raise InputError(src, "frame_dt", f"expected one finite number of seconds > 0, got {dt.tolist()!r}")
    try:
        cam = Camera(width=int(k[0]), height=int(k[1]), fx=k[2], fy=k[3], cx=k[4], cy=k[5], world_to_camera=m)
    except InputError as exc:  # named by the file, not by the Camera class
        raise InputError(src, "world_to_camera" if exc.field == "world_to_camera" else "intrinsics",
                         f"{exc.field}: {exc.message}") from None
    return RGBDFrames(rgb=data["rgb"], alpha=data["alpha"], depth=data["depth"], camera=cam,
                      frame_dt=float(dt), source=src, mask=data["mask"] if "mask" in data.files else None)


def project(camera: Camera, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points [..., 3] -> (row, col, z): pixel coordinates (pixel centres at integers)
    and camera depth [m]."""
    P = np.asarray(points, dtype=np.float64)
    M = np.asarray(camera.world_to_camera, dtype=np.float64)
    xc = P @ M[:3, :3].T + M[:3, 3]
    z = xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = camera.fx * xc[..., 0] / z + camera.cx
        v = camera.fy * xc[..., 1] / z + camera.cy
    return v - 0.5, u - 0.5, z


def unproject(camera: Camera, rows, cols, depth) -> np.ndarray:
    """Pixel coordinates (pixel centres at integers) and camera depth [m] -> world points
    [..., 3]; the inverse of :func:`project`."""
    rows, cols, z = (np.asarray(a, dtype=np.float64) for a in (rows, cols, depth))
    x = (cols + 0.5 - camera.cx) / camera.fx * z
    y = (rows + 0.5 - camera.cy) / camera.fy * z
    xc = np.stack([x, y, z], axis=-1)
    M = np.asarray(camera.world_to_camera, dtype=np.float64)
    return (xc - M[:3, 3]) @ M[:3, :3]
