"""Observations a camera gives: RGB-D frame sequences (rendered or captured), ID-free tracks
from optical flow lifted by depth, depth point sets, and which particles a camera sees.

:func:`render_rgbd` renders a rollout with depth; :func:`write_rgbd` / :func:`read_rgbd` store
it; :func:`track_points` turns a sequence into tracks (the ``knockgs observe`` command writes
them in the tracked-points format the discrepancy loop and the calibration read) and
:func:`tracking_error` estimates their error; :func:`surface_truth` and :func:`track_errors`
measure tracks of a rendered sequence against where the surface points they started on went;
:func:`depth_point_sets` and :func:`pointset_descriptor` give the descriptor of point sets
without correspondence; :func:`visible_particles` selects the particles seen in every frame.
"""

from ._rgbd import RGBDFrames, project, read_rgbd, render_rgbd, unproject, write_rgbd
from ._tracking import (
    PixelTracks,
    TrackSettings,
    depth_point_sets,
    pointset_descriptor,
    track_pixels,
    track_points,
    tracking_error,
    visible_particles,
)
from ._truth import TrackErrors, surface_truth, track_errors

__all__ = [
    "RGBDFrames",
    "render_rgbd",
    "write_rgbd",
    "read_rgbd",
    "project",
    "unproject",
    "TrackSettings",
    "PixelTracks",
    "track_pixels",
    "track_points",
    "tracking_error",
    "surface_truth",
    "TrackErrors",
    "track_errors",
    "depth_point_sets",
    "pointset_descriptor",
    "visible_particles",
]
