"""The scene file of a built asset: which rendered Gaussians the particles move (private).

``<object>.scene.npz`` sits next to the asset's normalized PLY (``<object>.ply``) and holds
``static_mask`` ([len(gaussians)] bool, support Gaussians rendered but not simulated) and
``gaussian_index`` ([n_gs] int64, the Gaussian row of each Gaussian-associated particle,
``flatnonzero(~static_mask)``). With the PLY and a rollout it is all a renderer needs.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from knockgs_core.io import write_npz
from knockgs_core.errors import InputError

__all__ = ["scene_path", "save_scene", "load_scene"]


def scene_path(ply_path: str | os.PathLike) -> Path:
    """The scene file that belongs to an asset PLY: ``NAME.ply`` -> ``NAME.scene.npz``."""
    ply = Path(ply_path)
    stem = ply.name[: -len(".ply")] if ply.name.endswith(".ply") else ply.name
    return ply.with_name(stem + ".scene.npz")


def save_scene(built, path: str | os.PathLike) -> None:
    """Write the scene file of a :class:`~knockgs_core.assets.BuiltAsset` (compressed, atomically)."""
    write_npz(path, static_mask=np.asarray(built.static_mask, dtype=bool),
              gaussian_index=np.asarray(built.particles.gaussian_index))


def load_scene(path: str | os.PathLike, *, n_gaussians: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(static_mask [G] bool, gaussian_index [n_gs] int64)`` of a scene file.

    ``n_gaussians``: the number of Gaussians of the PLY it is used with (checked when given).
    Raises :class:`~knockgs_core.errors.InputError` naming the file and the field when the
    file is missing or unreadable, a field is absent, or the two fields disagree.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputError(path, "file", "does not exist (written by `knockgs asset make --normalized` "
                         "next to the PLY, and by the workflow's asset rule)") from None
    except Exception as exc:
        raise InputError(path, "file", f"not a KnockGS scene file ({exc})") from None
    for key in ("static_mask", "gaussian_index"):
        if key not in data:
            raise InputError(path, key, "missing from the scene file")
    static_mask = np.asarray(data["static_mask"])
    gaussian_index = np.asarray(data["gaussian_index"])
    if static_mask.dtype != bool or static_mask.ndim != 1:
        raise InputError(path, "static_mask", f"expected a 1-D bool array, got {static_mask.dtype} {list(static_mask.shape)}")
    if n_gaussians is not None and static_mask.size != n_gaussians:
        raise InputError(path, "static_mask", f"{static_mask.size} entries for a PLY of {n_gaussians} Gaussians")
    if not np.issubdtype(gaussian_index.dtype, np.integer) or not np.array_equal(gaussian_index, np.flatnonzero(~static_mask)):
        raise InputError(path, "gaussian_index", "must list the rows where static_mask is False, in order")
    return static_mask, gaussian_index.astype(np.int64)
