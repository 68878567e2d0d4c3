"""A sigma-point filter on the same step and noise model as the EKF, to compare with it.

The spherical-radial (cubature) point set: 2n points x +- sqrt(n) L e_j with P = L L^T
(hand-written Cholesky), all weights 1/(2n), so the predicted covariance is a sum of
positive terms. Each point goes through :meth:`StepModel.predict` (no Jacobian) and
:meth:`StepModel.measure`; the process noise and the measurement variance are those of
the EKF (:func:`ekf.process_noise`, :meth:`NoiseModel.measurement_variance`) evaluated at
the mean. Update: K = Pxz / Pzz, P = P - K Pzz K^T, symmetrised; SOC clamped as in the EKF.
When that update moves the SOC by more than the EKF's ITERATE_SOC it is iterated, as the
EKF's is (iterated posterior linearisation, Garcia-Fernandez et al. 2015): fresh points
from the last posterior (x_j, P_j) give the measurement's statistical linearisation there,
z ~ A x + b with error variance Omega, and the update is redone from the predicted
(x, P) with H = A and R + Omega. Why: a rested first sample is one precise voltage
against a wide guess, and the points span that guess (soc0 +- sqrt(n) soc0_sigma: with a
guess 0.6 +- 0.3 and four states, SOC 0 to 1.2, the OCV flat beyond 1), so the single
update takes the secant over all of it, far from the OCV's slope near the truth, and
overshoots (to SOC 1 for a truth of 0.95) with a sigma that then holds the error.
Cost per sample: 2n + 1 model steps (the mean's for the direction and the noise) and one
Cholesky (n square roots), against one step and its Jacobian for the EKF.
"""

from __future__ import annotations

import math

import numpy as np

from .ekf import (ITERATE_SOC, ITERATE_TOL, MAX_ITERATIONS, Filter, clamp_state,
                  process_noise)

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
            x0, P0 = xm, P.copy()                        # the predicted state
            xm = xm + K * (v_meas - zm)
            P = P - pzz * np.outer(K, K)
            P = 0.5 * (P + P.T)
            if abs(clamp_state(sm, xm.tolist())[0] - x0[0]) >= ITERATE_SOC:
                xm, P = self._iterate(x0, P0, xm, P, R, v_meas, i_seen, aux_mean, tw,
                                      tw_ocv, tfac)
        self.x, self.P = clamp_state(sm, xm.tolist()), P
        return zm

    def _measure_points(self, points, i_seen, aux, tw, tw_ocv, tfac) -> np.ndarray:
        """h at points of the predicted state (the current through each point's offset
        state; direction and u_prev those of the mean's step)."""
        sm = self.step_model
        z = []
        for p in points.tolist():
            a = aux
            if sm.i_b >= 0:
                i = i_seen - p[sm.i_b]
                g0, dg0, _, _ = sm.current_factors(i, None)
                a = aux._replace(i=i, g0=g0, dg0=dg0)
            z.append(sm.measure(p, a, tw, tw_ocv, tfac, jacobian=False)[0])
        return np.array(z)

    def _iterate(self, x0, P0, xu, Pu, R, v_meas, i_seen, aux, tw, tw_ocv, tfac):
        """Iterated posterior linearisation of the update from the predicted (x0, P0),
        starting at the posterior (xu, Pu); returns the last (x, P)."""
        sm, n = self.step_model, self.step_model.n
        for _ in range(MAX_ITERATIONS):
            xj = np.array(clamp_state(sm, xu.tolist()))
            L = np.array(cholesky(Pu.tolist()))
            spread = math.sqrt(n) * L.T                  # row j: sqrt(n) L e_j
            z = self._measure_points(np.concatenate([xj + spread, xj - spread]), i_seen,
                                     aux, tw, tw_ocv, tfac)
            zbar = float(z.mean())
            # A L e_j = (z+_j - z-_j) / (2 sqrt(n)): the slope along each point pair
            A = np.linalg.solve(L.T, (z[:n] - z[n:]) / (2.0 * math.sqrt(n)))
            dz = z - zbar
            ALT = A @ L                                  # A L, so A Pu A^T = |A L|^2
            omega = max(float(dz @ dz) / (2 * n) - float(ALT @ ALT), 0.0)
            c = P0 @ A
            S = float(A @ c) + R + omega
            K = c / S
            x_next = x0 + K * (v_meas - zbar - A @ (x0 - xj))
            Pu = P0 - S * np.outer(K, K)
            Pu = 0.5 * (Pu + Pu.T)
            done = abs(x_next[0] - xj[0]) < ITERATE_TOL
            xu = x_next
            if done:
                break
        return xu, Pu
