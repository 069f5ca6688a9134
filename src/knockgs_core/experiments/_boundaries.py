"""Discretization and object boundaries of a frozen library (paper Sec. "Discretization,
object and identifiability boundaries").

One component of an object's simulator contract is changed at a time: the hidden "world"
(the five targets) is re-simulated under the changed specification, and theta is estimated
by local ridge from Probe A with the ORIGINAL library (built under the unchanged contract)
and, where asked, with a REBUILT library (the 54 candidates re-simulated under the changed
specification). The conditions (:data:`BOUNDARY_KINDS`):

- ``reference``: nothing changed (the main benchmark; a rebuilt library reproduces it bit
  for bit, because CPU rollouts are deterministic);
- ``fill_density``: the interior fill's particles per cell (``fill.max_particles_per_cell``)
  changed; every particle keeps the per-particle Probe-A force of the original specification,
  so the total force changes with the particle count (the paper's setting);
- ``fill_density_equal_force``: the same fill, the probe force rescaled so the total force on
  the selected particles equals the original's;
- ``fill_seed{k}``: the fill's random seed changed (``contract seed + k``, k = 1 .. n), the
  same specification (a random realization, not a changed model);
- ``grid``: the MPM grid ``n_grid`` scaled (the same particles; the substep is kept unless the
  CFL bound of the new grid needs a shorter one that divides the export intervals);
- ``resolution``: the world made at another resolution profile of the same contract
  (:func:`resolution_profile`: by default ``ci`` <-> ``default``, ``paper`` -> ``default``): its
  own Gaussians, fill, grid, substep and probe forces (force factors 1). Data made elsewhere,
  at a resolution the library was not built at; skipped where the two profiles' resolutions are
  the same (the Ficus's ``ci`` and ``default``).

Fill conditions apply only to objects whose contract has an interior fill.

Probe forces. A contract scales its per-particle forces by ``probe_reference_particles / N``
and a box probe's by its ``selected_reference`` (:meth:`ObjectContract.resolve_probes`: the
total force is the same at every resolution profile). A condition multiplies the
resolved probe force of the changed contract by a factor (:attr:`ConditionWorld.force_factors`):
``N_new / N_orig`` keeps the original per-particle force, ``N_new / N_orig * S_orig / S_new``
(S: particles the probe selects) keeps the original total force. Where the particles are the
same, both factors are exactly 1. The ``resolution`` world keeps its own contract's
forces (factor 1): it is that profile's contract exactly, as data made there would be.

Leave-one-object-out: a shared library of the other objects' candidate tables
(:func:`shared_library`) estimates the held-out object's targets (:func:`loo_table`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable, Literal, Mapping, Sequence

import numpy as np
import pandas as pd

from ..descriptors import FEATURE_NAMES
from ..errors import InputError

__all__ = [
    "BOUNDARY_KINDS",
    "BOUNDARY_LIBRARIES",
    "BoundarySettings",
    "BoundaryStudyCondition",
    "ConditionWorld",
    "boundary_condition",
    "boundary_conditions",
    "condition_contract",
    "condition_world",
    "boundary_table",
    "boundary_note",
    "shared_library",
    "loo_table",
]

#: condition kinds in table order; ``fill_seed`` expands to ``fill_seed1 .. fill_seed{n}``
BOUNDARY_KINDS: tuple[str, ...] = ("reference", "fill_density", "fill_density_equal_force", "fill_seed", "grid", "resolution")
#: the profile a ``resolution`` world is made at, unless the settings name one
RESOLUTION_NEIGHBOURS: Mapping[str, str] = {"ci": "default", "default": "ci", "paper": "default"}
#: the library an estimate comes from: the main one, or the candidates re-simulated under the condition
BOUNDARY_LIBRARIES: tuple[str, ...] = ("original", "rebuilt")
_FILL_KINDS = frozenset({"fill_density", "fill_density_equal_force", "fill_seed"})
_SOURCE = "config boundaries"


@dataclass(frozen=True)
class BoundarySettings:
    """The boundary study's settings (the config's ``boundaries`` block mirrors these defaults).

    ``conditions``: condition kinds to run (:data:`BOUNDARY_KINDS`); ``rebuild``: kinds whose
    matched library is rebuilt; ``fill_particles_per_cell``: the changed fill density
    (particles per interior fill cell; the contracts use 4); ``fill_seeds``: how many seeds
    ``fill_seed`` runs; ``n_grid_scale``: the grid condition's ``n_grid`` multiplier;
    ``resolution_profile``: the profile the ``resolution`` world is made at (``None``: the
    neighbour in :data:`RESOLUTION_NEIGHBOURS`).
    """

    conditions: tuple[str, ...] = BOUNDARY_KINDS
    rebuild: tuple[str, ...] = ("fill_density", "grid", "resolution")
    fill_particles_per_cell: int = 2
    fill_seeds: int = 3
    n_grid_scale: float = 0.75
    resolution_profile: str | None = None

    def __post_init__(self):
        object.__setattr__(self, "conditions", tuple(self.conditions))
        object.__setattr__(self, "rebuild", tuple(self.rebuild))
        for field in ("conditions", "rebuild"):
            bad = [k for k in getattr(self, field) if k not in BOUNDARY_KINDS]
            if bad:
                raise InputError(_SOURCE, field, f"unknown condition {bad[0]!r}; allowed: {', '.join(BOUNDARY_KINDS)}")
        if int(self.fill_particles_per_cell) < 1:
            raise InputError(_SOURCE, "fill_particles_per_cell", f"must be >= 1, got {self.fill_particles_per_cell}")
        if int(self.fill_seeds) < 1:
            raise InputError(_SOURCE, "fill_seeds", f"must be >= 1, got {self.fill_seeds}")
        if not (math.isfinite(self.n_grid_scale) and self.n_grid_scale > 0 and self.n_grid_scale != 1):
            raise InputError(_SOURCE, "n_grid_scale", f"must be finite, > 0 and != 1, got {self.n_grid_scale}")
        if self.resolution_profile is not None and self.resolution_profile not in RESOLUTION_NEIGHBOURS:
            raise InputError(_SOURCE, "resolution_profile",
                             f"must be one of {', '.join(RESOLUTION_NEIGHBOURS)} or null, got {self.resolution_profile!r}")

    @classmethod
    def from_config(cls, block: Mapping) -> "BoundarySettings":
        """Settings from the config's ``boundaries`` block (workflow-only keys ignored)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in block.items() if k in names})


