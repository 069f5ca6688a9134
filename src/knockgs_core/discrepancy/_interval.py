"""The theta interval: what the evidence says about theta, and where it stops (private).

An interval on theta = (s_E, s_rho) is built in log theta from up to three fits of the same
data (docs/discrepancy.md, "Theta interval"):

- ``estimate``: theta fitted by the loop's model, with its statistical standard deviation
  ``sd`` (the linearized least squares, the residual's own variance) and the step the
  linearization still asks for (``remaining``: where the fit stopped short of its minimum);
- ``refined``: theta that the model refined by ``r`` would fit (the model at ``estimate``
  moved by the theta change that reproduces the refinement's change);
- ``second``: the same for the model refined by ``r^2``, where the loop has it.

The statistical half-width is ``h = 2 sd + |remaining|``. Where the data do not show the
model's discretization error (data at the model's own resolution: the term's coefficient at
most the ramp's start and the residual within the noise), the interval is ``estimate +- h``:
a discretization change the data do not show does not widen it.

Where they do, the refinement decides. The pair (model, refined) is *asymptotic* in a
component when the refinement moves theta by at most ``h`` there; with a second refinement,
when the observed order ``p = ln(|e1| / |e2|) / ln r`` (``e1 = refined - estimate``,
``e2 = second - refined``, of one sign) is at least :data:`MIN_ORDER`, or all three agree
within ``h``. Asymptotic: the continuum is extrapolated (first order from the pair, the
observed order from three) and the interval reaches it on the refinement's side; on the other
side it is widened by ``|e1|`` (the refinement's change gives the size, not the sign, where
convergence is not monotone). Not asymptotic: no continuum value is given (``None`` with the
reason) and the interval is unbounded on the refinement's side (0 or infinity in theta).

Where the data show the error, the interval also carries the *floor's share* ``w`` on both
sides: the bias in theta that the misfit the fit leaves above the noise could hide. A model
error shaped like one of the discretization changes the loop knows (the grid placements', the
refinement's) leaves a misfit of norm ``m`` behind a theta bias of ``m`` times that change's
theta-per-misfit ratio; ``w`` is the largest of those ratios times the measured excess misfit.
The refinement's change has a sign, this share has none: a model error of the data's own
kind (a continuum against a grid, a body sampled differently) biases theta either way.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MIN_ORDER", "interval_from_estimates", "theta_per_misfit", "worst_theta_per_misfit"]

#: the smallest observed order of convergence at which three estimates are taken as asymptotic
MIN_ORDER = 0.5


def _order(e1: float, e2: float, factor: float) -> float | None:
    """The observed order of convergence of one component from the refinement's changes
    ``e1`` (model -> refined) and ``e2`` (refined -> second) [log theta] at ratio ``factor``;
    None where they do not converge (opposite signs, or the second change not smaller)."""
    if e1 * e2 <= 0.0 or abs(e2) >= abs(e1):
        return None
    return math.log(abs(e1) / abs(e2)) / math.log(factor)


def theta_per_misfit(A: np.ndarray, changes) -> tuple[np.ndarray, np.ndarray]:
    """How far each model change ``changes`` ([K, rows] or a list of [rows], m) would bias
    theta per unit of the misfit it leaves, when the fit's columns are ``A`` [rows, k] (the
    first two: log s_E, log s_rho). A change ``D = A x + s`` (``s`` orthogonal to the columns)
    in the data moves the least-squares theta by ``x[:2]`` and leaves the misfit ``s``.

    Returns (``ratios`` [K', 2], ``|x[:2]| / |s|`` [1/m] of each change with a misfit,
    ``shapes`` [K, rows], the misfits ``s``)."""
    coefs = [np.linalg.lstsq(A, np.asarray(D, dtype=np.float64), rcond=None)[0] for D in changes]
    shapes = np.stack([np.asarray(D, dtype=np.float64) - A @ x for D, x in zip(changes, coefs)])
    norms = np.linalg.norm(shapes, axis=1)
    ratios = [np.abs(x[:2]) / n for x, n in zip(coefs, norms) if n > 0]
    return (np.stack(ratios) if ratios else np.zeros((0, 2))), shapes


def worst_theta_per_misfit(A: np.ndarray) -> np.ndarray:
    """The most a model error can bias each of log s_E and log s_rho per unit of its norm, when
    the fit's columns are ``A`` [rows, k] (the first two: log s_E, log s_rho): a change ``D`` in
    the data moves the least-squares coefficients by ``x = (A^T A)^-1 A^T D``, and over every
    ``D`` of norm 1 the largest ``|x_j|`` is ``sqrt(((A^T A)^-1)_jj)``, reached by the ``D`` in
    the columns' span that a change of ``x_j`` alone would leave after the others' fit.

    Returns [2] in log theta per m of misfit (``inf`` where the columns do not determine
    theta)."""
    A = np.asarray(A, dtype=np.float64)
    if A.ndim != 2 or A.shape[0] < A.shape[1]:
        return np.full(2, np.inf)
    _, sv, Vt = np.linalg.svd(A, full_matrices=False)   # (A^T A)^-1 = V diag(1 / sv^2) V^T
    if sv[-1] <= sv[0] * max(A.shape) * np.finfo(np.float64).eps:
        return np.full(2, np.inf)
    return np.sqrt(np.sum((Vt[:, :2] / sv[:, None]) ** 2, axis=0))


def interval_from_estimates(estimate, sd, *, remaining=None, refined=None, second=None, factor: float = 1.5,
                            shows_error: bool = True, floor_share=None) -> dict:
    """The theta interval from the estimates of one fit, in log theta (each [2]: log s_E,
    log s_rho): ``estimate`` and its statistical ``sd``; ``remaining``, the step the
    linearized fit still asks for (None: 0); ``refined`` and ``second``, theta fitted by the
    model refined by ``factor`` and by ``factor**2`` (None: not available); ``shows_error``,
    whether the data show the model's discretization error (else the interval is the
    statistical one whatever the refinement does); ``floor_share`` [2], the floor's share of
    the half-width in log theta (None: 0), added on both sides where ``shows_error``.

    Returns a dict: ``interval`` [[lo, hi] of s_E, [lo, hi] of s_rho] (0 or ``inf`` where
    unbounded), ``unbounded`` [[lo?, hi?], ...], ``statistical_sd_log`` [2],
    ``statistical_half_width_log`` [2] (``2 sd + |remaining|``), ``basis`` (``statistical``,
    ``refinement``), ``asymptotic`` [2] (None without a refined estimate), ``observed_order``
    [2] (None where not measured), ``continuum`` [2] (theta extrapolated to the continuum, None
    where the estimates are not asymptotic), ``continuum_reason`` [2] (why not; None where
    given), ``floor_share_log`` [2] (the share added on both sides; 0 where the data do not
    show the error) and ``theta_at`` (theta at ``estimate``, ``refined``,
    ``second_refinement``)."""
    est = np.asarray(estimate, dtype=np.float64).reshape(2)
    sd = np.asarray(sd, dtype=np.float64).reshape(2)
    rem = np.zeros(2) if remaining is None else np.abs(np.asarray(remaining, dtype=np.float64).reshape(2))
    half = 2.0 * sd + rem
    lo, hi = est - half, est + half
    theta_at = {"estimate": [float(math.exp(x)) for x in est]}
    out = {"statistical_sd_log": [float(x) for x in sd], "statistical_half_width_log": [float(x) for x in half],
           "basis": "statistical", "asymptotic": None, "observed_order": [None, None], "continuum": [None, None],
           "continuum_reason": ["no refined model", "no refined model"]}
    if refined is not None:
        ref = np.asarray(refined, dtype=np.float64).reshape(2)
        theta_at["refined"] = [float(math.exp(x)) for x in ref]
        sec = None if second is None else np.asarray(second, dtype=np.float64).reshape(2)
        if sec is not None:
            theta_at["second_refinement"] = [float(math.exp(x)) for x in sec]
        asymptotic, reasons, continuum, orders = [], [], [], []
        for k in range(2):
            e1 = float(ref[k] - est[k])
            order = None
            if sec is None:
                ok = abs(e1) <= half[k]
                reason = None if ok else (f"the refinement moves theta by {abs(e1):.3g} in log, more than its statistical "
                                          f"half-width {half[k]:.3g}, and no third resolution gives an order")
                cont = ref[k] + e1 / (factor - 1.0) if ok else None
            else:
                e2 = float(sec[k] - ref[k])
                order = _order(e1, e2, factor)
                within = max(abs(e1), abs(e1 + e2)) <= half[k]
                ok = within or (order is not None and order >= MIN_ORDER)
                if not ok:
                    reason = ("the refinements do not converge (the second change is not smaller, or of the other sign)"
                              if order is None else f"the observed order {order:.2f} is below {MIN_ORDER}")
                else:
                    reason = None
                if ok and order is not None:
                    cont = sec[k] + e2 / (factor**order - 1.0)
                else:
                    cont = ref[k] + e1 / (factor - 1.0) if ok else None
            asymptotic.append(bool(ok))
            reasons.append(reason)
            orders.append(order)
            continuum.append(cont)
            if not shows_error:
                continue
            # the refinement's side: out to the continuum when asymptotic, unbounded when not;
            # the other side widened by the refinement's change (its size, not its sign)
            reach = [x for x in (ref[k], cont, None if sec is None else sec[k]) if x is not None]
            if e1 > 0:
                lo[k] = est[k] - abs(e1) - half[k]
                hi[k] = max(reach) + half[k] if ok else math.inf
            elif e1 < 0:
                hi[k] = est[k] + abs(e1) + half[k]
                lo[k] = min(reach) - half[k] if ok else -math.inf
        out.update({"asymptotic": asymptotic, "observed_order": orders,
                    "continuum": [None if c is None else float(math.exp(c)) for c in continuum],
                    "continuum_reason": reasons})
        if shows_error:
            out["basis"] = "refinement"
    share = np.zeros(2) if (floor_share is None or not shows_error) else np.abs(np.asarray(floor_share, np.float64).reshape(2))
    lo, hi = lo - share, hi + share
    out["floor_share_log"] = [float(x) for x in share]
    out["interval"] = [[float(math.exp(lo[k])) if math.isfinite(lo[k]) else 0.0,
                        float(math.exp(hi[k])) if math.isfinite(hi[k]) else math.inf] for k in range(2)]
    out["unbounded"] = [[not math.isfinite(lo[k]), not math.isfinite(hi[k])] for k in range(2)]
    out["theta_at"] = theta_at
    return out
