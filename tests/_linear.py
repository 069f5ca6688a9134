"""A linear stand-in for the discrepancy loop's forward model (the interval and model-error
tests): positions = rest + s_E * A(t) + s_rho * B(t), exported at 20 ms for 12 frames."""

from __future__ import annotations

from types import SimpleNamespace


class LinearForward:
    """``X0`` [M, 3] rest positions, ``A`` and ``B`` [T, M, 3] (or broadcastable) responses to
    s_E and s_rho (``B`` None: s_rho unused)."""

    EXPORT = SimpleNamespace(frame_dt=0.02, n_frames=12)

    def __init__(self, X0, A, B=None):
        self.particles = SimpleNamespace(positions=X0, n_gs=len(X0))
        self.X0, self.A, self.B = X0, A, B

    def probe_export(self, probe):
        return self.EXPORT

    def rollout(self, spec, probe):
        X = self.X0[None] + spec.theta[0] * self.A
        return X if self.B is None else X + spec.theta[1] * self.B

