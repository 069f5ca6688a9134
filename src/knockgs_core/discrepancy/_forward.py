"""The forward model of the loop: a contract at (theta, effect strengths), cached (private)."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..sim import is_still_sticky, with_effects
from ._catalogue import Candidate

__all__ = ["ModelSpec", "ForwardModel"]


@dataclass(frozen=True)
class ModelSpec:
    """A model of the loop: ``theta = (s_E, s_rho)`` and the strengths ``u`` of the added
    catalogue effects (``effects``: tuple of (key, u) in the order they were added)."""

    theta: tuple[float, float]
    effects: tuple[tuple[str, float], ...] = ()

    def with_theta(self, theta) -> ModelSpec:
        return ModelSpec((float(theta[0]), float(theta[1])), self.effects)

    def with_effect(self, key: str, u: float) -> ModelSpec:
        eff = dict(self.effects)
        eff[key] = float(u)
        keys = [k for k, _ in self.effects] + ([key] if key not in dict(self.effects) else [])
        return ModelSpec(self.theta, tuple((k, eff[k]) for k in keys))

    @property
    def effect_keys(self) -> tuple[str, ...]:
        return tuple(k for k, _ in self.effects)

    def cache_key(self, probe: str):
        return (probe, round(self.theta[0], 12), round(self.theta[1], 12), tuple((k, round(u, 12)) for k, u in self.effects))


@dataclass
class ForwardModel:
    """Simulates ``contract`` on ``particles`` at a :class:`ModelSpec`; rollouts are cached
    by (probe, spec), oldest dropped first beyond ``max_cache`` entries or
    ``max_cache_bytes``. ``catalogue`` maps effect keys to :class:`Candidate` entries (given
    when the model is built, or by :meth:`with_catalogue`). ``device`` and ``deterministic``:
    every rollout's (:func:`knockgs_core.rollout.run_rollouts`). ``n_simulations`` and
    ``seconds`` count the simulator calls actually made."""

    contract: object
    particles: object
    catalogue: dict[str, Candidate] = field(default_factory=dict)
    device: str | None = None
    deterministic: bool = False
    max_cache: int = 64
    max_cache_bytes: float = 2e9
    n_simulations: int = 0
    seconds: float = 0.0
    _cache: dict = field(default_factory=dict, repr=False)

    def with_catalogue(self, catalogue: dict[str, Candidate]) -> ForwardModel:
        """This model with ``catalogue``, taking over its cache and counters (the rollouts
        cached so far have no effects, so they stay valid); use it in place of this one."""
        if any(effects for (_, _, _, effects) in self._cache):
            raise InputError("model", "catalogue", "the cache holds rollouts with effects of another catalogue")
        return dataclasses.replace(self, catalogue=dict(catalogue))

    def effects(self, spec: ModelSpec) -> tuple:
        out = []
        for key, u in spec.effects:
            if key not in self.catalogue:
                raise InputError("model", "effects", f"unknown effect '{key}'")
            if u != 0.0:
                out.append(self.catalogue[key].effect(u))
        return tuple(out)

    def rollout(self, spec: ModelSpec, probe: str) -> np.ndarray:
        """Positions [T, N, 3] (float32) of every particle under ``probe``."""
        key = spec.cache_key(probe)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        from ..rollout import run_rollout

        params = with_effects(self.contract.sim, *self.effects(spec))
        t0 = time.perf_counter()
        r = run_rollout(
            self.contract, spec.theta, probe, particles=self.particles, device=self.device,
            deterministic=self.deterministic,
            sim_overrides={"effects": params.effects, "boundaries": params.boundaries},
        )
        self.seconds += time.perf_counter() - t0
        self.n_simulations += 1
        while self._cache and (len(self._cache) >= self.max_cache or
                               sum(a.nbytes for a in self._cache.values()) + r.positions.nbytes > self.max_cache_bytes):
            self._cache.pop(next(iter(self._cache)))
        self._cache[key] = r.positions
        return r.positions

    def deformation(self, spec: ModelSpec, probe: str) -> np.ndarray:
        """Deformation gradients [T, n_gs, 3, 3] of the Gaussian-associated particles (not cached)."""
        from ..rollout import run_rollout

        params = with_effects(self.contract.sim, *self.effects(spec))
        t0 = time.perf_counter()
        r = run_rollout(
            self.contract, spec.theta, probe, particles=self.particles, device=self.device,
            deterministic=self.deterministic, export_F=True,
            sim_overrides={"effects": params.effects, "boundaries": params.boundaries},
        )
        self.seconds += time.perf_counter() - t0
        self.n_simulations += 1
        return r.F

    def probe_export(self, probe: str):
        if probe not in self.contract.probes:
            known = sorted(self.contract.probes)
            raise InputError(f"object {self.contract.name}", "probe", f"unknown probe '{probe}'; known: {known}")
        return self.contract.probes[probe].export

    # contract facts the catalogue needs -----------------------------------------------
    def has_gravity(self) -> bool:
        return any(abs(g) > 0 for g in self.contract.sim.gravity)

    def has_still_support(self) -> bool:
        return any(is_still_sticky(bc) for bc in self.contract.sim.boundaries)

    def base_materials(self):
        """Per-particle base (E, nu, rho) at theta = (1, 1), no effects."""
        E, nu, rho = self.contract.particle_materials(self.particles, (1.0, 1.0))
        n = len(self.particles.positions)
        return tuple(np.broadcast_to(np.asarray(a, dtype=np.float64), (n,)) for a in (E, nu, rho))