@dataclass(frozen=True)
class BoundaryStudyCondition:
    """One condition: ``name`` (a path component), ``kind`` (:data:`BOUNDARY_KINDS`),
    ``component`` (what changed), ``force`` (``per_particle``: the original per-particle
    probe force; ``total``: the original total force; ``contract``: the changed contract's
    own), ``contract_preserved`` (whether the
    original library's contract still holds: true for the reference and a new fill seed),
    ``rebuild`` (whether a matched library is rebuilt) and the changed value."""

    name: str
    kind: str
    component: str
    force: Literal["per_particle", "total", "contract"]
    contract_preserved: bool
    rebuild: bool
    value: float | int | str | None = None

    def describe(self, contract) -> str:
        """One line for tables: what changed, from what to what."""
        if self.kind == "reference":
            return "unchanged contract"
        if self.kind == "fill_seed":
            return f"fill seed {contract.fill.seed} -> {self.value}"
        if self.kind == "grid":
            return f"n_grid {contract.sim.n_grid} -> {self.value}"
        if self.kind == "resolution":
            return f"world at the {self.value} profile's resolution, library at {contract.profile}'s"
        force = "equal total force" if self.force == "total" else "original per-particle force"
        return f"fill {contract.fill.max_particles_per_cell} -> {self.value} particles/cell, {force}"


def resolution_profile(contract, settings: BoundarySettings) -> str:
    """The profile a ``resolution`` world of ``contract`` is made at: the settings' choice, else
    the neighbour of the contract's profile (:data:`RESOLUTION_NEIGHBOURS`)."""
    other = settings.resolution_profile or RESOLUTION_NEIGHBOURS.get(contract.profile)
    if other is None or other == contract.profile or other not in contract.profiles:
        raise InputError(_SOURCE, "resolution_profile", f"no other profile for {contract.name} at {contract.profile!r}"
                         f" (got {other!r}; the contract's profiles: {', '.join(contract.profiles)})")
    return other


def _resolution_contract(contract, other: str):
    from ..contract import load_contract

    return load_contract(contract.source, other)


def _same_resolution(a, b) -> bool:
    """Whether two profiles of one contract simulate the same particles on the same grid."""
    return a.profiles[a.profile] == b.profiles[b.profile]


def boundary_conditions(contract, settings: BoundarySettings) -> list[str]:
    """The condition names that apply to ``contract``, in table order (fill conditions only
    where the contract has an interior fill; ``resolution`` only where the other profile's
    resolution differs)."""
    names = []
    for kind in settings.conditions:
        if kind in _FILL_KINDS and not contract.fill.enabled:
            continue
        if kind == "resolution":
            other = _resolution_contract(contract, resolution_profile(contract, settings))
            if _same_resolution(contract, other):
                continue
        if kind == "fill_seed":
            names += [f"fill_seed{k}" for k in range(1, int(settings.fill_seeds) + 1)]
        else:
            names.append(kind)
    return names


