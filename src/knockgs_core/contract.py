"""Object contracts: config/objects/NAME.yaml -> a validated, frozen :class:`ObjectContract`.

A contract is loaded by path (``load_contract("some/dir/pillow.yaml")``: works from any
directory) or by name (``load_contract("pillow")``: ``objects/pillow.yaml`` in the
configuration directory). Finding the configuration directory (:func:`find_config_dir`),
first match wins:

1. the ``config_dir`` argument;
2. the environment variable ``KNOCKGS_CONFIG_DIR``;
3. a ``config/`` folder holding ``objects/`` in the current working directory or one of
   its parents (a project checkout);
4. the ``config/`` folder of the source checkout this package was imported from (an
   editable install).

The JSON Schema of a contract ships with the package (``knockgs_core/schemas/
object.schema.yaml``, read through :mod:`importlib.resources`; :func:`schema_path`), so
validation never depends on the working directory. Every problem with a contract raises
:class:`~knockgs_core.errors.InputError` naming the file and the field (a dotted path,
``probes.standard_x.force[0]``).

Defaults live in the frozen dataclasses (this module and :class:`knockgs_core.sim.SimParams`);
the schema mirrors them.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from dataclasses import dataclass, field, fields, replace
from fractions import Fraction
from functools import cached_property, lru_cache
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from .io import input_problem, json_safe
from .errors import InputError
from .sim import (
    Box,
    DomainWalls,
    ExportSchedule,
    FixedCuboid,
    Material,
    ParticleTranslation,
    Probe,
    SimParams,
)

__all__ = [
    "ObjectContract",
    "at_resolution",
    "with_body",
    "AssetSettings",
    "FillSettings",
    "Profile",
    "PROFILES",
    "RESOURCE_LIMITS",
    "THETA_STIFFEST",
    "check_held_out",
    "load_contract",
    "read_yaml",
    "list_objects",
    "find_config_dir",
    "schema_path",
    "cfl_dt",
    "load_candidates",
    "load_targets",
]

#: the resolution profiles every contract defines
PROFILES = ("ci", "default", "paper")
#: (s_E, s_rho) of the stiffest, lightest candidate: the fastest waves of the library
THETA_STIFFEST = (1.15, 0.75)
_ENV = "KNOCKGS_CONFIG_DIR"


# --------------------------------------------------------------------------- settings

@dataclass(frozen=True)
class AssetSettings:
    """Where the Gaussians come from and how they are preprocessed.

    ``procedural`` (a built-in asset name) or ``ply`` (path to a 3DGS PLY); ``seed`` of the
    procedural geometry or of the PLY subsampling; ``opacity_threshold``; ``rotations``
    ((axis, degrees) pairs, applied in order); ``crop`` (a :class:`Box` in the rotated
    source frame, or None); ``static_boxes`` (support Gaussians rendered, not simulated;
    normalized domain); ``n_gaussians`` (from the profile; None keeps every PLY Gaussian).
    """

    procedural: str | None = None
    ply: Path | None = None
    seed: int = 0
    opacity_threshold: float = 0.0
    rotations: tuple[tuple[str, float], ...] = ()
    crop: Box | None = None
    static_boxes: tuple[Box, ...] = ()
    n_gaussians: int | None = None


@dataclass(frozen=True)
class FillSettings:
    """Interior fill (see :func:`knockgs_core.assets.fill_interior`); ``resolution`` comes
    from the profile. ``volumes``: the particles' rest-volume rule (``cell_share``,
    ``enclosed`` or ``wall``; docs/assets.md); ``wall_thickness`` [m]: the wall of the
    ``wall`` rule; ``passenger_boxes`` (normalized domain): parts of the body thinner than any
    fill cell (a vase's lip), whose particles the ``enclosed`` rule lets ride on the body with
    no share of it, and which the body's level set leaves out (:mod:`knockgs_core.assets._volumes`).
    A contract whose fill is off keeps them for its solid body (:func:`with_body`).
    ``body_resolution``: the cells per axis of the grid on which the ``enclosed`` rule measures
    the body (None: the fill's own grid, which :func:`at_resolution` refines with the simulation
    grid); fixed, every level of a refinement study carries one body, the one the reference
    meshes (:func:`knockgs_core.assets.body_level_set` measures on it too)."""

    enabled: bool = False
    box: Box | None = None
    density_threshold: float = 0.3
    max_particles_per_cell: int = 4
    seed: int = 0
    resolution: int = 128
    volumes: str = "cell_share"
    wall_thickness: float | None = None
    passenger_boxes: tuple[Box, ...] = ()
    body_resolution: int | None = None


@dataclass(frozen=True)
class Profile:
    """What a resolution profile may change."""

    n_gaussians: int | None
    n_grid: int
    fill_resolution: int
    dt: float


def check_volume_rule(fill: FillSettings, source) -> None:
    """Refuse, in one line naming the field, a volume rule its other fill settings do not
    support: ``enclosed`` measures the body on the fill grid (``enabled: true``); ``wall`` is a
    thin wall with no interior fill and needs its ``wall_thickness`` > 0 [m], which no other
    rule reads."""
    from .assets._volumes import VOLUME_RULES

    if fill.volumes not in VOLUME_RULES:
        raise InputError(source, "fill.volumes", f"must be one of {', '.join(VOLUME_RULES)}, got {fill.volumes!r}")
    if fill.volumes == "enclosed" and not fill.enabled:
        raise InputError(source, "fill.volumes", "enclosed measures the body on the fill grid: needs fill.enabled: true")
    if fill.volumes == "wall":
        if fill.enabled:
            raise InputError(source, "fill.volumes", "wall is a thin wall with no interior fill: needs fill.enabled: false")
        t = fill.wall_thickness
        if t is None or not (math.isfinite(t) and t > 0):
            raise InputError(source, "fill.wall_thickness", f"the wall rule needs a thickness > 0 [m], got {t!r}")
    elif fill.wall_thickness is not None:
        raise InputError(source, "fill.wall_thickness", f"is read by volumes: wall only (volumes is {fill.volumes})")
    b = fill.body_resolution
    if b is not None and (isinstance(b, bool) or not isinstance(b, int) or not 2 <= b <= 1024):
        raise InputError(source, "fill.body_resolution", f"must be a whole number of cells in [2, 1024], got {b!r}")
    for name in ("passenger_boxes", "body_resolution"):
        if getattr(fill, name) not in ((), None) and fill.enabled and fill.volumes != "enclosed":
            raise InputError(source, f"fill.{name}",
                             f"is read by volumes: enclosed only (volumes is {fill.volumes} with the fill on)")


# --------------------------------------------------------------------------- CFL

def _p_wave_speed(mat: Material, theta) -> float:
    return Material(mat.E * theta[0], mat.nu, mat.rho * theta[1]).p_wave_speed()


def _frame_gcd(frame_dts: Sequence[float]) -> Fraction:
    g = Fraction(0)
    for f in frame_dts:
        q = Fraction(f).limit_denominator(10 ** 9)
        g = q if g == 0 else Fraction(math.gcd(g.numerator * q.denominator, q.numerator * g.denominator),
                                      g.denominator * q.denominator)
    return g


def cfl_dt(materials: Mapping[str, Material] | Sequence[Material], *, n_grid: int,
           grid_lim: float = 2.0, theta_max: tuple[float, float] = THETA_STIFFEST,
           safety: float = 0.3, frame_dts: Sequence[float] = ()) -> float:
    """Largest stable substep ``safety * dx / c_p`` [s] for the fastest p-wave speed over
    ``materials`` at ``theta_max`` (E scaled by ``theta_max[0]``, rho by ``theta_max[1]``).

    With ``frame_dts``, the largest dt below that bound that divides every export
    interval exactly: ``g / ceil(g / dt_max)`` with ``g`` their greatest common divisor.
    """
    mats = list(materials.values()) if isinstance(materials, Mapping) else list(materials)
    c = max(_p_wave_speed(m, theta_max) for m in mats)
    dt_max = safety * (grid_lim / n_grid) / c
    if not frame_dts:
        return dt_max
    g = _frame_gcd(frame_dts)
    return float(g / math.ceil(g / Fraction(dt_max)))


# --------------------------------------------------------------------------- contract

@dataclass(frozen=True, eq=False)
class ObjectContract:
    """One object's fixed simulator contract at one resolution profile.

    ``probes`` hold the nominal forces from the file; :meth:`resolve_probes` (used by
    :func:`knockgs_core.assets.build_asset`, which stores the result as
    ``BuiltAsset.probes``) applies ``selected_reference`` and ``match_total_force`` against
    the built particles (``probe_selected_reference``: probe name -> the particles its box
    selects at the paper profile). ``hash`` is the sha256 of the canonical JSON of :meth:`to_dict`. Variants for
    experiments (another fill seed, grid, ...) are made with :func:`dataclasses.replace`.
    """

    name: str
    profile: str
    source: Path
    description: str
    asset: AssetSettings
    fill: FillSettings
    sim: SimParams
    materials: dict[str, Material]
    regions: dict[str, tuple[Box, ...]]
    probes: dict[str, Probe]
    probe_force_match: dict[str, str]
    roles: dict[str, Any]
    probe_reference_particles: int
    camera: dict[str, Any]
    candidates_path: Path
    targets_path: Path
    profiles: dict[str, Profile]
    probe_selected_reference: dict[str, int] = field(default_factory=dict)

    @cached_property
    def hash(self) -> str:
        """sha256 of the canonical JSON of :meth:`to_dict` (recomputed for a copy made
        with :func:`dataclasses.replace`, so a changed contract never keeps a stale hash)."""
        return _canonical_hash(self.to_dict())

    # ---- derived views
    @property
    def region_names(self) -> tuple[str, ...]:
        """``("base", *regions)``: the region index order of particles."""
        return ("base", *self.regions)

    @property
    def calibration_probe(self) -> Probe:
        return self.probes[self.roles["calibration"]]

    def cfl_dt(self, *, safety: float = 0.3, theta_max=THETA_STIFFEST) -> float:
        """:func:`cfl_dt` for this contract's materials, grid and probe export intervals."""
        return cfl_dt(self.materials, n_grid=self.sim.n_grid, grid_lim=self.sim.grid_lim,
                      theta_max=theta_max, safety=safety,
                      frame_dts=[p.export.frame_dt for p in self.probes.values()])

    def assign_regions(self, positions) -> np.ndarray:
        """Region index [N] int32 of normalized-domain ``positions``: the first region
        (in file order) with a box containing the point, else 0 (base)."""
        pos = np.asarray(positions, dtype=np.float64)
        region = np.zeros(len(pos), dtype=np.int32)
        free = np.ones(len(pos), dtype=bool)
        for k, boxes in enumerate(self.regions.values(), start=1):
            inside = np.zeros(len(pos), dtype=bool)
            for b in boxes:
                inside |= b.contains(pos)
            hit = inside & free
            region[hit] = k
            free &= ~hit
        return region

    def particle_materials(self, particles, theta=(1.0, 1.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-particle ``(E, nu, rho)`` float32 arrays of length N; E and rho of every
        region are multiplied by ``theta = (s_E, s_rho)``."""
        s_e, s_rho = (float(t) for t in theta)
        if not (s_e > 0 and s_rho > 0 and math.isfinite(s_e) and math.isfinite(s_rho)):
            raise InputError(self.source, "theta", f"scales must be finite and > 0, got {theta!r}")
        names = tuple(particles.region_names)
        table = []
        for nm in names:
            if nm not in self.materials:
                raise InputError(self.source, "materials",
                                 f"particles use region {nm!r}, which has no material")
            m = self.materials[nm]
            table.append((m.E * s_e, m.nu, m.rho * s_rho))
        t = np.asarray(table, dtype=np.float64)[np.asarray(particles.region)]
        return t[:, 0].astype(np.float32), t[:, 1].astype(np.float32), t[:, 2].astype(np.float32)

    def probe_selection(self, probe: Probe | str, positions) -> np.ndarray:
        """[N] bool: particles a probe acts on (all of them for a global probe)."""
        p = self.probes[probe] if isinstance(probe, str) else probe
        pos = np.asarray(positions)
        return np.ones(len(pos), dtype=bool) if p.box is None else p.box.contains(pos)

    def resolve_probes(self, particles) -> dict[str, Probe]:
        """Probes checked against built ``particles`` (:class:`~knockgs_core.assets.ParticleSet`).

        A box that selects no particle raises :class:`InputError`. The simulator multiplies
        every per-particle force by ``probe_reference_particles / N`` (N: all particles), so a
        global probe's total force is ``|f| * probe_reference_particles`` at every profile. A box
        probe with ``selected_reference: S_ref`` (the particles its box selects at the paper
        profile) is rescaled by ``(S_ref / n) (N / probe_reference_particles)`` (n: the particles
        it selects here), so its total force is ``|f| * S_ref`` at every profile (without it the
        total, ``|f| * probe_reference_particles * n / N``, follows how the profile samples the
        box). A probe with ``match_total_force: REF`` keeps its direction and gets the magnitude
        ``|f_REF| * n_REF / n_self`` of REF's resolved force, so both deliver the same total
        force and impulse.
        """
        counts = {}
        for name, p in self.probes.items():
            n = int(np.count_nonzero(self.probe_selection(p, particles.positions)))
            if n == 0:
                raise InputError(self.source, f"probes.{name}.box",
                                 f"selects no particles (box {p.box.center} +- {p.box.half_size}, "
                                 f"{len(particles)} particles)")
            counts[name] = n
        out = dict(self.probes)
        n_all = len(particles.positions)
        for name, s_ref in self.probe_selected_reference.items():
            factor = float(s_ref) / counts[name] * n_all / float(self.probe_reference_particles)
            out[name] = replace(self.probes[name], force=tuple(float(x) * factor for x in self.probes[name].force))
        for name, ref in self.probe_force_match.items():
            f = np.asarray(self.probes[name].force, dtype=np.float64)
            mag = np.linalg.norm(out[ref].force) * counts[ref] / counts[name]
            out[name] = replace(self.probes[name],
                                force=tuple(float(x) for x in f / np.linalg.norm(f) * mag))
        return out

    def load_candidates(self):
        return load_candidates(self.candidates_path)

    def load_targets(self, split: str = "main"):
        return load_targets(split, self.targets_path)

    def to_dict(self) -> dict:
        """The resolved contract (defaults filled, this profile only) as JSON-able data;
        a procedural asset adds its generator version."""
        d = {
            "name": self.name, "profile": self.profile, "description": self.description,
            "asset": _asset_dict(self.asset), "fill": _fill_dict(self.fill), "sim": _sim_dict(self.sim),
            "materials": json_safe(self.materials),
            "regions": {k: json_safe(v) for k, v in self.regions.items()},
            "probes": json_safe(self.probes), "probe_force_match": dict(self.probe_force_match),
            **({"probe_selected_reference": dict(self.probe_selected_reference)} if self.probe_selected_reference else {}),
            "roles": json_safe(self.roles), "probe_reference_particles": self.probe_reference_particles,
            "camera": json_safe(self.camera),
            "candidates": self.candidates_path.name, "targets": self.targets_path.name,
        }
        if self.asset.procedural is not None:
            from .assets._procedural import GENERATOR_VERSION

            d["asset"]["generator_version"] = GENERATOR_VERSION
        return d


def _asset_dict(asset: AssetSettings) -> dict:
    """``json_safe(asset)`` with the PLY path reduced to its file name (the hash of a
    contract does not depend on where the project lives)."""
    d = json_safe(asset)
    if asset.ply is not None:
        d["ply"] = asset.ply.name
    return d


def _fill_dict(fill: FillSettings) -> dict:
    """``json_safe(fill)`` without the volume rule's keys where they keep their defaults, so a
    contract that does not use them keeps the hash it had before they existed."""
    d = json_safe(fill)
    if fill.volumes != "enclosed" or not fill.passenger_boxes:
        del d["passenger_boxes"]
    if fill.volumes != "enclosed" or fill.body_resolution is None:
        del d["body_resolution"]
    if d["volumes"] == "cell_share" and d["wall_thickness"] is None:
        del d["volumes"], d["wall_thickness"]
    return d


def _sim_dict(sim: SimParams) -> dict:
    """``json_safe(sim)`` with each boundary condition tagged by its contract ``type``."""
    d = json_safe(sim)
    d["boundaries"] = [{**json_safe(b), "type": _BOUNDARY_TYPES_INV[type(b)]} for b in sim.boundaries]
    return d


def _canonical_hash(d: dict) -> str:
    text = json.dumps(d, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


# --------------------------------------------------------------------------- locating files

def at_resolution(contract: ObjectContract, n_grid: int) -> ObjectContract:
    """``contract`` on a grid of ``n_grid`` cells per axis, its fill resolution scaled by
    ``n_grid / contract.sim.n_grid`` (rounded) and the substep by the contracts' rule
    (:meth:`ObjectContract.cfl_dt`). Gaussians, materials and probes unchanged; its
    :attr:`~ObjectContract.hash` is the new grid's (files made at another grid are refused)."""
    if isinstance(n_grid, bool) or int(n_grid) != n_grid or int(n_grid) < 8:
        raise InputError(contract.source, "sim.n_grid", f"a grid of at least 8 cells per axis, got {n_grid!r}")
    n = int(n_grid)
    factor = n / contract.sim.n_grid
    fill = replace(contract.fill, resolution=max(2, int(round(contract.fill.resolution * factor))))
    out = replace(contract, sim=replace(contract.sim, n_grid=n), fill=fill)
    return replace(out, sim=replace(out.sim, dt=float(out.cfl_dt())))


def with_body(contract: ObjectContract, *, volumes: str | None = None, solid: bool = False, seed: int = 11) -> ObjectContract:
    """``contract`` with its body stated: the particles' rest-volume rule ``volumes``
    (``fill.volumes``: ``cell_share``, ``enclosed``, ``wall``; None: the contract's own) and,
    with ``solid``, the inside of its closed Gaussian surface filled (PhysGaussian's fill over
    the whole domain, ``seed``; ``enclosed`` volumes unless ``volumes`` says otherwise): the
    body a closed surface bounds, whatever its contract's fill. The fill's ``passenger_boxes``
    and ``body_resolution`` stay where the rule that reads them (``enclosed``) is chosen, and go
    otherwise. Its hash is the new body's."""
    fill = contract.fill
    if solid:
        lim = float(contract.sim.grid_lim) / 2.0
        fill = replace(fill, enabled=True, box=Box((lim, lim, lim), (lim, lim, lim)), seed=int(seed),
                       volumes=volumes or "enclosed")
    elif volumes is not None:
        fill = replace(fill, volumes=volumes)
    if fill.volumes != "enclosed":
        fill = replace(fill, passenger_boxes=(), body_resolution=None)
    out = replace(contract, fill=fill)
    check_volume_rule(out.fill, contract.source)
    return out


def find_config_dir(config_dir: str | os.PathLike | None = None) -> Path:
    """The configuration directory (see the module docstring for the search order)."""
    if config_dir is not None:
        p = Path(config_dir)
        if not p.is_dir():
            raise InputError(p, "config_dir", "is not a directory")
        return p.resolve()
    env = os.environ.get(_ENV)
    if env:
        p = Path(env)
        if not p.is_dir():
            raise InputError(p, _ENV, "is not a directory")
        return p.resolve()
    here = Path.cwd().resolve()
    for d in (here, *here.parents):
        if (d / "config" / "objects").is_dir():
            return d / "config"
    pkg_root = Path(__file__).resolve().parents[2] / "config"
    if (pkg_root / "objects").is_dir():
        return pkg_root
    raise InputError(here, "config_dir",
                     f"no config/objects folder in the working directory or above (contracts are looked up "
                     f"by name there); give the contract as a path, pass config_dir or set {_ENV}")


def schema_path() -> Path:
    """The object-contract JSON Schema shipped with the package (``knockgs_core/schemas``)."""
    from importlib.resources import as_file, files

    resource = files("knockgs_core").joinpath("schemas", "object.schema.yaml")
    with as_file(resource) as p:  # a real file for a normal (unzipped) install
        if not Path(p).is_file():
            raise InputError(p, "schema", "not found: the knockgs package is incomplete (reinstall it)")
        return Path(p)


def list_objects(config_dir: str | os.PathLike | None = None) -> list[str]:
    """Names of the contracts in ``config/objects``."""
    return sorted(p.stem for p in (find_config_dir(config_dir) / "objects").glob("*.yaml"))


# --------------------------------------------------------------------------- YAML and schema

def _yaml_loader():
    import yaml

    class Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # libyaml when available
        """SafeLoader that rejects duplicate keys and reads 1e-4 as a float (YAML 1.2)."""

    def construct_mapping(loader, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = loader.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r}", key_node.start_mark)
            seen.add(key)
        return loader.construct_mapping(node, deep=deep)

    Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, construct_mapping)
    Loader.add_implicit_resolver(
        "tag:yaml.org,2002:float",
        re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                    |[-+]?\.(?:inf|Inf|INF)
                    |\.(?:nan|NaN|NAN))$""", re.X),
        list("-+0123456789."))
    return Loader


#: deepest nesting of mappings and lists accepted in a YAML file (a contract needs about 6)
_MAX_YAML_DEPTH = 64


def _read_yaml(path: Path) -> Any:
    """The YAML document of ``path``, read with the strict loader of :func:`_yaml_loader`.

    Aliases (``*name``) are refused while the text is parsed, before any document is
    built, so a small file cannot expand into a huge one (an "alias bomb"); so is nesting
    deeper than ``_MAX_YAML_DEPTH`` (which would exhaust the recursion limit). A file that
    is not UTF-8 text, a folder or an unreadable file are refused naming the file.
    """
    import yaml

    from .io import input_problem

    problem = input_problem(path, kind="yaml")  # a FIFO would block the read, a device never end it
    if problem is not None:
        raise InputError(path, "file", problem)
    try:
        text = path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise InputError(path, "file", "does not exist") from None
    except IsADirectoryError:
        raise InputError(path, "file", "is a folder, not a YAML file") from None
    except OSError as exc:
        raise InputError(path, "file", f"cannot be read ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise InputError(path, "file", f"not UTF-8 text (a binary file?): byte {exc.start}") from None
    loader = _yaml_loader()
    depth = 0
    try:
        for event in yaml.parse(text, Loader=loader):
            line = event.start_mark.line + 1 if event.start_mark is not None else "?"
            if isinstance(event, yaml.AliasEvent):
                raise InputError(path, "yaml", f"line {line}: aliases (*{event.anchor}) are not allowed")
            if isinstance(event, yaml.CollectionStartEvent):
                depth += 1
                if depth > _MAX_YAML_DEPTH:
                    raise InputError(path, "yaml", f"line {line}: nested deeper than {_MAX_YAML_DEPTH} levels")
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
        return yaml.load(text, Loader=loader)
    except yaml.YAMLError as exc:
        raise InputError(path, "yaml", f"not valid YAML: {exc}") from None


def read_yaml(path: str | os.PathLike) -> Any:
    """A YAML file read as strictly as a contract (:func:`_read_yaml`: duplicate keys, aliases and
    deep nesting refused, the path checked first as an input), for the workflow's config files;
    errors are :class:`InputError` naming the file."""
    return _read_yaml(Path(path))


def _check_finite(data: Any, path: Path, where: str = "") -> None:
    """Every number of a contract is finite (infinity is written ``null`` where allowed)."""
    if isinstance(data, dict):
        for k, v in data.items():
            _check_finite(v, path, f"{where}.{k}" if where else str(k))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            _check_finite(v, path, f"{where}[{i}]")
    elif isinstance(data, float) and not math.isfinite(data):
        raise InputError(path, where or "(top level)", f"{data} is not a finite number")


#: resource-sized fields: field -> (largest value accepted, bytes one unit of the field implies,
#: what that unit is). A grid of n cells a side has n^3 nodes of at least 16 bytes (mass and
#: momentum, float32); a fill grid n^3 cells of at least 4; a Gaussian about 240 bytes (59 float32
#: attributes); an exported frame 12 bytes a particle (positions) and 36 more with F. The bounds
#: leave the paper profile (n_grid 120, fill 128, 1.3 million Gaussians, 121 frames) far inside.
RESOURCE_LIMITS = {
    "n_grid": (1024, 16, "grid node", 3),
    "fill_resolution": (1024, 4, "fill cell", 3),
    "n_gaussians": (100_000_000, 240, "Gaussian", 1),
    "n_frames": (10_000, 48, "frame of one particle", 1),
}


def _implied(field: str, value: int) -> str:
    limit, per, unit, power = RESOURCE_LIMITS[field]
    units = value ** power
    return (f"{value} means {units:.3g} {unit}s, at least {units * per / 1e9:.3g} GB; at most {limit} "
            f"({limit ** power * per / 1e9:.3g} GB) is accepted")


def _check_resources(data: dict, path: Path) -> None:
    """Refuse resource-sized fields (grid and fill resolution, Gaussian and frame counts) whose
    implied memory no machine holds, before anything is allocated (the schema's type checks come
    later: only integers are judged here)."""
    def judge(field, where, v):
        if isinstance(v, int) and not isinstance(v, bool) and v > RESOURCE_LIMITS[field][0]:
            raise InputError(path, where, _implied(field, v))

    for name, prof in (data.get("profiles") or {}).items() if isinstance(data.get("profiles"), dict) else ():
        if isinstance(prof, dict):
            for field in ("n_grid", "fill_resolution", "n_gaussians"):
                judge(field, f"profiles.{name}.{field}", prof.get(field))
    probes = data.get("probes")
    for name, probe in (probes.items() if isinstance(probes, dict) else ()):
        export = probe.get("export") if isinstance(probe, dict) else None
        if isinstance(export, dict):
            judge("n_frames", f"probes.{name}.export.n_frames", export.get("n_frames"))


def _check_materials(data: dict, path: Path) -> None:
    """E > 0, rho > 0 and -1 < nu < 0.5, finite (the schema's bounds let NaN through)."""
    materials = data.get("materials")
    for name, m in (materials.items() if isinstance(materials, dict) else ()):
        if not isinstance(m, dict):
            continue
        for key, ok, rule in (("E", lambda v: v > 0, "> 0"), ("rho", lambda v: v > 0, "> 0"),
                              ("nu", lambda v: -1.0 < v < 0.5, "in (-1, 0.5)")):
            v = m.get(key)
            if isinstance(v, (int, float)) and not isinstance(v, bool) and not (math.isfinite(v) and ok(v)):
                raise InputError(path, f"materials.{name}.{key}", f"{v} is not a finite number {rule}")


@lru_cache(maxsize=4)
def _validator(path: str):
    from jsonschema import Draft202012Validator

    # the schema itself is checked against the metaschema by the test suite, not per process
    return Draft202012Validator(_read_yaml(Path(path)))


def _field_of(error) -> str:
    parts = []
    for p in error.absolute_path:
        if isinstance(p, int):
            parts.append(f"[{p}]")
        else:
            parts.append(("." if parts else "") + str(p))
    base = "".join(parts)

    def join(key):
        return f"{base}.{key}" if base else str(key)

    if error.validator == "additionalProperties" and isinstance(error.instance, dict):
        allowed = set(error.schema.get("properties", {}))
        extra = sorted(k for k in error.instance if k not in allowed)
        if extra:
            return join(extra[0])
    if error.validator == "required":
        m = re.match(r"'([^']+)' is a required property", error.message)
        if m:
            return join(m.group(1))
    return base or "(top level)"


def _validate(data: Any, path: Path, schema: Path) -> None:
    from jsonschema.exceptions import best_match

    if not isinstance(data, dict):
        raise InputError(path, "(top level)", "the contract must be a YAML mapping")
    validator = _validator(str(schema))
    errors = list(validator.iter_errors(data))
    if not errors:
        return
    err = best_match(errors)
    # descend into oneOf / if-then errors for the most specific message
    while err.context:
        err = best_match(err.context)
    fld = _field_of(err)
    msg = err.message
    if err.validator == "additionalProperties":
        msg = f"unknown key ({msg})"
    if fld == "asset" and err.validator in ("oneOf", "not", "required"):
        msg = "exactly one of 'procedural' and 'ply' must be given"
    raise InputError(path, fld, msg)


# --------------------------------------------------------------------------- building

def _box(d: Mapping | None) -> Box | None:
    if d is None:
        return None
    return Box(tuple(float(x) for x in d["center"]), tuple(float(x) for x in d["half_size"]))


def _vec(v) -> tuple[float, float, float]:
    return tuple(float(x) for x in v)


def _kwargs(d: Mapping, names: Sequence[str]) -> dict:
    return {k: d[k] for k in names if k in d}


def _end_time(d: Mapping) -> dict:
    if "end_time" in d:
        return {"end_time": math.inf if d["end_time"] is None else float(d["end_time"])}
    return {}


def _boundary(d: Mapping, i: int, path: Path):
    kind = d["type"]
    if kind == "domain_walls":
        return DomainWalls(**_kwargs(d, ("padding", "mode")))
    cls = FixedCuboid if kind == "fixed_cuboid" else ParticleTranslation
    kw = _kwargs(d, ("start_time",))
    if d.get("friction") is not None:
        if "friction" not in {f.name for f in fields(cls)}:
            raise InputError(path, f"sim.boundaries[{i}].friction",
                             "friction is not supported by this simulator version")
        kw["friction"] = float(d["friction"])
    if "velocity" in d:
        kw["velocity"] = _vec(d["velocity"])
    return cls(box=_box(d["box"]), **kw, **_end_time(d))


_BOUNDARY_TYPES_INV = {DomainWalls: "domain_walls", FixedCuboid: "fixed_cuboid",
                       ParticleTranslation: "particle_translation"}


def _probe(name: str, d: Mapping) -> Probe:
    kw = _kwargs(d, ("start_time", "n_steps", "dt_ref"))
    if "export" in d:
        kw["export"] = ExportSchedule(float(d["export"]["frame_dt"]), int(d["export"]["n_frames"]))
    return Probe(name=name, force=_vec(d["force"]), box=_box(d.get("box")), **kw)


def _resolve_path(name_or_path: str | os.PathLike, config_dir) -> Path:
    s = str(name_or_path)
    if s.endswith((".yaml", ".yml")) or os.sep in s or "/" in s:
        return Path(s).resolve()
    cfg = find_config_dir(config_dir)
    p = cfg / "objects" / f"{s}.yaml"
    if not p.is_file():
        raise InputError(cfg / "objects", "name",
                         f"no contract {s!r}; available: {', '.join(list_objects(cfg)) or 'none'}")
    return p


def load_contract(name_or_path: str | os.PathLike, profile: str = "default", *,
                  config_dir: str | os.PathLike | None = None, n_grid: int | None = None) -> ObjectContract:
    """Load, validate and resolve an object contract at one profile.

    ``name_or_path``: an object name (``config/objects/NAME.yaml`` under the configuration
    directory, see :func:`find_config_dir`) or a path to a YAML file. ``profile`` in the
    file's ``profiles`` (``ci``, ``default``, ``paper``). ``n_grid``: the profile's contract on
    that many cells per axis (:func:`at_resolution`); None: the profile's grid. Unknown keys,
    wrong types and inconsistent references raise :class:`InputError` naming the file and the
    field.
    """
    path = _resolve_path(name_or_path, config_dir)
    data = _read_yaml(path)
    if isinstance(data, dict):
        _check_materials(data, path)
        _check_finite(data, path)
        _check_resources(data, path)
    _validate(data, path, schema_path())
    contract = _build(data, path, _tables_dir(path, config_dir), profile)
    return contract if n_grid is None else at_resolution(contract, n_grid)


def _tables_dir(path: Path, config_dir) -> Path:
    """Where a contract's candidate and target tables live: ``config_dir`` when given, the
    configuration directory of a contract in ``.../objects/``, else the project's
    configuration directory if there is one, else the contract's own folder."""
    if config_dir is not None:
        return find_config_dir(config_dir)
    if path.parent.name == "objects":
        return path.parent.parent
    try:
        return find_config_dir()
    except InputError:
        return path.parent


def _build(data: dict, path: Path, cfg: Path, profile: str) -> ObjectContract:
    # ~100 lines on purpose: one validated field after another, in the schema's order, each
    # refusal naming the file and the field.
    if profile not in data["profiles"]:
        raise InputError(path, "profile", f"unknown profile {profile!r}; the file defines "
                         f"{', '.join(data['profiles'])}")
    profiles = {k: Profile(v["n_gaussians"], int(v["n_grid"]), int(v["fill_resolution"]), float(v["dt"]))
                for k, v in data["profiles"].items()}
    prof = profiles[profile]

    a = data["asset"]
    ply = None
    if "ply" in a:
        ply = Path(a["ply"]) if os.path.isabs(a["ply"]) else (path.parent / a["ply"]).resolve()
        problem = input_problem(ply)
        if problem is not None:
            raise InputError(path, "asset.ply", f"file {ply} {problem}")
    asset = AssetSettings(
        procedural=a.get("procedural"), ply=ply,
        **_kwargs(a, ("seed",)),
        **({"opacity_threshold": float(a["opacity_threshold"])} if "opacity_threshold" in a else {}),
        rotations=tuple((r["axis"], float(r["degrees"])) for r in a.get("rotations", [])),
        crop=_box(a.get("crop")),
        static_boxes=tuple(_box(b) for b in a.get("static_boxes", [])),
        n_gaussians=prof.n_gaussians)
    if asset.procedural is not None and asset.n_gaussians is None:
        raise InputError(path, f"profiles.{profile}.n_gaussians", "a procedural asset needs a count")

    f = data.get("fill", {})
    fill = FillSettings(**_kwargs(f, ("enabled", "density_threshold", "max_particles_per_cell", "seed", "volumes")),
                        box=_box(f.get("box")), resolution=prof.fill_resolution,
                        wall_thickness=None if f.get("wall_thickness") is None else float(f["wall_thickness"]),
                        passenger_boxes=tuple(_box(b) for b in f.get("passenger_boxes", [])),
                        body_resolution=None if f.get("body_resolution") is None else int(f["body_resolution"]))
    if fill.enabled and fill.box is None:
        raise InputError(path, "fill.box", "required when fill.enabled is true")
    check_volume_rule(fill, path)

    s = data["sim"]
    sim_kw = _kwargs(s, ("grid_lim", "grid_v_damping_scale", "cfl_limit", "guard_every", "transfer"))
    if s.get("pic_relaxation_time") is not None:
        sim_kw["pic_relaxation_time"] = float(s["pic_relaxation_time"])
    if "gravity" in s:
        sim_kw["gravity"] = _vec(s["gravity"])
    if "boundaries" in s:
        sim_kw["boundaries"] = tuple(_boundary(b, i, path) for i, b in enumerate(s["boundaries"]))
    sim = SimParams(n_grid=prof.n_grid, dt=prof.dt, **sim_kw)

    materials = {k: Material(float(v["E"]), float(v["nu"]), float(v["rho"]))
                 for k, v in data["materials"].items()}
    regions = {k: tuple(_box(b) for b in v) for k, v in data.get("regions", {}).items()}
    for k in regions:
        if k not in materials:
            raise InputError(path, f"regions.{k}", f"region {k!r} has no materials entry")
    for k in materials:
        if k != "base" and k not in regions:
            raise InputError(path, f"materials.{k}", f"material {k!r} has no regions entry")

    probes = {k: _probe(k, v) for k, v in data["probes"].items()}
    match = {}
    for k, v in data["probes"].items():
        ref = v.get("match_total_force")
        if ref is None:
            continue
        if ref not in probes or ref == k:
            raise InputError(path, f"probes.{k}.match_total_force", f"unknown probe {ref!r}")
        if probes[k].box is None or probes[ref].box is None:
            raise InputError(path, f"probes.{k}.match_total_force", "both probes need a contact box")
        if not np.linalg.norm(probes[k].force) > 0:
            raise InputError(path, f"probes.{k}.force", "needs a direction (non-zero force)")
        match[k] = ref
    selected_reference = {}
    for k, v in data["probes"].items():
        if v.get("selected_reference") is None:
            continue
        if probes[k].box is None:
            raise InputError(path, f"probes.{k}.selected_reference", "needs a contact box (a global probe's reference "
                             "is probe_reference_particles)")
        if k in match:
            raise InputError(path, f"probes.{k}.selected_reference", "a probe with match_total_force takes its total "
                             "force from the matched probe")
        selected_reference[k] = int(v["selected_reference"])

    r = data["roles"]
    roles = {"calibration": r["calibration"], "heldout": list(r.get("heldout", [])),
             "diagnostic": list(r.get("diagnostic", []))}
    for key, names in (("calibration", [roles["calibration"]]), ("heldout", roles["heldout"]),
                       ("diagnostic", roles["diagnostic"])):
        for i, nm in enumerate(names):
            if nm not in probes:
                where = f"roles.{key}" if key == "calibration" else f"roles.{key}[{i}]"
                raise InputError(path, where, f"unknown probe {nm!r}")

    cam = data["camera"]
    camera = {"width": int(cam["width"]), "height": int(cam["height"]), "fov_deg": float(cam["fov_deg"]),
              "eye": _vec(cam["eye"]), "target": _vec(cam["target"]), "up": _vec(cam["up"])}
    if np.allclose(camera["eye"], camera["target"]):
        raise InputError(path, "camera.target", "coincides with camera.eye")

    _check_profile_steps(path, profiles, probes, materials, float(s.get("grid_lim", SimParams.grid_lim)))

    contract = ObjectContract(
        name=data["name"], profile=profile, source=path, description=data.get("description", ""),
        asset=asset, fill=fill, sim=sim, materials=materials, regions=regions, probes=probes,
        probe_force_match=match, roles=roles, probe_selected_reference=selected_reference,
        probe_reference_particles=int(data["probe_reference_particles"]), camera=camera,
        candidates_path=cfg / data.get("candidates", "candidates.csv"),
        targets_path=cfg / data.get("targets", "targets.csv"), profiles=profiles)
    if contract.name != path.stem:
        raise InputError(path, "name", f"{contract.name!r} differs from the file name {path.stem!r}")
    return contract


def _check_profile_steps(path: Path, profiles: Mapping[str, Profile], probes: Mapping[str, Probe],
                         materials: Mapping[str, Material], grid_lim: float) -> None:
    """Every profile's dt divides the export intervals and respects the CFL bound."""
    frame_dts = [p.export.frame_dt for p in probes.values()]
    for pname, pr in profiles.items():
        for fdt in frame_dts:
            k = fdt / pr.dt
            if abs(k - round(k)) > 1e-6 * max(1.0, k):
                raise InputError(path, f"profiles.{pname}.dt",
                                 f"{pr.dt} does not divide the export interval {fdt}")
        limit = cfl_dt(materials, n_grid=pr.n_grid, grid_lim=grid_lim)
        if pr.dt > limit * (1 + 1e-9):
            raise InputError(path, f"profiles.{pname}.dt",
                             f"{pr.dt} exceeds the CFL bound 0.3 dx / c_p = {limit:.4g} s "
                             f"(stiffest candidate {THETA_STIFFEST})")


# --------------------------------------------------------------------------- candidates / targets

def _read_table(path: Path, columns: Sequence[str]):
    import pandas as pd

    problem = input_problem(path)
    if problem is not None:
        raise InputError(path, "file", problem)
    try:
        df = pd.read_csv(path, comment="#")
    except FileNotFoundError:
        raise InputError(path, "file", "does not exist") from None
    except Exception as exc:
        raise InputError(path, "file", f"not a readable CSV table ({exc})") from None
    for c in columns:
        if c not in df.columns:
            raise InputError(path, c, "column is missing")
    for c in ("E_scale", "density_scale"):
        v = pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=float)
        if not np.all(np.isfinite(v) & (v > 0)):
            raise InputError(path, c, "values must be finite numbers > 0")
        df[c] = v
    if df["case_name"].duplicated().any():
        raise InputError(path, "case_name", f"duplicate case {df['case_name'][df['case_name'].duplicated()].iloc[0]!r}")
    return df


def _default_table(name: str, path) -> Path:
    return Path(path) if path is not None else find_config_dir() / name


def load_candidates(path: str | os.PathLike | None = None):
    """Candidate table (``case_name, E_scale, density_scale``; 54 rows), default
    ``config/candidates.csv``; duplicate names or pairs raise :class:`InputError`."""
    path = _default_table("candidates.csv", path)
    df = _read_table(path, ("case_name", "E_scale", "density_scale"))
    if df.duplicated(["E_scale", "density_scale"]).any():
        raise InputError(path, "E_scale,density_scale", "duplicate parameter pair")
    return df[["case_name", "E_scale", "density_scale"]].reset_index(drop=True)


def load_targets(split: str = "main", path: str | os.PathLike | None = None):
    """Held-out targets of one ``split`` (``main`` = the paper's five), default
    ``config/targets.csv``; returns ``case_name, E_scale, density_scale``."""
    path = _default_table("targets.csv", path)
    df = _read_table(path, ("split", "case_name", "E_scale", "density_scale"))
    splits = list(dict.fromkeys(df["split"]))
    if split not in splits:
        raise InputError(path, "split", f"unknown split {split!r}; the file has {', '.join(splits)}")
    out = df[df["split"] == split][["case_name", "E_scale", "density_scale"]].reset_index(drop=True)
    dup = out.duplicated(["E_scale", "density_scale"])
    if dup.any():
        r = out[dup].iloc[0]
        raise InputError(path, "E_scale,density_scale", f"split {split!r}: target {r.case_name!r} repeats the "
                         f"parameter pair ({r.E_scale:g}, {r.density_scale:g}) of an earlier target")
    return out


def check_held_out(candidates_path: str | os.PathLike | None = None,
                   targets_path: str | os.PathLike | None = None) -> None:
    """Every target of every split held out from the candidates: no target has a candidate's
    parameter pair or case name (a target equal to a candidate would be found by looking it up
    in the library), and no two targets of a split share a pair (:func:`load_targets`). Run when
    the workflow's config is read, for every split, so that no table is built from a leaked
    target. Raises :class:`InputError` naming the targets file and the row."""
    candidates = load_candidates(candidates_path)
    path = _default_table("targets.csv", targets_path)
    table = _read_table(path, ("split", "case_name", "E_scale", "density_scale"))
    pairs = {(float(r.E_scale), float(r.density_scale)): r.case_name for r in candidates.itertuples(index=False)}
    names = set(candidates.case_name)
    for split in dict.fromkeys(table["split"]):
        for r in load_targets(split, path).itertuples(index=False):
            pair = (float(r.E_scale), float(r.density_scale))
            if pair in pairs:
                raise InputError(path, "E_scale,density_scale", f"split {split!r}: target {r.case_name!r} "
                                 f"({pair[0]:g}, {pair[1]:g}) is the candidate {pairs[pair]!r}: a held-out target "
                                 "must not be in the library")
            if r.case_name in names:
                raise InputError(path, "case_name", f"split {split!r}: target {r.case_name!r} has a candidate's name")
