"""Passive versus active observation: why a known probe fixes the scale of (s_E, s_rho).

Under a *passive* observation (the object sagging under gravity on its support, no known
force), momentum balance ``rho a = div sigma(E) + rho g`` is unchanged when E and rho are
scaled together: every trajectory depends on theta only through ``s_E / s_rho``, so only that
ratio is identifiable. A known force ``f`` enters as ``a = f / m``: it fixes the scale. In the
MPM solver the same holds step by step (particle masses and stresses scale together, grid
velocities are their quotient, gravity adds ``g dt`` to them), so rollouts at
``(a s_E, a s_rho)`` equal those at ``(s_E, s_rho)``; for ``a`` a power of two, bit for bit,
but for the solver's absolute empty-node mass threshold (docs/probe_shifts.md: one float32 ulp
where an object has nodes near it).

:func:`passive_protocol` defines the protocol per object: gravity along the camera's down
direction, of the magnitude that gives the passive response at theta = (1, 1) Probe A's
mean RMS displacement (secant steps from a rollout at g = 1 m/s^2 until within 10 %, at most
three), exported like Probe A; it also records the invariance check. The
passive library (the same 54 candidates) and the targets' passive responses feed every
estimator exactly like the Probe-A route; :func:`passive_active_table` compares the two.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from ..errors import InputError
from ..metrics import joint_error_pct, rms_displacement_curve

__all__ = ["PASSIVE_PROBE", "PassiveProtocol", "passive_protocol", "passive_rollout", "error_directions",
           "passive_active_table", "passive_active_note", "ratio_span_pct", "plot_passive_active"]

#: the name the passive protocol's rollouts carry as their probe
PASSIVE_PROBE = "passive_sag"


@dataclass(frozen=True)
class PassiveProtocol:
    """The passive protocol of one object: ``gravity`` [m/s^2, normalized domain] switched on
    at t = 0 with the object at rest, no force applied, exported every ``frame_dt`` [s] for
    ``n_frames`` frames (Probe A's schedule)."""

    gravity: tuple[float, float, float]
    frame_dt: float
    n_frames: int

    def probe(self):
        from ..sim import ExportSchedule, Probe

        return Probe(name=PASSIVE_PROBE, force=(0.0, 0.0, 0.0), export=ExportSchedule(self.frame_dt, self.n_frames))

    def run_kwargs(self) -> dict:
        """Keyword arguments of :func:`knockgs_core.rollout.run_rollout` for this protocol."""
        return {"probe": self.probe(), "sim_overrides": {"gravity": tuple(self.gravity)}}

    def to_dict(self) -> dict:
        return {"probe": PASSIVE_PROBE, "gravity": list(self.gravity), "frame_dt": self.frame_dt, "n_frames": self.n_frames}

    @classmethod
    def from_dict(cls, d: Mapping, source: str = "passive protocol") -> PassiveProtocol:
        try:
            g = tuple(float(x) for x in d["gravity"])
            out = cls(gravity=g, frame_dt=float(d["frame_dt"]), n_frames=int(d["n_frames"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(source, "gravity", f"not a passive protocol ({exc})") from None
        if len(g) != 3 or not all(math.isfinite(x) for x in g) or not out.frame_dt > 0 or out.n_frames < 2:
            raise InputError(source, "gravity", "needs a finite 3-vector gravity, frame_dt > 0 and n_frames >= 2")
        return out


def passive_rollout(contract, theta, protocol: PassiveProtocol, *, particles, device=None, deterministic: bool = False):
    """The rollout of ``contract`` at ``theta`` under the passive protocol
    (:class:`knockgs_core.rollout.Rollout`; its probe is named :data:`PASSIVE_PROBE`).
    ``deterministic``: as in :func:`knockgs_core.rollout.run_rollouts`."""
    from ..rollout import run_rollout

    return run_rollout(contract, theta, PASSIVE_PROBE, particles=particles, device=device, deterministic=deterministic,
                       **protocol.run_kwargs())


def _mean_rms(X: np.ndarray, n_gs: int) -> float:
    return float(np.mean(rms_displacement_curve(np.asarray(X)[:, :n_gs])))


def passive_protocol(contract, particles, *, device=None, deterministic: bool = False,
                     scales: Sequence[float] = (0.5, 2.0)) -> tuple[PassiveProtocol, dict]:
    """The object's passive protocol and the record of how it was set and checked.

    Gravity points along the contract camera's down direction (``-up``); its magnitude makes
    the passive response at theta = (1, 1) as large as Probe A's (mean over frames of the RMS
    displacement of the Gaussian-associated particles): from a rollout at 1 m/s^2, secant steps
    on ``rms ~ g^k`` until within 10 %, at most three (the record says how close it came). The
    record holds both responses, the search and the invariance check: the largest position
    difference [m] between theta = (a, a) and (1, 1) for ``a`` in ``scales``, under the
    passive protocol (0 expected) and under Probe A (the known force breaks it).
    ``deterministic``: every rollout's, as in :func:`knockgs_core.rollout.run_rollouts`."""
    A = contract.calibration_probe
    up = np.asarray(contract.camera["up"], dtype=np.float64)
    down = -up / np.linalg.norm(up)
    unit = PassiveProtocol(gravity=tuple(float(x) + 0.0 for x in down), frame_dt=A.export.frame_dt, n_frames=A.export.n_frames)
    n_gs = particles.n_gs
    from ..rollout import run_rollout

    XA = run_rollout(contract, (1.0, 1.0), A.name, particles=particles, device=device,
                     deterministic=deterministic).positions
    rms_a = _mean_rms(XA, n_gs)

    def response(g: float) -> tuple[np.ndarray, float]:
        p = PassiveProtocol(gravity=tuple(float(g * x) + 0.0 for x in down), frame_dt=unit.frame_dt, n_frames=unit.n_frames)
        X = passive_rollout(contract, (1.0, 1.0), p, particles=particles, device=device,
                            deterministic=deterministic).positions
        return X, _mean_rms(X, n_gs)

    # the response is nearly linear in g at small strains; where it is not (a swinging
    # plant), secant steps in log-log on rms ~ g^k, until within 10 % (at most 3 more rollouts)
    g, (XP1, rms_p) = 1.0, response(1.0)
    if not (rms_p > 0 and math.isfinite(rms_p)):
        raise InputError(contract.source, "camera.up", "the object does not move under gravity along -up")
    history = [(g, rms_p)]
    k = 1.0
    for _ in range(3):
        if abs(rms_p / rms_a - 1.0) < 0.1:
            break
        g_new = g * (rms_a / rms_p) ** (1.0 / k)
        XP1, r_new = response(g_new)
        if r_new > 0 and abs(math.log(g_new / g)) > 1e-12:
            k = min(max(math.log(r_new / rms_p) / math.log(g_new / g), 0.2), 5.0)
        g, rms_p = g_new, r_new
        history.append((g, rms_p))
    protocol = PassiveProtocol(gravity=tuple(float(g * x) + 0.0 for x in down), frame_dt=unit.frame_dt, n_frames=unit.n_frames)
    check = []
    for a in scales:
        Xp = passive_rollout(contract, (a, a), protocol, particles=particles, device=device,
                             deterministic=deterministic).positions
        Xa = run_rollout(contract, (a, a), A.name, particles=particles, device=device,
                         deterministic=deterministic).positions
        check.append({"scale": float(a), "passive_max_abs_diff": float(np.max(np.abs(Xp - XP1))),
                      "passive_bitwise_equal": bool(np.array_equal(Xp, XP1)),
                      "active_max_abs_diff": float(np.max(np.abs(Xa - XA))),
                      "active_rms_change": float(np.sqrt(np.mean(np.sum((Xa[:, :n_gs] - XA[:, :n_gs]) ** 2, -1))))})
    record = {"object": contract.name, "profile": contract.profile, "probe_a": A.name, **protocol.to_dict(),
              "gravity_magnitude": float(g),
              "rule": "passive mean RMS displacement at theta (1, 1) = Probe A's: secant steps until within 10 %, at most 3",
              "probe_a_mean_rms": rms_a, "passive_mean_rms": rms_p,
              "gravity_search": [{"g": a, "passive_mean_rms": b} for a, b in history], "invariance": check}
    return protocol, record


def error_directions(theta_hat, theta_true) -> dict:
    """The estimate's log error split along the ratio direction ``log(s_E / s_rho)`` and the
    scale direction ``log(s_E s_rho)`` (orthonormal: each is the projection on
    ``(1, -1) / sqrt 2`` and ``(1, 1) / sqrt 2``), as ``100 |projection|`` (about a percent)."""
    d = np.log(np.asarray(theta_hat, dtype=np.float64)) - np.log(np.asarray(theta_true, dtype=np.float64))
    return {"ratio_error": 100.0 * abs(d[0] - d[1]) / math.sqrt(2.0), "scale_error": 100.0 * abs(d[0] + d[1]) / math.sqrt(2.0)}


def ratio_span_pct(thetas) -> float:
    """Span of ``s_E / s_rho`` over ``thetas``: ``100 (max / min - 1)`` (the paper's 162 % for
    the five main targets)."""
    r = np.array([a / b for a, b in thetas], dtype=np.float64)
    return float(100.0 * (r.max() / r.min() - 1.0))


def passive_active_table(estimates: Mapping[str, Mapping[str, Mapping]], targets: pd.DataFrame,
                         methods: Sequence[str]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``estimates[protocol][method]``: frozen estimate documents (``predictions`` with
    ``case_name``, ``E_scale``, ``density_scale``). Returns (summary, per-target rows): per
    (protocol, method) the mean joint error [%], the mean ratio- and scale-direction errors
    (:func:`error_directions`) and the span of the estimated ``s_E / s_rho`` over the
    targets beside the true span (:func:`ratio_span_pct`)."""
    truth = {r.case_name: (float(r.E_scale), float(r.density_scale)) for r in targets.itertuples(index=False)}
    rows, summary = [], []
    for protocol, by_method in estimates.items():
        for m in methods:
            if m not in by_method:
                raise InputError(f"{protocol} estimates", "method", f"no estimate of {m!r}")
            preds = {p["case_name"]: (float(p["E_scale"]), float(p["density_scale"])) for p in by_method[m]["predictions"]}
            missing = set(truth) - set(preds)
            if missing:
                raise InputError(f"{protocol} estimates of {m}", "predictions", f"no estimate for {sorted(missing)}")
            per = []
            for case, th in truth.items():
                est = preds[case]
                per.append({"protocol": protocol, "method": m, "target": case, "E_true": th[0], "rho_true": th[1],
                            "E_hat": est[0], "rho_hat": est[1], "joint_error_pct": joint_error_pct(est, th),
                            **error_directions(est, th)})
            rows += per
            df = pd.DataFrame(per)
            summary.append({"protocol": protocol, "method": m, "joint_error_pct": float(df["joint_error_pct"].mean()),
                            "ratio_error": float(df["ratio_error"].mean()), "scale_error": float(df["scale_error"].mean()),
                            "ratio_span_est_pct": ratio_span_pct([preds[c] for c in truth]),
                            "ratio_span_true_pct": ratio_span_pct(list(truth.values()))})
    return pd.DataFrame(summary), pd.DataFrame(rows)


def passive_active_note(summary: pd.DataFrame, records: Sequence[Mapping]) -> str:
    """What the table shows, with the invariance check of the protocol records."""
    lr = summary[summary["method"] == "local_ridge"].set_index("protocol")
    inv = []
    for rec in records:
        for c in rec["invariance"]:
            inv.append(f"a = {c['scale']:g}: passive max |dx| = {c['passive_max_abs_diff']:.3g} m"
                       f"{' (bit for bit)' if c['passive_bitwise_equal'] else ''}, Probe A {c['active_max_abs_diff']:.3g} m")
    note = ("Passive: the object sags under gravity along the camera's down direction (no known force; magnitude set so that "
            "its response at theta (1, 1) is as large as Probe A's), exported like Probe A; the same 54 candidates and "
            "estimators. Ratio and scale errors: 100 |projection| of the log error on log(s_E/s_rho) and log(s_E s_rho) "
            "(orthonormal). Ratio span: 100 (max/min - 1) of s_E/s_rho over the targets (paper: 162 % true, 163 % estimated). "
            f"Invariance, rollouts at (a, a) against (1, 1): {'; '.join(inv)}.")
    if {"active", "passive"} <= set(lr.index):
        note += (f" Local ridge: active {lr.loc['active', 'joint_error_pct']:.2f} % joint "
                 f"(scale {lr.loc['active', 'scale_error']:.2f}), "
                 f"passive {lr.loc['passive', 'joint_error_pct']:.2f} % (ratio {lr.loc['passive', 'ratio_error']:.2f}, "
                 f"scale {lr.loc['passive', 'scale_error']:.2f}).")
    return note


def plot_passive_active(rows: pd.DataFrame, path, *, title: str = "", method: str = "local_ridge") -> None:
    """Estimates of ``method`` in the (s_E, s_rho) plane under both protocols, the targets,
    and each target's invariance line ``s_E / s_rho = const`` (dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..reporting import save_figure

    fig, ax = plt.subplots(figsize=(5.2, 4.4))
    sub = rows[rows["method"] == method]
    truth = sub.drop_duplicates("target")
    lim = np.array([0.3, 2.2])
    for r in truth.itertuples(index=False):
        ratio = r.E_true / r.rho_true
        ax.plot(lim * ratio, lim, color="0.75", ls="--", lw=0.8, zorder=0)
    ax.scatter(truth["E_true"], truth["rho_true"], marker="*", s=120, c="k", label="target", zorder=3)
    styles = {"active": ("o", "tab:blue", "Probe A (active)"), "passive": ("s", "tab:orange", "passive (gravity)")}
    for protocol, (mk, col, lab) in styles.items():
        p = sub[sub["protocol"] == protocol]
        if p.empty:
            continue
        ax.scatter(p["E_hat"], p["rho_hat"], marker=mk, facecolors="none", edgecolors=col, s=60, label=lab, zorder=2)
        for r in p.itertuples(index=False):
            ax.plot([r.E_true, r.E_hat], [r.rho_true, r.rho_hat], color=col, lw=0.7, alpha=0.7)
    ax.set_xlabel("s_E")
    ax.set_ylabel("s_rho")
    ax.set_xlim(0.3, 1.4)
    ax.set_ylim(0.6, 2.0)
    ax.set_title(title or f"{method}: passive vs active (dashed: s_E/s_rho = const)", fontsize=9)
    ax.legend(fontsize=8, loc="upper left")
    save_figure(fig, path, dpi=120)
    plt.close(fig)
