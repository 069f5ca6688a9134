"""A first object contract for a splat file: ``knockgs asset init`` (private).

:func:`scaffold_contract` reads a splat (INRIA or SuperSplat compressed layout, with the
reading rules of :func:`~knockgs_core.assets.read_splat`) and chooses, by the rules below,
everything a contract needs; :func:`contract_text` writes the choices as a commented YAML
contract that :func:`~knockgs_core.contract.load_contract` accepts unchanged. Every rule is
a default to edit, not a measurement.

1. Opacity filter: Gaussians below ``opacity_threshold`` (default 0.05) are dropped.
2. Up axis (overridable): from the opacity-weighted covariance of the kept centres other
   than the floaters (rule 3), the
   long axis of an elongated body (``sqrt(l1 / l2) >= sqrt(l2 / l3)``, eigenvalues
   ``l1 >= l2 >= l3``) or else the short axis of a flat one; snapped to the nearest source
   axis when within 20 degrees; its sign follows the y-down convention of 3DGS training
   (COLMAP) and of SuperSplat scenes when its y component is at least 0.5 in magnitude,
   else points to +z. The horizontal long axis becomes x (snapped the same way).
3. Floaters: statistical outliers of the opacity-weighted centres, a centre whose mean
   distance to its 8 nearest kept neighbours exceeds the opacity-weighted mean of that
   distance by more than 3 weighted standard deviations. The crop box is the bounding box
   of the others, padded by their median neighbour distance; outliers outside it are
   removed (the contract's crop), those inside it stay.
4. Support: a fixed cuboid holding the lowest slab of the body, ``max(5 % of the height,
   1.5 ci grid cells)`` thick, over the slab's footprint padded by one ci cell, and
   reaching one ci cell below the body.
5. Probes: Probe A ``standard_x`` pushes every particle along -x (the horizontal long
   axis), Probe B ``standard_y`` along -y; one step of 0.1 ms, 31 frames at 20 ms. The
   force gives the body an initial velocity of 0.03 (normalized lengths per second) at
   the base material: ``|f| = 0.03 rho V / (N_ref * 1e-4 s)``, V the volume of the grid
   cells at the default profile that hold kept centres (an estimate of the body).
6. Camera: looks at the body's bounding-box centre from azimuth -60 degrees (from +x
   towards -y) and elevation 20 degrees, at the distance that fits the bounding sphere
   in the vertical field of view of 40 degrees (portrait for a tall body).
7. Material: E = 1e4 Pa, nu = 0.3, rho = 1000 kg/m^3 (a soft solid); the substep of each
   profile is the CFL bound's largest divisor of 20 ms of the form 20 ms / (2^a 5^b).
8. Fill: the interior fill over the body's bounding box padded by 0.05, density threshold
   0.3, 4 particles per cell.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from knockgs_core.errors import InputError

from ._ply import SplatRepairs, read_splat
from ._transform import preprocess, rotation_matrix

__all__ = ["Scaffold", "SourceSelection", "scaffold_contract", "contract_text", "parse_up", "source_selection"]

#: source axes: a chosen direction within this angle of one is snapped to it [degrees]
_SNAP_DEGREES = 20.0
#: neighbours of the floater rule
_NEIGHBOURS = 8
#: outlier rule: weighted mean + this many weighted standard deviations
_OUTLIER_SIGMAS = 3.0
#: the profiles of a scaffold: Gaussians kept by subsampling (None: all), grid, fill grid
_PROFILES = {"ci": (4000, 32, 32), "default": (16000, 48, 48), "paper": (None, 100, 128)}
_GRID_LIM = 2.0
_FRAME_DT = 0.02
_KICK = 0.03
_DT_REF = 1.0e-4
_BASE = {"E": 1.0e4, "nu": 0.3, "rho": 1000.0}


@dataclass(frozen=True)
class Scaffold:
    """The choices of :func:`scaffold_contract` for one splat file.

    ``counts``: Gaussians in the file, below the opacity threshold, floaters (statistical
    outliers), floaters outside the crop (removed), kept. ``repairs``: the reading rules'
    counts. ``data``: the contract as a dict (schema keys, normalized domain).
    ``notes``: one line per choice, written as comments into the contract.
    """

    name: str
    splat: Path
    layout: str
    repairs: SplatRepairs
    counts: dict
    up: tuple[float, float, float]
    up_rule: str
    data: dict
    notes: dict = field(default_factory=dict)


def parse_up(text: str, *, source: object = "--up") -> np.ndarray:
    """An up direction from ``x``, ``-y``, ``+z`` or three numbers ``a,b,c`` (unit [3] float64)."""
    t = str(text).strip().lower()
    axes = {"x": 0, "y": 1, "z": 2}
    if t.lstrip("+-") in axes and len(t) <= 2:
        v = np.zeros(3)
        v[axes[t.lstrip("+-")]] = -1.0 if t.startswith("-") else 1.0
        return v
    try:
        v = np.array([float(s) for s in t.split(",")], dtype=np.float64)
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or not np.linalg.norm(v) > 0:
        raise InputError(source, "up", f"expected x, -y, +z or three numbers a,b,c (not all zero), got {text!r}")
    return v / np.linalg.norm(v)


def _snap(d: np.ndarray) -> np.ndarray:
    """``d`` (unit) replaced by the nearest signed source axis when within the snap angle."""
    i = int(np.argmax(np.abs(d)))
    if abs(d[i]) >= math.cos(math.radians(_SNAP_DEGREES)):
        out = np.zeros(3)
        out[i] = math.copysign(1.0, d[i])
        return out
    return d


def _weighted_cov(x: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mu = (w[:, None] * x).sum(0) / w.sum()
    d = x - mu
    return mu, (w[:, None] * d).T @ d / w.sum()


def _up_axis(centres: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, str]:
    """Rule 2 of the module docstring: the up direction and a line saying why."""
    _, cov = _weighted_cov(centres, w)
    lam, vec = np.linalg.eigh(cov)  # ascending
    l3, l2, l1 = np.maximum(lam, 1e-30)
    elong, flat = math.sqrt(l1 / l2), math.sqrt(l2 / l3)
    if elong >= flat:
        d, why = vec[:, 2], f"the long axis of an elongated body (axis ratios {elong:.2f} long, {flat:.2f} flat)"
    else:
        d, why = vec[:, 0], f"the short axis of a flat body (axis ratios {elong:.2f} long, {flat:.2f} flat)"
    d = _snap(d / np.linalg.norm(d))
    if abs(d[1]) >= 0.5:
        d = d if d[1] < 0 else -d
        why += "; sign: y down (3DGS/COLMAP and SuperSplat convention)"
    else:
        d = d if d[2] >= 0 else -d
        why += "; sign: towards +z"
    return d, why


def _frame(up: np.ndarray, centres: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] whose rows are x (horizontal long axis), y and up (rule 2)."""
    up = up / np.linalg.norm(up)
    flat = centres - np.outer(centres @ up, up)
    _, cov = _weighted_cov(flat, w)
    lam, vec = np.linalg.eigh(cov)
    e1 = vec[:, 2] - (vec[:, 2] @ up) * up
    if not np.linalg.norm(e1) > 1e-9:  # a body without horizontal extent
        e1 = np.eye(3)[int(np.argmin(np.abs(up)))]
        e1 = e1 - (e1 @ up) * up
    e1 /= np.linalg.norm(e1)
    snapped = _snap(e1)
    if abs(snapped @ up) < 1e-9:
        e1 = snapped
    # of +-e1, the one nearest a positive source axis (fewest turns about z)
    if e1[int(np.argmax(np.abs(e1)))] < 0:
        e1 = -e1
    e2 = np.cross(up, e1)
    return np.stack([e1, e2, up])