def _kind_of(name: str) -> tuple[str, int | None]:
    if name.startswith("fill_seed") and name[len("fill_seed"):].isdigit():
        return "fill_seed", int(name[len("fill_seed"):])
    if name in BOUNDARY_KINDS and name != "fill_seed":
        return name, None
    raise InputError(_SOURCE, "condition", f"unknown condition {name!r}; allowed: "
                     f"{', '.join(k if k != 'fill_seed' else 'fill_seed<k>' for k in BOUNDARY_KINDS)}")


def boundary_condition(contract, name: str, settings: BoundarySettings) -> BoundaryStudyCondition:
    """The condition ``name`` (e.g. ``fill_density``, ``fill_seed2``) of ``contract``."""
    kind, k = _kind_of(name)
    if kind in _FILL_KINDS and not contract.fill.enabled:
        raise InputError(contract.source, "fill.enabled", f"condition {name!r} changes the interior fill, "
                         "which this contract does not have")
    rebuild = kind in settings.rebuild
    if kind == "reference":
        return BoundaryStudyCondition(name, kind, "none", "per_particle", True, rebuild)
    if kind == "fill_seed":
        if not 1 <= k <= int(settings.fill_seeds):
            raise InputError(_SOURCE, "fill_seeds", f"condition {name!r}: seed index outside 1 .. {settings.fill_seeds}")
        return BoundaryStudyCondition(name, kind, "fill seed", "per_particle", True, rebuild, int(contract.fill.seed) + k)
    if kind == "grid":
        n = int(round(contract.sim.n_grid * float(settings.n_grid_scale)))
        if n < 4 or n == contract.sim.n_grid:
            raise InputError(_SOURCE, "n_grid_scale", f"n_grid {contract.sim.n_grid} x {settings.n_grid_scale} "
                             f"gives {n}: not a changed grid of at least 4 cells")
        return BoundaryStudyCondition(name, kind, "grid", "per_particle", False, rebuild, n)
    if kind == "resolution":
        other = resolution_profile(contract, settings)
        if _same_resolution(contract, _resolution_contract(contract, other)):
            raise InputError(_SOURCE, "resolution_profile", f"{contract.name}'s {other!r} profile has the resolution "
                             f"of {contract.profile!r}: not a changed condition")
        return BoundaryStudyCondition(name, kind, "resolution profile", "contract", False, rebuild, other)
    m = int(settings.fill_particles_per_cell)
    if m == contract.fill.max_particles_per_cell:
        raise InputError(_SOURCE, "fill_particles_per_cell",
                         f"equals the contract's fill density ({m}): not a changed condition")
    force = "total" if kind == "fill_density_equal_force" else "per_particle"
    return BoundaryStudyCondition(name, kind, "fill density", force, False, rebuild, m)


def condition_contract(contract, condition: BoundaryStudyCondition):
    """The contract with the condition's one component changed (a copy; the grid condition
    also shortens the substep where the new grid's CFL bound needs it)."""
    replace = dataclasses.replace
    if condition.kind == "reference":
        return contract
    if condition.kind == "fill_seed":
        return replace(contract, fill=replace(contract.fill, seed=int(condition.value)))
    if condition.kind == "grid":
        sim = replace(contract.sim, n_grid=int(condition.value))
        variant = replace(contract, sim=sim)
        dt = min(contract.sim.dt, variant.cfl_dt())
        return replace(variant, sim=replace(sim, dt=dt)) if dt != contract.sim.dt else variant
    if condition.kind == "resolution":
        return _resolution_contract(contract, str(condition.value))
    return replace(contract, fill=replace(contract.fill, max_particles_per_cell=int(condition.value)))


