"""Calibrating one's own object from a measured Probe-A observation (docs/own_splat.md).

A measurement is what a camera gives of the object's Probe-A response, without particle
identities: tracked points (the format ``knockgs observe tracks`` writes) or an RGB-D sequence
(the format ``knockgs observe rgbd`` writes and a calibrated RGB-D capture is stored in, tracked
here). Its descriptor is set against a library observed the same way: each candidate's
Probe-A rollout rendered as RGB-D with the measurement's camera, kept at an RGB-D file's
precision (colour and coverage float16, :func:`as_stored`), followed by the same tracker with
the same settings, and described from the tracks alone (the observation ladder's ``flow`` rung,
:mod:`._ladder`, with the measurement's tracker). Then the library's local ridge estimates
theta, which is frozen and written back: its predictions under the held-out probes, beside
those of the base material theta = (1, 1), are what :func:`calibration_rows` and
:func:`plot_calibration` report.

The estimate's interval is the unclipped local-ridge estimate +- 2 leave-one-neighbour-out
jackknife standard errors (:class:`knockgs_core.calibration.LocalRidge`): how much the estimate
leans on single neighbours, not a calibrated confidence interval.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd

from ..errors import InputError

__all__ = ["OBSERVE_TRACKS_DEFAULTS", "BASE_THETA", "ObservationSettings", "camera_to_dict", "camera_from_dict",
           "as_stored", "observe_frames",
           "observe_rollout", "measured_observation", "estimate_summary", "calibration_rows", "calibration_report",
           "plot_calibration"]

#: the tracker settings of ``knockgs observe tracks`` (its command-line defaults; the rest is
#: :class:`knockgs_core.observe.TrackSettings`'): what a measurement made by it was tracked with
OBSERVE_TRACKS_DEFAULTS = {"method": "lk", "radius": 7, "max_seeds": 400}

#: the contract's base material, the prediction before calibration
BASE_THETA = (1.0, 1.0)

MEASUREMENT_KINDS = ("tracks", "rgbd")


@dataclass(frozen=True)
class ObservationSettings:
    """How the measurement and the library are observed. ``kind``: ``tracks`` (tracked points,
    ``.parquet``/``.csv``/``.npz``) or ``rgbd`` (an RGB-D ``.npz``, tracked here); ``track``:
    :class:`knockgs_core.observe.TrackSettings` fields over :data:`OBSERVE_TRACKS_DEFAULTS`
    (the tracker the measurement was made with); ``width``, ``height`` [px]: the library's
    image size for tracked points (None: the contract camera's; an RGB-D measurement brings
    its own camera)."""

    kind: Literal["tracks", "rgbd"] = "tracks"
    track: Mapping = field(default_factory=dict)
    width: int | None = None
    height: int | None = None

    def __post_init__(self):
        if self.kind not in MEASUREMENT_KINDS:
            raise InputError("calibration", "kind", f"must be one of {', '.join(MEASUREMENT_KINDS)}, got {self.kind!r}")

    def tracker(self):
        """The :class:`knockgs_core.observe.TrackSettings` of both observations (no depth noise)."""
        from ..observe import TrackSettings

        return TrackSettings(**{**OBSERVE_TRACKS_DEFAULTS, **dict(self.track)})


def camera_to_dict(camera) -> dict:
    """A :class:`knockgs_core.render.Camera` as JSON: ``width``, ``height`` [px], ``fx``, ``fy``,
    ``cx``, ``cy`` [px] and ``world_to_camera`` [4, 4] (an RGB-D file's fields)."""
    return {"width": int(camera.width), "height": int(camera.height), "fx": float(camera.fx), "fy": float(camera.fy),
            "cx": float(camera.cx), "cy": float(camera.cy),
            "world_to_camera": np.asarray(camera.world_to_camera, dtype=np.float64).tolist()}


def camera_from_dict(d: Mapping):
    """The camera of :func:`camera_to_dict`."""
    from ..render import Camera

    return Camera(width=int(d["width"]), height=int(d["height"]), fx=float(d["fx"]), fy=float(d["fy"]),
                  cx=float(d["cx"]), cy=float(d["cy"]), world_to_camera=np.asarray(d["world_to_camera"], dtype=np.float64))


def as_stored(frames):
    """``frames`` as an RGB-D file holds them (:func:`knockgs_core.observe.write_rgbd`: colour
    and coverage rounded to float16), so a rendered sequence is tracked as a stored one is."""
    from dataclasses import replace

    return replace(frames, rgb=frames.rgb.astype(np.float16).astype(np.float32),
                   alpha=frames.alpha.astype(np.float16).astype(np.float32))


def _curve(points, source) -> np.ndarray:
    from ..descriptors import rms_curves

    return np.asarray(rms_curves(points, source=source)[0], dtype=np.float64)


def observe_frames(frames, settings: ObservationSettings, *, n_frames: int, source: str = "frames"):
    """Track an RGB-D sequence at its stored precision and describe the tracks. Returns (phi
    [5], the tracks' normalized RMS displacement curve r [T], info: seeds, tracks, median
    flow [px], the tracker's error estimate [m])."""
    from ..descriptors import descriptor
    from ..observe import track_points

    points, info = track_points(as_stored(frames), settings.tracker())
    phi = descriptor(points, n_frames=n_frames, source=source)
    return phi, _curve(points, source), {k: info[k] for k in ("seeds", "tracks", "median_flow_px", "error_std")}


def observe_rollout(gaussians, static_mask, gaussian_index, positions, F, camera, settings: ObservationSettings, *,
                    frame_dt: float, device: str = "cpu", source: str = "rollout"):
    """A rollout (``positions`` [T, N, 3], ``F`` [T, n_gs, 3, 3]) rendered as RGB-D by
    ``camera`` and observed as :func:`observe_frames` observes a measurement."""
    from ..observe import render_rgbd

    frames = render_rgbd(gaussians, static_mask, gaussian_index, positions, F, camera, frame_dt=frame_dt, device=device)
    return observe_frames(frames, settings, n_frames=positions.shape[0], source=source)


def measured_observation(path, settings: ObservationSettings, probe):
    """The measured Probe-A observation at ``path`` (kind ``settings.kind``) under ``probe`` (a
    :class:`knockgs_core.sim.Probe`: its export schedule is the frames'). Returns (phi [5],
    curve r [T], info, camera: the RGB-D sequence's, or None for tracked points). A file whose
    frames are not the probe's export frames, or that names another probe, is an
    :class:`InputError` naming it and the field."""
    src = str(path)
    n = int(probe.export.n_frames)
    if settings.kind == "rgbd":
        from ..observe import read_rgbd

        if Path(src).suffix.lower() != ".npz":
            raise InputError(src, "kind", "an RGB-D measurement is an .npz (knockgs observe rgbd's format)")
        frames = read_rgbd(src)
        if abs(frames.frame_dt - probe.export.frame_dt) > 1e-9 * probe.export.frame_dt:
            raise InputError(src, "frame_dt", f"{frames.frame_dt} s between frames, but probe '{probe.name}' exports "
                             f"every {probe.export.frame_dt} s")
        if frames.n_frames != n:
            raise InputError(src, "frame", f"{frames.n_frames} frames, but probe '{probe.name}' exports {n}")
        phi, curve, info = observe_frames(frames, settings, n_frames=n, source=src)
        return phi, curve, {"kind": "rgbd", **info}, frames.camera
    from ..descriptors import descriptor
    from ..discrepancy import read_measured

    m = read_measured(src)
    named = m.meta.get("probe")
    if named and named != probe.name:
        raise InputError(src, "metadata.probe", f"the measurement is of probe '{named}', but the calibration probe is "
                         f"'{probe.name}'")
    idx = m.frame_indices(probe.export.frame_dt, n)
    if not np.array_equal(np.asarray(idx), np.arange(m.n_frames)) or m.n_frames != n:
        raise InputError(src, "frame", f"{m.n_frames} frames; the descriptor needs every one of probe '{probe.name}''s "
                         f"{n} export frames, 0..{n - 1}, in order")
    phi = descriptor(m.points, n_frames=n, source=src)
    info = {"kind": "tracks", "tracks": int(m.points.shape[1])}
    if "tracker_error_std" in m.meta:
        info["error_std"] = float(m.meta["tracker_error_std"])
    return phi, _curve(m.points, src), info, None


def estimate_summary(estimate: Mapping) -> dict:
    """The local ridge's frozen estimate of one measurement (a :func:`frozen_estimate`
    document): theta, the jackknife standard errors, the interval (the unclipped estimate +- 2
    standard errors, module docs), the condition number, the neighbours and whether it fell back."""
    (p,) = estimate["predictions"]
    d = p["details"]
    out = {"s_E": float(p["E_scale"]), "s_rho": float(p["density_scale"]), "fallback": bool(d.get("fallback")),
           "fallback_reason": d.get("fallback_reason"), "condition_number": d.get("condition_number"),
           "neighbours": list(d.get("neighbours", [])), "k": d.get("k"), "alpha": d.get("alpha")}
    se = d.get("uncertainty")
    raw = d.get("unclipped")
    if se and raw:
        out["se"] = [float(se["E_scale"]), float(se["density_scale"])]
        out["interval"] = [[float(raw[n]) - 2 * s, float(raw[n]) + 2 * s]
                           for n, s in zip(("E_scale", "density_scale"), out["se"])]
    else:
        out["se"], out["interval"] = None, None
    out["clipped"] = dict(d.get("clipped") or {})
    out["unclipped"] = [float(raw["E_scale"]), float(raw["density_scale"])] if raw else None
    return out


def calibration_rows(thetas: Mapping[str, tuple[float, float]], predictions: Mapping[tuple[str, str], np.ndarray],
                     observed: Mapping[str, np.ndarray], measured_curve, *, calibration_probe: str) -> pd.DataFrame:
    """One row per (prediction, probe): ``thetas`` {"before"/"after": (s_E, s_rho)};
    ``predictions`` {(prediction, probe): Gaussian-particle positions [T, N, 3] [m]};
    ``observed`` {prediction: the tracked curve r [T] of its Probe-A rollout}, ``measured_curve``
    the measurement's. Columns: the peak and final RMS displacement [m] of the prediction, its
    trajectory RMS distance [m] from the prediction before calibration, and under Probe A the
    RMS difference between its tracked curve and the measured one (normalized by the tracks'
    frame-0 bounding-box diagonal, as the descriptor is)."""
    from ..metrics import rms_displacement_curve, trajectory_rmse

    measured = np.asarray(measured_curve, dtype=np.float64)
    rows = []
    for (which, probe), X in predictions.items():
        c = rms_displacement_curve(X)
        row = {"prediction": which, "s_E": thetas[which][0], "s_rho": thetas[which][1], "probe": probe,
               "role": "calibration" if probe == calibration_probe else "heldout",
               "peak_rms_displacement": float(c.max()), "final_rms_displacement": float(c[-1]),
               "traj_rms_vs_before": trajectory_rmse(X, predictions[("before", probe)])}
        if probe == calibration_probe:
            o = np.asarray(observed[which], dtype=np.float64)
            if o.shape != measured.shape:
                raise InputError("calibration", "frame", f"{o.size} observed frames but {measured.size} measured")
            row["tracked_curve_rmse_vs_measured"] = float(np.sqrt(np.mean((o - measured) ** 2)))
        else:
            row["tracked_curve_rmse_vs_measured"] = float("nan")
        rows.append(row)
    return pd.DataFrame(rows)


def calibration_report(obj: str, summary: Mapping, rows: pd.DataFrame, info: Mapping) -> str:
    """The report's Markdown: the estimate, its interval and condition number, the measurement,
    the predictions' table and the figure."""
    from ..reporting import to_markdown

    iv = summary["interval"]
    lines = [f"# Calibration of {obj}", "",
             f"Measurement: {info['measurement']} ({info['kind']}, {info.get('tracks', '?')} tracks"
             + (f", tracker error estimate {info['error_std']:.3g} m" if info.get("error_std") is not None else "")
             + f"); library: {info['n_candidates']} candidates under probe {info['probe']}, each rendered, tracked "
             f"({info['tracker']}) and described as the measurement.", "",
             "| quantity | value |", "|---|---|",
             f"| estimate (s_E, s_rho) | ({summary['s_E']:.4f}, {summary['s_rho']:.4f}) |"]
    if iv:
        lines.append(f"| interval s_E | [{iv[0][0]:.4f}, {iv[0][1]:.4f}] |")
        lines.append(f"| interval s_rho | [{iv[1][0]:.4f}, {iv[1][1]:.4f}] |")
    cn = summary.get("condition_number")
    lines += [f"| condition number | {cn:.4g} |" if cn is not None else "| condition number | - (fallback) |",
              f"| neighbours (k), alpha | {len(summary['neighbours'])}, {summary['alpha']} |",
              f"| fallback | {summary['fallback_reason'] or 'no'} |",
              "| clipped to the candidates' bounds | " + (", ".join(
                  f"{k} (unclipped {summary['unclipped'][i]:.4f})" for i, (k, v) in enumerate(summary["clipped"].items())
                  if v) or "no") + " |",
              "", "Interval: the unclipped local-ridge estimate +- 2 leave-one-neighbour-out jackknife standard errors "
              "(how much it leans on single neighbours; not a calibrated confidence interval). Condition number: of the "
              "centred neighbourhood design augmented with sqrt(alpha) I.", "",
              to_markdown(rows, title="Predictions before (base material) and after (frozen estimate)",
                          note="RMS displacements and trajectory distances in normalized-domain m over the Gaussian "
                               "particles; tracked-curve RMSE: the Probe-A prediction rendered and tracked as the "
                               "measurement, against it (normalized units). A held-out probe's prediction has no "
                               "measurement here to be scored against."),
              "", "![report](report.png)", ""]
    return "\n".join(lines)


def plot_calibration(path, *, library: pd.DataFrame, summary: Mapping, measured_curve, observed: Mapping[str, np.ndarray],
                     curves: Mapping[tuple[str, str], np.ndarray], frames: Mapping[str, np.ndarray],
                     frame_dt: float, title: str = "") -> None:
    """The one-page figure: (a) the library and the estimate with its interval in the theta
    plane; (b) the measured Probe-A tracked curve against the predictions' before and after;
    (c) the held-out probes' predicted RMS displacement curves [m]; (d) a rendered frame of each
    prediction under the first held-out probe (``frames`` {prediction: RGB [H, W, 3]})."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..reporting import save_figure

    colors = {"before": "tab:blue", "after": "tab:orange"}
    fig, ax = plt.subplots(2, 2, figsize=(9.0, 7.5))
    a = ax[0, 0]
    a.scatter(library["E_scale"], library["density_scale"], s=12, c="0.6", label="candidates")
    nb = library[library["case_name"].isin(summary["neighbours"])]
    a.scatter(nb["E_scale"], nb["density_scale"], s=40, facecolors="none", edgecolors="k", label="neighbours")
    a.plot(*BASE_THETA, "s", color=colors["before"], label="before (base)")
    iv = summary["interval"]
    if iv:  # about the unclipped estimate: it need not hold a clipped one
        from matplotlib.patches import Rectangle

        a.add_patch(Rectangle((iv[0][0], iv[1][0]), iv[0][1] - iv[0][0], iv[1][1] - iv[1][0], fill=False,
                              ec=colors["after"], label="interval"))
    if any(summary["clipped"].values()):
        a.plot(*summary["unclipped"], "x", color=colors["after"], label="unclipped")
    a.plot(summary["s_E"], summary["s_rho"], "*", ms=12, color=colors["after"], label="estimate (after)")
    a.set_xlabel("s_E")
    a.set_ylabel("s_rho")
    a.set_title("(a) library, estimate, interval (+- 2 jackknife SE)", fontsize=9)
    a.legend(fontsize=7)
    b = ax[0, 1]
    t = np.arange(len(measured_curve)) * frame_dt
    b.plot(t, measured_curve, "k-", lw=2, label="measured")
    for which in ("before", "after"):
        b.plot(t, observed[which], "--", color=colors[which], label=f"{which}, tracked")
    b.set_xlabel("t [s]")
    b.set_ylabel("tracked RMS displacement / D")
    b.set_title("(b) Probe A: measurement and predictions", fontsize=9)
    b.legend(fontsize=7)
    c = ax[1, 0]
    for (which, probe), curve in curves.items():
        c.plot(np.arange(len(curve)) * frame_dt, curve, "-" if which == "after" else "--", color=colors[which],
               label=f"{which}, {probe}")
    c.set_xlabel("t [s]")
    c.set_ylabel("RMS displacement [m]")
    c.set_title("(c) held-out probes: predictions (Gaussian particles)", fontsize=9)
    c.legend(fontsize=7)
    d = ax[1, 1]
    d.imshow(np.clip(np.concatenate([frames["before"], frames["after"]], axis=1), 0, 1))
    d.set_axis_off()
    d.set_title("(d) before | after: first held-out probe, peak frame", fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
