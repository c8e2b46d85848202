"""Shared by the polar-cascade benches (bench/polar_accuracy.py, bench/deviation_declination.py):
the gyro bias prior from levelling at rest on the launcher, before launch."""
from __future__ import annotations

from estimators.levelling import LevellingState, levelling_step


def levelling_at_rest(t_s, gyro_body_rad_s, accel_body_m_s2, level_s: float) -> LevellingState:
    """Levelling (estimators/levelling.py) over the samples with FC time ``t_s < level_s`` (s), the
    airframe at rest; its ``gyro_mean_rad_s`` (body axes, Earth rate included) is the attitude
    filter's gyro bias prior. The arrays are indexed per IMU sample, body frame."""
    lev = LevellingState()
    k = 0
    while t_s[k] < level_s:
        lev = levelling_step(lev, gyro_body_rad_s[k], accel_body_m_s2[k])
        k += 1
    return lev
