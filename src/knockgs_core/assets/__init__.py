"""Gaussian assets: 3DGS PLY files (INRIA and SuperSplat compressed), contract scaffolds,
PhysGaussian preprocessing, interior fill, procedural Pillow / Ficus / Vasedeck stand-ins,
and contract-driven building.

Conventions: :class:`GaussianSet` holds *activated* parameters (scales as standard
deviations, unit wxyz quaternions, opacities in (0, 1)); positions of
:class:`ParticleSet` are in the normalized domain ``[0, 2]^3`` with the object's largest
extent 1 and centre (1, 1, 1); Gaussian-associated particles come first, fill after.
"""

from ._build import BuiltAsset, body_level_set, build_asset, load_source_gaussians
from ._figure import asset_figure
from ._fill import FillGrid, FillResult, body_distance, body_fraction, density_grid, fill_grid, fill_interior, interior_cells
from ._gaussians import SH_C0, GaussianSet, matrix_to_quat, quat_multiply, quat_to_matrix
from ._particles import ParticleSet, load_particles, save_particles
from ._ply import SplatFile, SplatRepairs, read_ply, read_splat, write_ply
from ._procedural import CAPTURE_ROTATION, PROCEDURAL_ASSETS, make_procedural
from ._scaffold import Scaffold, SourceSelection, contract_text, parse_up, scaffold_contract, source_selection
from ._scene import load_scene, save_scene, scene_path
from ._transform import Normalization, preprocess, rotation_matrix, transform_gaussians
from ._volumes import VOLUME_RULES, enclosed_volumes, surface_areas, wall_volumes

__all__ = [
    "SH_C0",
    "GaussianSet",
    "read_ply",
    "read_splat",
    "SplatFile",
    "SplatRepairs",
    "write_ply",
    "Scaffold",
    "SourceSelection",
    "scaffold_contract",
    "contract_text",
    "parse_up",
    "source_selection",
    "Normalization",
    "preprocess",
    "rotation_matrix",
    "transform_gaussians",
    "ParticleSet",
    "save_particles",
    "load_particles",
    "save_scene",
    "load_scene",
    "scene_path",
    "FillResult",
    "fill_interior",
    "density_grid",
    "interior_cells",
    "FillGrid",
    "fill_grid",
    "body_fraction",
    "body_distance",
    "body_level_set",
    "VOLUME_RULES",
    "enclosed_volumes",
    "wall_volumes",
    "surface_areas",
    "PROCEDURAL_ASSETS",
    "CAPTURE_ROTATION",
    "make_procedural",
    "BuiltAsset",
    "build_asset",
    "load_source_gaussians",
    "asset_figure",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_multiply",
]
