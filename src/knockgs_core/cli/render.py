"""``knockgs render``: a rollout's frames as images, or as deformed 3DGS PLY files.

Both subcommands take the asset's normalized PLY and its scene file (``<object>.ply`` and
``<object>.scene.npz`` next to it: written by ``knockgs asset make --normalized`` and by the
workflow under ``results/<profile>/assets/``) and a rollout with its deformation gradients
(``knockgs simulate ... -o R.parquet --export-F R.F.parquet``; the workflow's evaluation
rollouts ``<theta>.parquet`` and ``<theta>.F.parquet``).
"""

from __future__ import annotations

import sys
from pathlib import Path

from ..errors import InputError
from ._common import contract_inputs, image_side

__all__ = ["register", "run_frames", "run_ply"]


def _common(p) -> None:
    p.add_argument("--asset", required=True, help="the asset's normalized 3DGS PLY (knockgs asset make --normalized)")
    p.add_argument("--rollout", required=True, help="a rollout .parquet (knockgs simulate)")
    p.add_argument("--deformation", help="its deformation gradients (default: R.F.parquet next to R.parquet)")
    p.add_argument("--scene", help="the asset's scene file (default: <asset>.scene.npz next to the PLY)")
    p.add_argument("--frames", default="all", help="frame indices, e.g. '0,15,30' or 'all' (default)")
    p.add_argument("-o", "--output", required=True, help="output folder")


def register(sub) -> None:
    p = sub.add_parser("render", help="render a rollout's frames (PNG) or export them as deformed 3DGS PLY",
                       description=__doc__.splitlines()[0])
    s = p.add_subparsers(dest="render_command", required=True)
    fr = s.add_parser("frames", help="PNG per frame with the object's camera")
    _common(fr)
    fr.add_argument("--object", required=True, help="object whose contract camera is used (config/objects/NAME.yaml)")
    fr.add_argument("--profile", default="default", help="resolution profile of the contract (ci, default, paper)")
    fr.add_argument("--width", type=image_side, help="image width, 1 .. 8192 pixels (default: the contract camera's)")
    fr.add_argument("--height", type=image_side, help="image height, 1 .. 8192 pixels (default: the contract camera's)")
    fr.add_argument("--device", default="cpu", help="Warp device (cpu; cuda: a GPU no other process holds; cuda:0)")
    fr.add_argument("--config-dir", help="folder holding objects/ (default: the project's config/)")
    fr.set_defaults(func=run_frames)
    ply = s.add_parser("ply", help="a standard 3DGS PLY per frame (F Sigma_0 F^T as scales and rotations)")
    _common(ply)
    ply.set_defaults(func=run_ply)


def _frames(text: str, n: int) -> list[int]:
    if text == "all":
        return list(range(n))
    try:
        out = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise InputError("--frames", "frames", f"expected 'all' or comma-separated integers, got '{text}'") from None
    bad = [f for f in out if not 0 <= f < n]
    if not out or bad:
        raise InputError("--frames", "frames", f"frame indices must lie in 0..{n - 1}; got {text}")
    return out


def _paths(args) -> dict:
    from ..assets import scene_path

    asset = Path(args.asset)
    rollout = Path(args.rollout)
    return {"--asset": asset, "--scene": Path(args.scene) if args.scene else scene_path(asset), "--rollout": rollout,
            "--deformation": Path(args.deformation) if args.deformation
            else rollout.with_name(rollout.name.replace(".parquet", ".F.parquet"))}


def _check_inputs(args, paths: dict) -> None:
    """The input paths (``paths``, and ``--object``, ``--config-dir`` where given), checked
    before any work; a missing scene or F file says which command writes it."""
    from ..io import input_problem
    from ._common import check_command_inputs
    from .simulate import _contract_file

    hints = {"--scene": " (written next to the PLY by `knockgs asset make --normalized`)",
             "--deformation": " (written by `knockgs simulate ... --export-F`)"}
    for field, path in paths.items():
        problem = input_problem(path)
        if problem is not None:
            raise InputError(str(path), field, problem + (hints.get(field, "") if "does not exist" in problem else ""))
    obj = getattr(args, "object", None)
    check_command_inputs(args, {**paths, "--object": _contract_file(obj) if obj else None,
                                "--config-dir": getattr(args, "config_dir", None)}, folders=("--config-dir",))


