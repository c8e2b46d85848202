"""Linear Kalman filter predict and Joseph-form update as pure numpy functions.

These are the textbook equations (Brown & Hwang; filterpy's KalmanFilter uses the same ones):

    predict:  x- = F x,   P- = F P F^T + Q
    update:   y = z - H x,   S = H P H^T + R,   K = P H^T S^-1
              x+ = x + K y,  P+ = (I - K H) P (I - K H)^T + K R K^T      (Joseph form)

The operations are evaluated in filterpy's order (P H^T once, S^-1 by inversion), so a filter that
used filterpy's object gives the same floating-point result, bit for bit
(tests/test_kalman_numpy.py). Shapes: x (n,), P (n, n), F (n, n), Q (n, n), z (m,), H (m, n),
R (m, m).
"""
from __future__ import annotations

import numpy as np


def kf_predict(x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Prior (x-, P-) from the posterior and the transition F with process noise Q."""
    return F @ x, (F @ P) @ F.T + Q


def kf_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, H: np.ndarray, R: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Posterior (x+, P+) after the measurement z = H x + v, v ~ N(0, R); Joseph-form P+."""
    y = z - H @ x
    PHT = P @ H.T
    S = H @ PHT + R
    K = PHT @ np.linalg.inv(S)
    I_KH = np.eye(len(x)) - K @ H
    return x + K @ y, (I_KH @ P) @ I_KH.T + (K @ R) @ K.T