@dataclass(frozen=True)
class ConditionWorld:
    """A condition's simulated world: the ``original`` and the changed ``contract``, the
    changed contract's ``particles`` (:class:`~knockgs_core.assets.ParticleSet`) and
    ``force_factors`` (probe name -> the factor on the changed contract's resolved probe
    force, see the module docstring)."""

    condition: BoundaryStudyCondition
    original: object
    contract: object
    particles: object
    force_factors: Mapping[str, float]

    def rollout(self, theta: tuple[float, float], probe_name: str, *, device: str | None = None,
                deterministic: bool = False, export_F: bool = False, progress: Callable | None = None):
        """One rollout (:func:`knockgs_core.rollout.run_rollout`, whose ``device``,
        ``deterministic``, ``export_F`` and ``progress`` these are) of ``theta`` under the
        condition's probe ``probe_name``; the metadata gain ``boundary_condition`` and
        ``probe_force_factor``."""
        from ..rollout import run_rollout

        if probe_name not in self.force_factors:
            raise InputError(self.contract.source, "probes", f"unknown probe '{probe_name}'; known: {sorted(self.force_factors)}")
        probe = self.contract.resolve_probes(self.particles)[probe_name]
        factor = float(self.force_factors[probe_name])
        if factor != 1.0:
            probe = dataclasses.replace(probe, force=tuple(float(f) * factor for f in probe.force))
        ro = run_rollout(self.contract, theta, probe_name, particles=self.particles, device=device,
                         deterministic=deterministic, export_F=export_F, probe=probe, progress=progress)
        ro.meta["boundary_condition"] = self.condition.name
        ro.meta["probe_force_factor"] = factor
        return ro

    def summary(self, original_particles) -> dict:
        """Counts and forces for tables: particles, fill particles, grid, substep, the contract
        hash, and per probe the force factor and the total force relative to the original
        specification (``original_particles``: the unchanged contract's)."""
        t0 = _probe_forces(self.original, original_particles)
        t1 = _probe_forces(self.contract, self.particles)
        c = self.condition
        return {"condition": c.name, "kind": c.kind, "component": c.component, "value": c.value, "force": c.force,
                "contract_preserved": c.contract_preserved, "description": c.describe(self.original),
                "contract_hash": self.contract.hash, "calibration_probe": self.contract.roles["calibration"],
                "particles": len(self.particles), "fill_particles": int(self.particles.n_fill),
                "original_particles": len(original_particles), "n_grid": int(self.contract.sim.n_grid),
                "dt": float(self.contract.sim.dt), "force_factors": dict(self.force_factors),
                "total_force_ratio": {p: self.force_factors[p] * t1[p][1] / t0[p][1] for p in self.force_factors}}


def _probe_forces(contract, particles) -> dict[str, tuple[float, float]]:
    """probe name -> (per-particle force magnitude, total force magnitude over the selected
    particles) [N] as ``contract`` applies them to ``particles``: the resolved force scaled by
    ``probe_reference_particles / N``."""
    scale = float(contract.probe_reference_particles) / len(particles)
    out = {}
    for name, probe in contract.resolve_probes(particles).items():
        per_particle = float(np.linalg.norm(np.asarray(probe.force, dtype=np.float64))) * scale
        selected = int(np.count_nonzero(contract.probe_selection(probe, particles.positions)))
        out[name] = (per_particle, per_particle * selected)
    return out


def condition_world(contract, name: str, settings: BoundarySettings, *, particles=None,
                    original_particles=None, force_factors: Mapping[str, float] | None = None) -> ConditionWorld:
    """The world of condition ``name`` of ``contract``.

    ``particles`` (the changed contract's) and ``original_particles`` default to building the
    assets (:func:`knockgs_core.assets.build_asset`); ``force_factors`` default to those the
    condition's force rule gives from the two particle sets (a rollout job passes the ones
    its asset job recorded, so it needs no original asset).
    """
    from ..assets import build_asset

    condition = boundary_condition(contract, name, settings)
    variant = condition_contract(contract, condition)
    if particles is None:
        particles = build_asset(variant).particles
    if force_factors is None and condition.force == "contract":
        force_factors = {p: 1.0 for p in variant.probes}
    if force_factors is None:
        if original_particles is None:
            original_particles = build_asset(contract).particles
        t0 = _probe_forces(contract, original_particles)
        t1 = _probe_forces(variant, particles)
        i = 1 if condition.force == "total" else 0   # keep the total or the per-particle force
        force_factors = {p: t0[p][i] / t1[p][i] for p in variant.probes}
    return ConditionWorld(condition, contract, variant, particles, dict(force_factors))


# ------------------------------------------------------------------------------------ tables


