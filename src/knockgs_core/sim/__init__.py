"""MLS-MPM simulator in NVIDIA Warp (one code path for CPU and CUDA).

A static :class:`Model` (particles, materials, boundary conditions, probe) apart from a
time-varying :class:`State` (:mod:`knockgs_core.sim._model`); :class:`MPMSolver` advances one
substep (:mod:`knockgs_core.sim._solver`) as a frozen :class:`SolverConfig` says, its
``"auto"`` options resolved for the device in one place (:meth:`SolverConfig.resolve`);
:func:`simulate` runs a rollout and exports frames (:mod:`knockgs_core.sim._simulate`); the
Warp kernels are :mod:`knockgs_core.sim._kernels`, files by stage in one Warp module. Boundary
conditions, probes and solver settings are data (:mod:`knockgs_core.sim._config`). Extra
physics terms, all off by default, are effects (:mod:`knockgs_core.sim._effects`) following the
:class:`Effect` protocol (:mod:`knockgs_core.sim._protocol`: no-op hooks, scratch made by
``setup(model)`` and held by the solver), switched on with :func:`with_effects`.
"""

from .._lazy import lazy_names
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
    SolverConfig,
    GPU_SOLVER_OPTIONS,
    is_still_sticky,
    probe_weights,
)
from ._protocol import Effect

# The data (boundary conditions, probes, materials, solver settings) import without Warp; the
# parts that define or launch Warp kernels (effects, model, solver, rollouts) are imported on
# first use, so that reading a contract or a table does not pay Warp's start-up.
_LAZY = {
    "._effects": ("BodyForcePulse", "Gravity", "HiddenMass", "PoissonShift", "StiffnessGradient", "MaterialViscosity",
                  "SupportFriction", "SupportSlip", "VelocityDamping", "VonMisesPlasticity", "effect_examples",
                  "viscous_stability_limit", "with_effects"),
    "._model": ("GPU_STORAGE", "Model", "State", "body_volume", "build_model", "cell_crowding", "default_device",
                "device_storage", "make_state", "particle_volumes"),
    "._simulate": ("SimResult", "simulate", "simulate_many"),
    "._solver": ("MPMSolver",),
}
__getattr__, __dir__ = lazy_names(__name__, globals(), _LAZY)


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
    "probe_weights",
    "GPU_SOLVER_OPTIONS",
    "GPU_STORAGE",
    "MPMSolver",
    "SolverConfig",
    "Model",
    "SimResult",
    "State",
    "build_model",
    "device_storage",
    "default_device",
    "make_state",
    "particle_volumes",
    "body_volume",
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
