"""MLS-MPM simulator in NVIDIA Warp (one code path for CPU and CUDA).

A static :class:`Model` (particles, materials, boundary conditions, probe) apart from a
time-varying :class:`State`; :class:`MPMSolver` advances one substep; :func:`simulate` runs
a rollout and exports frames. Boundary conditions and probes are data
(:mod:`knockgs_core.sim._config`).
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
)
from ._solver import MPMSolver, Model, SimResult, State, build_model, default_device, make_state, particle_volumes, simulate

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
    "MPMSolver",
    "Model",
    "SimResult",
    "State",
    "build_model",
    "default_device",
    "make_state",
    "particle_volumes",
    "simulate",
]
