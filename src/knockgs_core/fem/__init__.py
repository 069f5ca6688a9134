"""A finite-element reference solver, written independently of the MPM simulator.

Small-strain linear elasticity on tetrahedra (P1, or P2 for convergence checks) over a
structured mesh of a box or a tapered plate (:mod:`._mesh`), assembled with scikit-fem
(:mod:`._elasticity`, which also gives the natural frequencies by shift-invert Lanczos),
Newmark average-acceleration time integration with consistent (or lumped) mass, optional
Rayleigh damping and gravity (:mod:`._newmark`). Supports are regions whose nodes are held
(all components, or some); probes are force pulses over the body or a region. The solver
modules import nothing from :mod:`knockgs_core.sim`: the two solvers share plain data only
(material constants, box geometry). :mod:`._verification` runs both on one problem (a block
held by its bottom layer) and tabulates the MPM's gap to the reference. docs/verification.md
has the formulation and the measured numbers, and the external anchor (NAFEMS FV32).
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
    natural_frequencies,
    static_solve,
    support_dofs,
)
from ._mesh import Region, box_mesh, level_set_mesh, mesh_size, tapered_plate_mesh, tensor_mesh
from ._newmark import DIRECT_MAX_DOFS, SOLVERS, ForcePulse, NewmarkResult, RayleighDamping, newmark
from ._world import BODIES, FemWorld, body_scale, fem_world_mesh, fem_world_rollout, fem_world_system, held_dofs
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
    "BODIES",
    "FemWorld",
    "body_scale",
    "fem_world_mesh",
    "fem_world_rollout",
    "fem_world_system",
    "held_dofs",
    "Region",
    "tensor_mesh",
    "box_mesh",
    "mesh_size",
    "tapered_plate_mesh",
    "level_set_mesh",
    "MASS_KINDS",
    "ElasticSystem",
    "assemble_elasticity",
    "body_force_load",
    "support_dofs",
    "static_solve",
    "natural_frequencies",
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
