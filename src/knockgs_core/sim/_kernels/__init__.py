"""Warp kernels of the MLS-MPM solver (quadratic B-splines, fixed-corotated elasticity) with an
APIC or an affine-FLIP particle-grid transfer.

One thread per particle or per grid node; inputs before outputs. The same kernels run on
the CPU and on CUDA. Grid kernels run over the *active box* only (the grid region that the
particles' stencils can reach), given as an offset ``lo`` and the launch dimensions.

Conventions: ``n_grid`` nodes per axis at positions ``i * dx``; a particle at ``x`` scatters
to the 3x3x3 nodes starting at ``base = int(x / dx - 0.5)``.

Transfers (``affine_flip`` flag of :func:`p2g`, :func:`grid_zero`, :func:`grid_update`,
:func:`g2p`): APIC (Jiang et al. 2015) replaces a particle's velocity ``v`` and affine
matrix ``C`` by the grid's, so the part of the particle velocity field that the grid cannot
hold is lost at every transfer, a numerical damping per substep. Affine FLIP (the AFLIP
family of Fei et al. 2021) adds the grid's *increment* instead: P2G also scatters the
momentum without this substep's stress (``grid_mv_old``), and G2P takes
``v <- a (v + sum w du) + (1 - a) v_pic`` and
``C <- a (C + sum w (4/dx^2) du (x_i - x_p)^T) + (1 - a) C_pic`` with the node increment
``du = u_new - u_old`` and ``a = exp(-dt / tau)`` (``tau`` a relaxation time towards PIC, so
the remaining dissipation is per second, not per substep). Positions advect with the grid
(PIC) velocity and ``F`` updates with the grid gradient ``C_pic`` in both transfers.

The files, by stage: ``_math`` (matrix helpers and layouts, the B-spline stencil, the polar
decomposition, the constitutive laws), ``_grid`` (grid zero, update and boundary conditions;
the fixed-point and vector atomics), ``_p2g`` (the scatter and the P2G by cells), ``_g2p``
(the gathers, G2P and the fused G2P), ``_state`` (rest state, export gathers, guard
statistics). All of them build ONE Warp module, named after this package
(:data:`~knockgs_core.sim._kernels._module.MODULE`), as when they were one file: one build,
one cache entry and one load on a device.
"""

from ._g2p import columns_to_mat33, fold_line, g2p, g2p_particle, g2p_prepare, gather_by_lines, gather_by_nodes
from ._grid import (FACE_TOLERANCE, FIXED_LIMIT, fixed_add, fixed_value, grid_bc_cuboid, grid_bc_walls, grid_update,
                    grid_update_fixed, grid_update_records, grid_zero, inside_box, nearest_face_normal, node_in_box,
                    updated_node, vec4_atomic_add, wall_velocity)
from ._math import (DISPLACEMENT_ARRAY, MATRIX_ARRAYS, bspline_weights, fixed_corotated_kirchhoff, kelvin_voigt_kirchhoff,
                    mat33_at, mat33_from_rows, mat33_put, mat33_to_f32, mat33_to_f64, mat33d_at, mat33d_put,
                    overload_per_layout, polar_rotation, stencil_base, stencil_inside, vec4_head)
from ._module import CUDA_MAX_REGISTERS, MODULE, NAME
from ._p2g import (apic_term, momentum_mass, node_term, p2g, p2g_particle, p2g_prepare, p2g_sort_keys, p2g_store, p2g_terms,
                   p2g_windows, stencil_offset, warp_run_end, warp_runs_before, window_run_end, window_run_sum,
                   window_runs_before, window_sums, window_sums_fixed)
from ._state import (STATS_BLOCK_DIM, STATS_PER_BLOCK, gather_F, gather_positions, guard_reset, particle_stats,
                     state_rest)

__all__ = [
    # the Warp module
    "NAME", "MODULE", "CUDA_MAX_REGISTERS",
    # shared math
    "mat33_to_f64", "mat33_to_f32", "mat33_at", "mat33_put", "mat33d_at", "mat33d_put", "MATRIX_ARRAYS",
    "DISPLACEMENT_ARRAY", "overload_per_layout", "bspline_weights", "stencil_base", "stencil_inside", "polar_rotation",
    "fixed_corotated_kirchhoff", "kelvin_voigt_kirchhoff", "vec4_head", "mat33_from_rows",
    # grid
    "grid_zero", "wall_velocity", "updated_node", "grid_update", "FIXED_LIMIT", "fixed_add", "fixed_value",
    "grid_update_fixed", "vec4_atomic_add", "grid_update_records", "grid_bc_walls", "inside_box", "nearest_face_normal",
    "FACE_TOLERANCE", "node_in_box", "grid_bc_cuboid",
    # particle to grid
    "p2g_terms", "p2g_particle", "p2g", "p2g_store", "p2g_prepare", "p2g_sort_keys", "stencil_offset", "momentum_mass",
    "apic_term", "node_term", "window_run_sum", "window_sums", "window_sums_fixed", "window_runs_before",
    "warp_runs_before", "warp_run_end", "window_run_end", "p2g_windows",
    # grid to particle
    "gather_by_nodes", "columns_to_mat33", "fold_line", "gather_by_lines", "g2p_particle", "g2p", "g2p_prepare",
    # the state as a whole
    "state_rest", "gather_positions", "gather_F", "STATS_PER_BLOCK", "STATS_BLOCK_DIM", "guard_reset", "particle_stats",
]
