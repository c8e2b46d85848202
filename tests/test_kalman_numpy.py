"""estimators/kalman.py against filterpy's KalmanFilter: the same floating-point result, bit for bit.

KF1 (mag_error_kf) and KF2 (ahrs_kf2) used filterpy's object; its import pulled in scipy.stats
(1.9 s of CPU at the daemon's start). The numpy functions must not change a single bit of either
filter, so the compiled core's 1e-9 equality with the reference keeps its meaning.
"""
from __future__ import annotations

import numpy as np
import pytest

from estimators.kalman import kf_predict, kf_update

filterpy_kalman = pytest.importorskip("filterpy.kalman")


def _random_spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


@pytest.mark.parametrize("n, m", [(9, 1), (9, 2), (9, 3), (12, 3)])   # KF2's and KF1's shapes
def test_predict_and_update_equal_filterpy_bit_for_bit(n, m):
    # GIVEN 200 seeded random filters of the shapes KF1 and KF2 use
    rng = np.random.default_rng(19)
    for _ in range(200):
        x = rng.normal(size=n)
        P = _random_spd(rng, n)
        F = np.eye(n) + 0.01 * rng.normal(size=(n, n))
        Q = np.diag(rng.uniform(1e-6, 1e-2, n))
        H = rng.normal(size=(m, n))
        R = _random_spd(rng, m) * 1e-2
        z = rng.normal(size=m)
        kf = filterpy_kalman.KalmanFilter(dim_x=n, dim_z=m)
        kf.x, kf.P, kf.F, kf.Q = x.copy(), P.copy(), F, Q
        # WHEN both predict, then update with the same measurement
        kf.predict()
        x_pred, P_pred = kf_predict(x, P, F, Q)
        pred_equal = np.array_equal(kf.x, x_pred) and np.array_equal(kf.P, P_pred)
        kf.update(z, R=R, H=H)
        x_post, P_post = kf_update(x_pred, P_pred, z, H, R)
        # THEN every element is the same double
        assert pred_equal
        assert np.array_equal(kf.x, x_post)
        assert np.array_equal(kf.P, P_post)