def _rotations(r: np.ndarray) -> list[tuple[str, float]]:
    """Axis rotations (x, then y, then z; degrees rounded to 0.01) with product ``r``."""
    b = math.degrees(math.asin(max(-1.0, min(1.0, -r[2, 0]))))
    a = math.degrees(math.atan2(r[2, 1], r[2, 2]))
    c = math.degrees(math.atan2(r[1, 0], r[0, 0]))
    out = [(ax, round(deg, 2)) for ax, deg in (("x", a), ("y", b), ("z", c))]
    return [(ax, 0.0 if deg == 0 else deg) for ax, deg in out if abs(deg) >= 0.005]


def _floaters(centres: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    """Rule 3: outlier mask [N] and the median neighbour distance."""
    from scipy.spatial import cKDTree

    k = min(_NEIGHBOURS, len(centres) - 1)
    dist, _ = cKDTree(centres).query(centres, k=k + 1)
    d = dist[:, 1:].mean(axis=1)
    mean = float((w * d).sum() / w.sum())
    std = float(np.sqrt((w * (d - mean) ** 2).sum() / w.sum()))
    return d > mean + _OUTLIER_SIGMAS * std, float(np.median(d))


def _nice_dt(bound: float) -> float:
    """Largest ``20 ms / (2^a 5^b)`` not above ``bound`` [s]."""
    ks = sorted({2 ** a * 5 ** b for a in range(40) for b in range(20) if 2 ** a * 5 ** b < 1e12})
    for k in ks:
        if _FRAME_DT / k <= bound * (1 + 1e-12):
            return _FRAME_DT / k
    raise InputError("scaffold", "dt", f"no substep below {bound:g} s")


def _round(v, nd=4) -> list[float]:
    return [float(round(float(x), nd)) + 0.0 for x in np.ravel(v)]


def _box(lo, hi, nd=4) -> dict:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return {"center": _round(0.5 * (lo + hi), nd), "half_size": _round(0.5 * (hi - lo), nd)}


def scaffold_contract(splat: str | os.PathLike, contract_path: str | os.PathLike, *, up=None,
                      opacity_threshold: float = 0.05) -> Scaffold:
    """Choose a contract for ``splat`` to be written at ``contract_path`` (rules in the module
    docstring). ``up``: None (rule 2) or a direction (see :func:`parse_up`), in the splat's
    own frame. The contract's name is the file stem of ``contract_path``; its ``asset.ply``
    is the splat's path relative to the contract's folder.

    Raises :class:`InputError` naming the file and the field for what the rules cannot
    handle: a file of fewer than 100 Gaussians, an opacity threshold that removes all (or
    all but 99) of them, a body without extent along the up axis.
    """
    import re

    from knockgs_core.sim import Box, Material

    splat = Path(splat)
    contract_path = Path(contract_path)
    name = contract_path.stem
    if not re.fullmatch(r"[a-z][a-z0-9_]*", name) or contract_path.suffix not in (".yaml", ".yml"):
        raise InputError(contract_path, "name", "a contract file is NAME.yaml with NAME of lower-case letters, "
                         "digits and '_' starting with a letter (the contract's name is its file stem)")
    if not (0.0 <= float(opacity_threshold) < 1.0):
        raise InputError("--opacity-threshold", "opacity_threshold", f"must lie in [0, 1), got {opacity_threshold}")
    sf = read_splat(splat)
    gs = sf.gaussians
    if len(gs) < 100:
        raise InputError(splat, "vertex", f"holds {len(gs)} Gaussians; a contract needs at least 100")
    opaque = gs.opacities >= np.float32(opacity_threshold)
    n_opaque = int(opaque.sum())
    if n_opaque < 100:
        raise InputError(splat, "opacity", f"{len(gs) - n_opaque} of the {len(gs)} Gaussians have an opacity below "
                         f"{opacity_threshold} (max {float(gs.opacities.max()):.3g}); at least 100 must stay "
                         "(lower --opacity-threshold)")
    centres = gs.means.astype(np.float64)[opaque]
    w = gs.opacities.astype(np.float64)[opaque]
    outlier, spacing = _floaters(centres, w)  # distances: the same in any rotated frame
    if up is None:
        up_dir, up_rule = _up_axis(centres[~outlier], w[~outlier])
    else:
        up_dir = parse_up(up) if isinstance(up, str) else np.asarray(up, np.float64) / np.linalg.norm(up)
        up_rule = "given (--up)"
    r_target = _frame(up_dir, centres[~outlier], w[~outlier])
    rotations = _rotations(r_target)
    r = rotation_matrix(rotations)
    rotated = centres @ r.T
    lo, hi = rotated[~outlier].min(0) - spacing, rotated[~outlier].max(0) + spacing
    crop = Box(tuple(_round(0.5 * (lo + hi), 6)), tuple(_round(0.5 * (hi - lo), 6)))
    removed_floaters = int(np.count_nonzero(outlier & ~crop.contains(rotated)))
    body, norm = preprocess(gs, opacity_threshold=opacity_threshold, rotations=rotations, crop=crop,
                            source=splat, field_prefix="asset.")
    if len(body) < 100:
        raise InputError(splat, "opacity", f"only {len(body)} Gaussians stay after the opacity filter and the crop; "
                         "a contract needs at least 100")
    p = body.means.astype(np.float64)
    blo, bhi = p.min(0), p.max(0)
    height = float(bhi[2] - blo[2])
    dx_ci = _GRID_LIM / _PROFILES["ci"][1]
    slab = max(0.05 * height, 1.5 * dx_ci)
    if height < 2.0 * slab:
        raise InputError(splat, "up", f"the body is {height:.3f} tall along its up axis (largest extent 1): its lowest "
                         f"slab ({slab:.3f}) would hold most of it; pass another --up")
    in_slab = p[:, 2] <= blo[2] + slab
    flo, fhi = p[in_slab].min(0) - dx_ci, p[in_slab].max(0) + dx_ci
    support = _box([flo[0], flo[1], blo[2] - dx_ci], [fhi[0], fhi[1], blo[2] + slab])

    # the body's volume: default-profile cells holding kept centres
    n_def = _PROFILES["default"][1]
    cells = np.unique(np.floor(p / (_GRID_LIM / n_def)).astype(np.int64), axis=0)
    volume = len(cells) * (_GRID_LIM / n_def) ** 3
    n_ref = len(body)
    force = _KICK * _BASE["rho"] * volume / (n_ref * _DT_REF)
    f = float(f"{force:.3g}")

    # camera: bounding sphere in the vertical field of view
    centre = 0.5 * (blo + bhi)
    radius = 0.5 * float(np.linalg.norm(bhi - blo))
    fov = 40.0
    tall = height > max(bhi[0] - blo[0], bhi[1] - blo[1])
    width, height_px = (300, 400) if tall else (400, 300)
    half_v = math.radians(fov / 2)
    half = min(half_v, math.atan(math.tan(half_v) * width / height_px))  # the narrower field binds
    dist = 1.1 * radius / math.sin(half)
    az, el = math.radians(-60.0), math.radians(20.0)
    eye = centre + dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])

    # the loader's CFL bound (knockgs_core.contract.cfl_dt): 0.3 dx / c_p at the stiffest, lightest
    # candidate theta = (1.15, 0.75)
    c_p = Material(_BASE["E"] * 1.15, _BASE["nu"], _BASE["rho"] * 0.75).p_wave_speed()
    profiles, notes_dt = {}, []
    for pname, (n_g, n_grid, fill_res) in _PROFILES.items():
        bound = 0.3 * (_GRID_LIM / n_grid) / c_p
        dt = _nice_dt(bound)
        n_keep = None if n_g is None or n_g >= len(gs) else int(n_g)
        profiles[pname] = {"n_gaussians": n_keep, "n_grid": n_grid, "fill_resolution": fill_res, "dt": dt}
        notes_dt.append(f"{pname} {dt:g} (bound {bound:.2g})")
    pad = 0.05
    fill_box = _box(np.maximum(blo - pad, 0.0), np.minimum(bhi + pad, _GRID_LIM), 3)
    rel = os.path.relpath(splat.resolve(), contract_path.resolve().parent)
    data = {
        "name": name,
        "description": f"scaffolded from {splat.name} by knockgs asset init",
        "asset": {"ply": Path(rel).as_posix(), "seed": 0, "opacity_threshold": float(opacity_threshold),
                  "rotations": [{"axis": a, "degrees": d} for a, d in rotations],
                  "crop": {"center": list(crop.center), "half_size": list(crop.half_size)},
                  "static_boxes": []},
        "fill": {"enabled": True, "box": fill_box, "density_threshold": 0.3, "max_particles_per_cell": 4,
                 "seed": 1},
        "sim": {"grid_lim": _GRID_LIM, "gravity": [0.0, 0.0, 0.0], "grid_v_damping_scale": 1.0,
                "transfer": "affine_flip",
                "boundaries": [{"type": "domain_walls", "padding": 3, "mode": "slip"},
                               {"type": "fixed_cuboid", "box": support}]},
        "materials": {"base": dict(_BASE)},
        "probes": {"standard_x": {"force": [-f, 0.0, 0.0], "export": {"frame_dt": _FRAME_DT, "n_frames": 31}},
                   "standard_y": {"force": [0.0, -f, 0.0], "export": {"frame_dt": _FRAME_DT, "n_frames": 31}}},
        "roles": {"calibration": "standard_x", "heldout": ["standard_y"], "diagnostic": []},
        "probe_reference_particles": int(n_ref),
        "camera": {"width": width, "height": height_px, "fov_deg": fov, "eye": _round(eye, 3),
                   "target": _round(centre, 3), "up": [0.0, 0.0, 1.0]},
        "candidates": "candidates.csv",
        "targets": "targets.csv",
        "profiles": profiles,
    }
    counts = {"file": len(gs), "below_opacity": len(gs) - n_opaque, "floaters": int(outlier.sum()),
              "floaters_removed": removed_floaters, "kept": len(body)}
    notes = {"up": up_rule, "scale": 1.0 / norm.scale, "volume": volume, "mass": _BASE["rho"] * volume,
             "dt": ", ".join(notes_dt), "spacing": spacing, "slab": slab}
    return Scaffold(name=name, splat=splat, layout=sf.layout, repairs=sf.repairs, counts=counts,
                    up=tuple(float(x) + 0.0 for x in up_dir), up_rule=up_rule, data=data, notes=notes)


