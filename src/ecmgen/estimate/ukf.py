"""A sigma-point filter on the same step and noise model as the EKF, to compare with it.

The spherical-radial (cubature) point set: 2n points x +- sqrt(n) L e_j with P = L L^T
(hand-written Cholesky), all weights 1/(2n), so the predicted covariance is a sum of
positive terms. Each point goes through :meth:`StepModel.predict` (no Jacobian) and
:meth:`StepModel.measure`; the process noise and the measurement variance are those of
the EKF (:func:`ekf.process_noise`, :meth:`NoiseModel.measurement_variance`) evaluated at
the mean. Update: K = Pxz / Pzz, P = P - K Pzz K^T, symmetrised; SOC clamped as in the EKF.
Cost per sample: 2n + 1 model steps (the mean's for the direction and the noise) and one
Cholesky (n square roots), against one step and its Jacobian for the EKF.
"""

from __future__ import annotations

import math

import numpy as np

from .ekf import Filter, clamp_state, process_noise

JITTER = 1e-15


def cholesky(P: list[list[float]]) -> list[list[float]]:
    """Lower-triangular L with L L^T = P; a non-positive pivot is floored at JITTER
    (the filter's P should never have one, this only keeps a run going)."""
    n = len(P)
    L = [[0.0] * n for _ in range(n)]
    for j in range(n):
        d = P[j][j] - sum(L[j][k] * L[j][k] for k in range(j))
        d = math.sqrt(d if d > JITTER else JITTER)
        L[j][j] = d
        for i in range(j + 1, n):
            L[i][j] = (P[i][j] - sum(L[i][k] * L[j][k] for k in range(j))) / d
    return L


class Ukf(Filter):
    """Sigma-point (cubature) Kalman filter on ``model``; :meth:`step` takes one sample."""

    def step(self, dt: float, i_seen: float, tw, tw_ocv, tfac: float, v_meas: float
             ) -> float:
        sm, n = self.step_model, self.step_model.n
        L = np.array(cholesky(self.P.tolist()))
        x = np.array(self.x)
        spread = math.sqrt(n) * L.T                      # row j: sqrt(n) L e_j
        points = np.concatenate([x + spread, x - spread])
        # the mean's own step: the direction and the noise levels
        _, charging, _, aux_mean = sm.predict(self.x, self.charging, dt, i_seen, tw, tfac,
                                              jacobian=False, tw_ocv=tw_ocv)
        aux_mean = aux_mean._replace(charging=charging)
        X, Z = [], []
        for p in points.tolist():
            xp, _, _, aux = sm.predict(p, self.charging, dt, i_seen, tw, tfac, jacobian=False,
                                       tw_ocv=tw_ocv)
            X.append(xp)
            Z.append(sm.measure(xp, aux._replace(charging=charging), tw, tw_ocv, tfac,
                                jacobian=False)[0])
        X, Z = np.array(X), np.array(Z)
        xm, zm = X.mean(axis=0), float(Z.mean())
        dX, dZ = X - xm, Z - zm
        q = np.array(process_noise(sm, self.noise, aux_mean, dt, self.first, self.P[0][0]))
        P = dX.T @ dX / (2 * n)
        P[np.diag_indices(n)] += q
        ocv = sm.ocv(float(xm[0]), tw_ocv)[0]
        R = self.variance(zm, ocv, dt, xm.tolist(), aux_mean, tw, tw_ocv, tfac)
        self.charging = charging
        if R > 0.0:
            # additive process noise, points not redrawn: it enters Pzz and Pxz through
            # the measurement's gradient at the mean (1 on the RC states, the OCV slope)
            H = np.array(sm.measure(xm.tolist(), aux_mean, tw, tw_ocv, tfac)[1])
            pzz = float(dZ @ dZ) / (2 * n) + float(H @ (q * H)) + R
            pxz = dX.T @ dZ / (2 * n) + q * H
            K = pxz / pzz
            xm = xm + K * (v_meas - zm)
            P = P - pzz * np.outer(K, K)
            P = 0.5 * (P + P.T)
        self.x, self.P = clamp_state(sm, xm.tolist()), P
        return zm
