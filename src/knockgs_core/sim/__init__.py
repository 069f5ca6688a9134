"""MLS-MPM simulator in NVIDIA Warp (one code path for CPU and CUDA).

A static :class:`Model` (particles, materials, boundary conditions, probe) apart from a
time-varying :class:`State`; :class:`MPMSolver` advances one substep; :func:`simulate` runs
a rollout and exports frames. Boundary conditions and probes are data
(:mod:`knockgs_core.sim._config`). Extra physics terms, all off by default, are effects
(:mod:`knockgs_core.sim._effects`) following the :class:`Effect` protocol
(:mod:`knockgs_core.sim._protocol`: no-op hooks, scratch made by ``setup(model)`` and held
by the solver), switched on with :func:`with_effects`.
"""

from ._config import (
    BoundaryCondition,
    Box,
    DomainWalls,
    ExportSchedule,
    FixedCuboid,
    Material,
    ParticleTranslation,
    Probe,
    SimParams,
    is_still_sticky,
)
from ._effects import (
    BodyForcePulse,
    Gravity,
    HiddenMass,
    PoissonShift,
    StiffnessGradient,
    MaterialViscosity,
    SupportFriction,
    SupportSlip,
    VelocityDamping,
    VonMisesPlasticity,
    effect_examples,
    viscous_stability_limit,
    with_effects,
)
from ._protocol import Effect
from ._solver import (GPU_SOLVER_OPTIONS, GPU_STORAGE, MPMSolver, Model, SimResult, State, build_model, cell_crowding,
                      default_device, device_storage, make_state, particle_volumes, simulate, simulate_many)

__all__ = [
    "BoundaryCondition",
    "Box",
    "DomainWalls",
    "ExportSchedule",
    "FixedCuboid",
    "Material",
    "ParticleTranslation",
    "Probe",
    "SimParams",
    "is_still_sticky",
    "GPU_SOLVER_OPTIONS",
    "GPU_STORAGE",
    "MPMSolver",
    "Model",
    "SimResult",
    "State",
    "build_model",
    "device_storage",
    "default_device",
    "make_state",
    "particle_volumes",
    "cell_crowding",
    "simulate",
    "simulate_many",
    "Effect",
    "VelocityDamping",
    "Gravity",
    "VonMisesPlasticity",
    "PoissonShift",
    "StiffnessGradient",
    "MaterialViscosity",
    "viscous_stability_limit",
    "SupportFriction",
    "SupportSlip",
    "BodyForcePulse",
    "HiddenMass",
    "with_effects",
    "effect_examples",
]