def _flow(v) -> str:
    """YAML flow form of a scalar, list or flat dict (numbers as Python writes them)."""
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_flow(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_flow(x) for x in v) + "]"
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        s = repr(v)
        return s if ("." in s or "e" in s or "inf" in s) else s + ".0"
    if isinstance(v, str):
        import json

        return json.dumps(v)
    return str(v)


def contract_text(s: Scaffold) -> str:
    """The contract of ``s`` as YAML, every choice with a comment saying how it was made."""
    d, c, n, a = s.data, s.counts, s.notes, s.data["asset"]
    rep = s.repairs
    support = d["sim"]["boundaries"][1]["box"]
    f = -d["probes"]["standard_x"]["force"][0]
    rot = "[" + ", ".join(f"{{axis: {r['axis']}, degrees: {_flow(r['degrees'])}}}" for r in a["rotations"]) + "]"
    up = ", ".join(f"{x:.3g}" for x in s.up)
    lines = [
        f"# {d['name']}: an object contract scaffolded by `knockgs asset init` from {s.splat.name}",
        f"# ({s.layout} layout; {c['file']:,} Gaussians). Every value below is a choice to check and edit;",
        "# `knockgs asset figure` draws what it keeps, removes and holds (docs/own_splat.md).",
        f"# Reading rules applied: {rep.opacity_saturated} opacity logit(s) of +-inf read as opacity 1 / 0, "
        f"{rep.zero_quaternions} zero quaternion(s)",
        f"# read as the identity, {rep.scales_clamped} Gaussian(s) with a scale clamped to [1e-9, 1] x the scene "
        "diagonal.",
        f"name: {d['name']}",
        f"description: {_flow(d['description'])}",
        "",
        "asset:",
        f"  ply: {_flow(a['ply'])}" + "            # relative to this file",
        "  seed: 0                                # seed of the subsampling to a profile's n_gaussians",
        f"  opacity_threshold: {_flow(a['opacity_threshold'])}"
        f"                # drops {c['below_opacity']:,} of {c['file']:,} Gaussians",
        f"  # up axis ({up} in the splat's frame): {s.up_rule};",
        "  # the rotations (x, then y, then z) turn it to +z and the horizontal long axis to +x.",
        "  # Override with `knockgs asset init --up -y` (or a,b,c), or edit the rotations.",
        f"  rotations: {rot}",
        "  # floaters: statistical outliers of the opacity-weighted centres (mean distance to the 8 nearest",
        f"  # above the weighted mean + 3 std): {c['floaters']:,} found, {c['floaters_removed']:,} outside this box "
        "(removed),",
        f"  # the rest inside it (kept). The crop is in the rotated splat frame; it keeps {c['kept']:,} Gaussians.",
        f"  crop: {_flow(a['crop'])}",
        "  # support Gaussians rendered but not simulated (normalized domain), e.g. a floor captured with",
        "  # the object: - {center: [1.0, 1.0, 0.4], half_size: [1.0, 1.0, 0.1]}",
        "  static_boxes: []",
        "",
        "# interior fill over the body's bounding box (normalized domain: largest extent 1, centre (1, 1, 1);",
        f"# one unit is {n['scale']:.4g} splat units)",
        f"fill: {_flow(d['fill'])}",
        "",
        "sim:",
        "  grid_lim: 2.0",
        "  gravity: [0.0, 0.0, 0.0]               # the knock's response alone; [0, 0, -9.81] adds the sag",
        "  grid_v_damping_scale: 1.0",
        "  transfer: affine_flip                  # pure affine FLIP (docs/assets.md)",
        "  boundaries:",
        "    - {type: domain_walls, padding: 3, mode: slip}",
        f"    - type: fixed_cuboid                 # the support: the lowest slab of the body ({n['slab']:.3f} thick)",
        f"      box: {_flow(support)}",
        "",
        "# Base material (SI units in the normalized domain, where the body's largest extent is 1 m):",
        "# E [Pa] Young's modulus, nu Poisson's ratio, rho [kg/m^3] density. Measure rho as mass / volume;",
        "# E from a static test (force / area over strain) or the first ring-down frequency f1 of the",
        "# real object of size L: keeping f1 the same in the normalized domain needs E_sim = E (1 m / L)^2",
        "# at the same rho. These defaults are a soft solid; theta = (s_E, s_rho) scales both.",
        f"materials:\n  base: {_flow(d['materials']['base'])}",
        "",
        f"# Probe A (calibration) and Probe B (held out): a global push along -x and -y, {f:g} N per",
        f"# particle for one 0.1 ms step (scaled by {d['probe_reference_particles']:,} / N at each profile), which "
        f"gives the body (~{n['mass']:.3g} kg",
        f"# at rho, volume ~{n['volume']:.3g} m^3 from the occupied cells) an initial velocity of ~{_KICK} m/s. "
        "Add box probes",
        "# (box: {center, half_size}, selected_reference) for a local contact.",
        "probes:",
    ]
    for k, p in d["probes"].items():
        lines += [f"  {k}:", f"    force: {_flow(p['force'])}", f"    export: {_flow(p['export'])}"]
    lines += [
        "",
        f"roles: {_flow(d['roles'])}",
        "",
        "# particles of the paper profile the probe forces refer to (the kept Gaussians; fill excluded)",
        f"probe_reference_particles: {d['probe_reference_particles']}",
        "",
        "# frames the body's bounding sphere from azimuth -60 and elevation 20 degrees",
        "camera:",
    ]
    lines += [f"  {k}: {_flow(v)}" for k, v in d["camera"].items()]
    lines += [
        "",
        "candidates: candidates.csv",
        "targets: targets.csv",
        "",
        "# n_gaussians: Gaussians of the file kept by seeded subsampling (null: all), before the filters;",
        f"# dt [s]: the CFL bound's largest divisor of 20 ms of the form 20 ms / (2^a 5^b): {n['dt']}",
        "profiles:",
    ]
    lines += [f"  {k}: {_flow(v)}" for k, v in d["profiles"].items()]
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class SourceSelection:
    """Which source Gaussians a contract keeps, at its profile (before the support split).

    ``counts``: ``file`` (Gaussians in the file; None for a procedural asset), ``profile``
    (after subsampling to the profile's ``n_gaussians``), ``below_opacity``,
    ``outside_crop`` (of those above the threshold) and ``kept``. ``repairs``: the reading
    rules' counts over the whole file (None for a procedural asset). ``removed_means``:
    [M, 3] centres of the removed Gaussians in the normalized domain (float64).
    """

    counts: dict
    repairs: SplatRepairs | None
    layout: str
    removed_means: np.ndarray


def source_selection(contract, normalization) -> SourceSelection:
    """Counts of the Gaussians ``contract`` keeps and removes, and where the removed ones lie
    (mapped by ``normalization``, the built asset's)."""
    from ._build import load_source_gaussians

    a = contract.asset
    gs = load_source_gaussians(contract)
    below = gs.opacities < np.float32(a.opacity_threshold)
    outside = np.zeros(len(gs), dtype=bool)
    if a.crop is not None:
        rotated = gs.means.astype(np.float64) @ rotation_matrix(a.rotations).T
        outside = ~below & ~a.crop.contains(rotated)
    removed = below | outside
    repairs, layout, n_file = None, "procedural", None
    if a.ply is not None:
        sf = read_splat(a.ply)
        repairs, layout, n_file = sf.repairs, sf.layout, len(sf.gaussians)
    counts = {"file": n_file, "profile": len(gs), "below_opacity": int(below.sum()),
              "outside_crop": int(outside.sum()), "kept": int(len(gs) - removed.sum())}
    return SourceSelection(counts, repairs, layout, normalization.apply(gs.means[removed]))
