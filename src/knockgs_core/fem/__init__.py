"""A finite-element reference solver, written independently of the MPM simulator.

Small-strain linear elasticity on tetrahedra (P1, or P2 for convergence checks) over a
structured mesh of a box (:mod:`._mesh`), assembled with scikit-fem (:mod:`._elasticity`),
Newmark average-acceleration time integration with consistent (or lumped) mass, optional
Rayleigh damping and gravity (:mod:`._newmark`). Supports are regions whose nodes are held;
probes are force pulses over the body or a region. The solver modules import nothing from
:mod:`knockgs_core.sim`: the two solvers share plain data only (material constants, box
geometry). :mod:`._verification` runs both on one problem (a block held by its bottom layer)
and tabulates the MPM's gap to the reference. docs/verification.md has the formulation and the
measured numbers.
"""

from ._elasticity import (
    MASS_KINDS,
    ElasticSystem,
    assemble_elasticity,
    body_force_load,
    find_elements,
    interpolate,
    interpolation_matrix,
    lame,
    static_solve,
    support_dofs,
)
from ._mesh import Region, box_mesh, mesh_size, tensor_mesh
from ._newmark import DIRECT_MAX_DOFS, SOLVERS, ForcePulse, NewmarkResult, RayleighDamping, newmark
from ._world import FemWorld, fem_world_mesh, fem_world_rollout
from ._verification import (
    BLOCK,
    MATERIAL,
    PROBE_DURATION,
    SUPPORT,
    VerificationSettings,
    block_particles,
    fem_block_reference,
    first_mode_period,
    mpm_block_rollout,
    mpm_dt,
    mpm_period_limit,
    mpm_period_order,
    response_gap,
    rms_curve,
    verification_note,
    verification_study,
)

__all__ = [
    "FemWorld",
    "fem_world_mesh",
    "fem_world_rollout",
    "Region",
    "tensor_mesh",
    "box_mesh",
    "mesh_size",
    "MASS_KINDS",
    "ElasticSystem",
    "assemble_elasticity",
    "body_force_load",
    "support_dofs",
    "static_solve",
    "find_elements",
    "interpolation_matrix",
    "interpolate",
    "lame",
    "SOLVERS",
    "DIRECT_MAX_DOFS",
    "ForcePulse",
    "RayleighDamping",
    "NewmarkResult",
    "newmark",
    "MATERIAL",
    "BLOCK",
    "SUPPORT",
    "PROBE_DURATION",
    "VerificationSettings",
    "block_particles",
    "mpm_dt",
    "mpm_period_limit",
    "mpm_period_order",
    "mpm_block_rollout",
    "fem_block_reference",
    "first_mode_period",
    "rms_curve",
    "response_gap",
    "verification_study",
    "verification_note",
]
