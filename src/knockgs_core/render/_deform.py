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
    return np.einsum("nij,njk,nlk->nil", F, cov0, F)


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
    mask = np.asarray(static_mask)
    if mask.dtype != bool or mask.shape != (n,):
        raise InputError(src, "static_mask", f"expected a bool array of shape [{n}], got "
                         f"{mask.dtype} {list(mask.shape)}")
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
    covs[dyn] = deform_covariances(cov0[dyn], F)
    return Scene(means, covs, colors, opacities)
