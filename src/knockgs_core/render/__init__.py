"""Gaussian-splat rendering on CPU or CUDA (NVIDIA Warp), after 3DGS / gsplat.

Layers: :func:`project` (EWA projection) -> :func:`bin_tiles` (square tiles, 16 px on CUDA and 4 px on
the CPU; depth order) -> :func:`rasterize` (front-to-back compositing, one Warp thread per pixel);
:func:`render` chains them. :func:`render_reference` is a slow NumPy reference of the
same rule, for tests. :func:`deform_covariances` / :func:`deformed_scene` move
Gaussians with simulated particles (PhysGaussian: ``Sigma_t = F Sigma_0 F^T``); :func:`render_frames` renders
every frame of such a motion, checking the rest scene once; :func:`render_rollout` / :func:`render_outputs` render
every frame of a rollout of an asset (its Gaussians, its scene's static mask, the simulated particles);
:func:`deformed_gaussians` gives one frame as a ``GaussianSet`` for a standard 3DGS PLY.

Conventions: OpenCV camera (x right, y down, z forward); pixel ``(row, col)`` has its
centre at ``(u, v) = (col + 0.5, row + 0.5)``; colours are RGB in [0, 1].
"""

from ._camera import Camera, Projection, RenderOutput, TileBins, camera_from_contract
from ._constants import TILE_SIZE
from ._deform import (Scene, covariance_to_scale_rotation, deform_covariances, deformed_gaussians, deformed_scene, render_frames,
                      render_outputs, render_rollout)
from ._reference import render_reference


def __getattr__(name):
    # the Warp pipeline is imported on first use: reading frames, cameras or the reference does
    # not pay Warp's start-up
    if name in ("bin_tiles", "project", "rasterize", "render"):
        from . import _pipeline

        value = getattr(_pipeline, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | {"bin_tiles", "project", "rasterize", "render"})

__all__ = [
    "Camera",
    "RenderOutput",
    "Projection",
    "TileBins",
    "Scene",
    "TILE_SIZE",
    "project",
    "bin_tiles",
    "rasterize",
    "render",
    "render_reference",
    "deform_covariances",
    "render_frames",
    "render_rollout",
    "camera_from_contract",
    "render_outputs",
    "deformed_scene",
    "deformed_gaussians",
    "covariance_to_scale_rotation",
]
