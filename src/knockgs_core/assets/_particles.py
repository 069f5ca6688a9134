"""Simulated particles of an asset and their ``.npz`` files (private)."""

from __future__ import annotations

import io
import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from knockgs_core.io import write_bytes
from knockgs_core.errors import InputError

from ._gaussians import _as_array, _readonly

__all__ = ["ParticleSet", "save_particles", "load_particles"]


@dataclass(frozen=True, eq=False)
class ParticleSet:
    """MPM particles in the normalized domain.

    Attributes
    ----------
    positions: [N, 3] float32
        Rest positions; rows ``0 .. n_gs-1`` are Gaussian-associated particles, the
        remaining ``n_fill`` rows are interior fill particles.
    volumes: [N] float32 or None
        Rest volumes [m^3]; None lets the simulator derive them from the initial number
        of particles per grid cell (PhysGaussian).
    n_gs: int
        Number of Gaussian-associated particles.
    gaussian_index: [n_gs] int64
        Row of each Gaussian-associated particle in the rendered Gaussian set.
    region: [N] int32
        Material-region index into ``region_names`` (0 = base material).
    region_names: tuple[str, ...]
        ``region_names[0] == "base"``.
    fill_cells: int
        Number of fill-grid cells that received fill particles.

    Arrays are copied on construction and read-only afterwards.
    """

    positions: np.ndarray
    volumes: np.ndarray | None
    n_gs: int
    gaussian_index: np.ndarray
    region: np.ndarray
    region_names: tuple[str, ...] = ("base",)
    fill_cells: int = 0

    def __post_init__(self):
        src = "ParticleSet"
        pos = _as_array(self.positions, src, "positions", (-1, 3), np.float32)
        n = pos.shape[0]
        if not np.all(np.isfinite(pos)):
            raise InputError(src, "positions", "contains non-finite values")
        n_gs = int(self.n_gs)
        if not 0 <= n_gs <= n:
            raise InputError(src, "n_gs", f"must lie in [0, {n}], got {self.n_gs}")
        vol = None
        if self.volumes is not None:
            vol = _as_array(self.volumes, src, "volumes", (n,), np.float32)
            if not np.all(vol > 0):
                raise InputError(src, "volumes", "must be finite and > 0")
            vol = _readonly(vol)
        gi = _as_array(self.gaussian_index, src, "gaussian_index", (n_gs,), np.int64)
        reg = _as_array(self.region, src, "region", (n,), np.int32)
        names = tuple(str(s) for s in self.region_names)
        if not names or names[0] != "base":
            raise InputError(src, "region_names", f"must start with 'base', got {names}")
        if n and (reg.min() < 0 or reg.max() >= len(names)):
            raise InputError(src, "region", f"indices must lie in [0, {len(names) - 1}]")
        object.__setattr__(self, "positions", _readonly(pos))
        object.__setattr__(self, "volumes", vol)
        object.__setattr__(self, "n_gs", n_gs)
        object.__setattr__(self, "gaussian_index", _readonly(gi))
        object.__setattr__(self, "region", _readonly(reg))
        object.__setattr__(self, "region_names", names)
        object.__setattr__(self, "fill_cells", int(self.fill_cells))

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_fill(self) -> int:
        """Number of fill particles."""
        return len(self) - self.n_gs

    @property
    def is_fill(self) -> np.ndarray:
        """[N] bool, True for fill particles."""
        m = np.zeros(len(self), dtype=bool)
        m[self.n_gs:] = True
        return m

    def region_counts(self) -> dict[str, int]:
        """Particles per material region."""
        counts = np.bincount(self.region, minlength=len(self.region_names))
        return {name: int(c) for name, c in zip(self.region_names, counts)}


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An ``.npz`` archive whose bytes depend only on ``arrays`` (fixed zip timestamps)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, arr in arrays.items():
            member = io.BytesIO()
            np.lib.format.write_array(member, np.ascontiguousarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            zf.writestr(info, member.getvalue())
    return buf.getvalue()


def save_particles(ps: ParticleSet, path: str | os.PathLike, *, contract=None) -> None:
    """Write ``ps`` to an ``.npz`` file (byte-identical for identical particle sets), atomically.

    With ``contract`` (the :class:`~knockgs_core.contract.ObjectContract` the particles were
    built from), its object name, profile and hash are stored too, and :func:`load_particles`
    refuses the file under any other contract.
    """
    meta = {"n_gs": ps.n_gs, "region_names": list(ps.region_names), "fill_cells": ps.fill_cells,
            "has_volumes": ps.volumes is not None, "format": "knockgs-particles/1"}
    if contract is not None:
        meta.update(object=contract.name, profile=contract.profile, contract_hash=contract.hash)
    arrays = {"positions": ps.positions, "gaussian_index": ps.gaussian_index,
              "region": ps.region,
              "meta": np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)}
    if ps.volumes is not None:
        arrays["volumes"] = ps.volumes
    write_bytes(path, _npz_bytes(arrays))