def _load(args, paths: dict, contract=None):
    """The asset, scene, rollout and F, each checked against the others (and the contract)."""
    from ..assets import load_scene, read_ply
    from ..rollout import check_rollout_meta, read_deformation, read_rollout

    gaussians = read_ply(paths["--asset"])
    static_mask, gaussian_index = load_scene(paths["--scene"], n_gaussians=len(gaussians))
    ro = read_rollout(paths["--rollout"])
    if contract is not None and "contract_hash" in ro.meta:  # a simulator rollout: its provenance must match
        check_rollout_meta(paths["--rollout"], ro.meta, object=contract.name, profile=contract.profile,
                           contract_hash=contract.hash)
    F = read_deformation(paths["--deformation"], rollout=ro, rollout_path=paths["--rollout"])
    if F.shape[1] != gaussian_index.size:
        raise InputError(str(paths["--deformation"]), "F", f"{F.shape[0]} frames x {F.shape[1]} particles; the scene "
                         f"{paths['--scene']} has {gaussian_index.size} Gaussian-associated particles")
    check_rollout_meta(paths["--rollout"], ro.meta, partial=True, n_gs=int(gaussian_index.size))
    return gaussians, gaussian_index, static_mask, ro, F


def _check(args, paths: dict, pattern: str, contract=None) -> None:
    from ..io import check_outputs

    inputs = {**paths, **(contract_inputs(contract) if contract is not None else {})}
    check_outputs({"--output": args.output}, inputs, directories={"--output": (pattern,)})


def _check_files(args, paths: dict, files: list[Path], contract=None) -> None:
    """Every file the command writes in its output folder, checked before the first is written
    (none of them a FIFO, a folder, a link or an input)."""
    from ..io import check_outputs

    inputs = {**paths, **(contract_inputs(contract) if contract is not None else {})}
    check_outputs({"--output": files}, inputs)


def run_ply(args) -> int:
    from ..assets import write_ply
    from ..render import deformed_gaussians

    paths = _paths(args)
    _check_inputs(args, paths)
    _check(args, paths, "frame_*.ply")
    gaussians, gaussian_index, _, ro, F = _load(args, paths)
    out = Path(args.output)
    frames = _frames(args.frames, ro.positions.shape[0])
    _check_files(args, paths, [out / f"frame_{t:04d}.ply" for t in frames])
    out.mkdir(parents=True, exist_ok=True)
    for t in frames:
        write_ply(deformed_gaussians(gaussians, gaussian_index, ro.positions[t], F[t]), out / f"frame_{t:04d}.ply")
    print(f"{len(frames)} PLY frame(s) of {len(gaussians)} Gaussians -> {out}", file=sys.stderr)
    return 0


def run_frames(args) -> int:
    import numpy as np
    from PIL import Image

    from ..contract import load_contract
    from ..render import camera_from_contract, render_rollout

    from ..io import atomic_write
    from .._warp import warp_device

    paths = _paths(args)
    _check_inputs(args, paths)
    contract = load_contract(args.object, args.profile, config_dir=args.config_dir)
    _check(args, paths, "frame_*.png", contract)
    warp_device(args.device)
    gaussians, gaussian_index, static_mask, ro, F = _load(args, paths, contract)
    camera = camera_from_contract(contract.camera, width=args.width, height=args.height)
    frames = _frames(args.frames, ro.positions.shape[0])
    _check_files(args, paths, [Path(args.output) / f"frame_{t:04d}.png" for t in frames], contract)
    rgb, _ = render_rollout(gaussians, static_mask, gaussian_index, ro.positions[frames], F[frames], camera, device=args.device)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    for t, img in zip(frames, rgb):
        with atomic_write(out / f"frame_{t:04d}.png") as fh:
            Image.fromarray((np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)).save(fh, format="png")
    print(f"{len(frames)} frame(s) at {camera.width}x{camera.height} -> {out}", file=sys.stderr)
    return 0