def boundary_table(metrics: pd.DataFrame, summaries: Mapping[str, Mapping], *, probe: str) -> pd.DataFrame:
    """One row per (condition, library): the joint error over the targets (mean, max, sd) and
    the mean Probe-B trajectory RMSE of the frozen write-back, both under the changed
    specification, and what the condition did to the contract.

    ``metrics``: rows of :func:`knockgs_core.experiments.evaluate_method` with ``condition``
    and ``library`` columns (one probe, ``probe``); ``summaries``: condition name ->
    :meth:`ConditionWorld.summary`, in table order. A rebuilt library preserves the contract.
    """
    rows = []
    for name, s in summaries.items():
        for library in BOUNDARY_LIBRARIES:
            e = metrics[(metrics["condition"] == name) & (metrics["library"] == library) & (metrics["probe"] == probe)]
            if e.empty:
                continue
            if e["target"].duplicated().any():
                raise InputError("boundary metrics", "target", f"duplicate targets for ({name}, {library})")
            err = e["joint_error_pct"].to_numpy(dtype=float)
            rows.append({
                "condition": name, "library": library, "component": s["component"],
                "contract_preserved": bool(s["contract_preserved"] or library == "rebuilt"),
                "joint_error_mean_pct": float(err.mean()), "joint_error_max_pct": float(err.max()),
                "joint_error_sd_pct": float(err.std(ddof=1)) if len(err) > 1 else 0.0,
                f"traj_rmse_{probe}": float(e["traj_rmse"].mean()), "n_targets": int(len(e)),
                "particles": int(s["particles"]), "n_grid": int(s["n_grid"]),
                "total_force_ratio": float(s["total_force_ratio"][s["calibration_probe"]]),
                "description": s["description"],
            })
    return pd.DataFrame(rows)


def boundary_note(table: pd.DataFrame, *, profile: str, probe_a: str, probe_b: str) -> str:
    """The Markdown note under a boundaries table: what the columns mean, and the fill seeds'
    mean and max joint error over every seed and target."""
    note = (f"Profile `{profile}`; local ridge from Probe A ({probe_a}); joint parameter error [%] over the "
            f"held-out targets re-simulated under each condition; trajectory RMSE of the frozen write-back "
            f"under Probe B ({probe_b}), same condition [normalized-domain m]. library original: the main "
            "library; rebuilt: the candidates re-simulated under the condition. total_force_ratio: the total "
            "Probe-A force relative to the original specification.")
    seeds = table[table["condition"].str.startswith("fill_seed") & (table["library"] == "original")]
    if not seeds.empty:
        mean = float((seeds["joint_error_mean_pct"] * seeds["n_targets"]).sum() / seeds["n_targets"].sum())
        note += (f" Fill seeds ({len(seeds)} seeds x {int(seeds['n_targets'].iloc[0])} targets, original library): "
                 f"mean {mean:.3g} %, max {seeds['joint_error_max_pct'].max():.3g} %.")
    return note


def shared_library(tables: Mapping[str, pd.DataFrame]) -> pd.DataFrame:
    """One library of several objects' candidate tables (object name -> library table):
    case names become ``object/case_name``; an ``object`` column records the source."""
    if not tables:
        raise InputError("shared library", "objects", "needs at least one other object's library")
    cols = ["case_name", "E_scale", "density_scale", *FEATURE_NAMES]
    parts = []
    for obj, t in tables.items():
        missing = [c for c in cols if c not in t.columns]
        if missing:
            raise InputError(f"library of {obj}", missing[0], "missing column")
        part = t[cols].copy()
        part["case_name"] = obj + "/" + part["case_name"].astype(str)
        part.insert(1, "object", obj)
        parts.append(part)
    return pd.concat(parts, ignore_index=True)


def loo_table(metrics: Mapping[str, pd.DataFrame], own: Mapping[str, pd.DataFrame], *, probes: Mapping[str, str],
              trained_on: Mapping[str, Sequence[str]]) -> pd.DataFrame:
    """Leave-one-object-out: one row per held-out object with the shared estimator's joint
    error (mean, max) and Probe-B trajectory RMSE, beside the object's own-library error.

    ``metrics``/``own``: object -> rows of :func:`knockgs_core.experiments.evaluate_method` of
    the shared estimator / of the object's own local ridge; ``probes``: object -> its Probe B;
    ``trained_on``: object -> the objects whose libraries trained the shared estimator.
    """
    rows = []
    for obj, e in metrics.items():
        e = e[e["probe"] == probes[obj]]
        o = own[obj].drop_duplicates("target")
        o_b = own[obj][own[obj]["probe"] == probes[obj]]
        err = e["joint_error_pct"].to_numpy(dtype=float)
        rows.append({
            "object": obj, "library": "shared (" + " + ".join(trained_on[obj]) + ")", "contract_preserved": False,
            "joint_error_mean_pct": float(err.mean()), "joint_error_max_pct": float(err.max()),
            "probe_b": probes[obj], "traj_rmse_b": float(e["traj_rmse"].mean()),
            "own_joint_error_mean_pct": float(o["joint_error_pct"].mean()),
            "own_traj_rmse_b": float(o_b["traj_rmse"].mean()), "n_targets": int(len(e)),
        })
    return pd.DataFrame(rows)