def _check_use(path: Path, meta: dict, ps: ParticleSet, contract) -> None:
    """The particle file against the contract it is used with (metadata when stored, else regions)."""
    for key, want in (("object", contract.name), ("profile", contract.profile), ("contract_hash", contract.hash)):
        got = meta.get(key)
        if got is not None and got != want:
            raise InputError(path, f"meta.{key}", f"the particles were built for {key} '{got}', "
                             f"used with '{want}' ({contract.source})")
    if tuple(ps.region_names) != tuple(contract.region_names):
        raise InputError(path, "meta.region_names", f"particle regions {list(ps.region_names)} are not the "
                         f"contract's {list(contract.region_names)} ({contract.source})")


def load_particles(path: str | os.PathLike, *, contract=None) -> ParticleSet:
    """Read a file written by :func:`save_particles`.

    With ``contract``, the file is checked against it: the stored object, profile and
    contract hash (when the file has them) and the material regions must match. Every
    problem raises :class:`~knockgs_core.errors.InputError` naming the file and the field.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputError(path, "file", "does not exist") from None
    except IsADirectoryError:
        raise InputError(path, "file", "is a folder, not a particle .npz file") from None
    except Exception as exc:  # BadZipFile, EOFError, ValueError (object arrays, a bad header), OSError
        raise InputError(path, "file", f"not a particle .npz file ({type(exc).__name__}: {exc})") from None
    for key in ("positions", "gaussian_index", "region", "meta"):
        if key not in data:
            raise InputError(path, key, "missing from the particle file")
    try:
        meta = json.loads(bytes(np.asarray(data["meta"], dtype=np.uint8)).decode())
    except (TypeError, ValueError) as exc:
        raise InputError(path, "meta", f"not the JSON of a particle file ({exc})") from None
    if not isinstance(meta, dict):
        raise InputError(path, "meta", "must be a JSON object")
    for key in ("n_gs", "region_names", "fill_cells"):
        if key not in meta:
            raise InputError(path, f"meta.{key}", "missing from the particle file")
    try:
        ps = ParticleSet(positions=data["positions"], volumes=data.get("volumes"),
                         n_gs=meta["n_gs"], gaussian_index=data["gaussian_index"],
                         region=data["region"], region_names=tuple(meta["region_names"]),
                         fill_cells=meta["fill_cells"])
    except InputError as exc:
        raise InputError(path, exc.field, exc.message) from None
    except (TypeError, ValueError) as exc:
        raise InputError(path, "meta", f"inconsistent particle file ({exc})") from None
    if contract is not None:
        _check_use(path, meta, ps, contract)
        _check_domain(path, ps.positions, contract)
    return ps


def _check_domain(path, positions, contract) -> None:
    """The particles inside the contract's simulation domain (3 cells from its walls, where the
    solver takes them) and not all at one point: refused naming the file, before a probe box
    that selects none of them is blamed."""
    x = np.asarray(positions, dtype=np.float64)
    lo, hi = 3 * contract.sim.dx, contract.sim.grid_lim - 3 * contract.sim.dx
    if x.size and (x.min() < lo or x.max() > hi):
        i = int(np.argmax(((x < lo) | (x > hi)).any(axis=1)))
        raise InputError(path, "positions", f"particle {i} at {x[i].tolist()} lies outside the simulation domain "
                         f"[{lo:g}, {hi:g}]^3 of {contract.source} (3 cells inside [0, grid_lim])")
    if len(x) > 1 and np.ptp(x, axis=0).max() == 0.0:
        raise InputError(path, "positions", f"all {len(x)} particles are at one point {x[0].tolist()}")
