"""The FC's status messages for an offline ``sim.offline.SimRun``, built from what the FC itself
measures (never from the simulator's truth): a 1 Hz HEARTBEAT and a 1 Hz EKF status, as the
daemon's link hands them to ``service.pipeline.Pipeline``.

- HEARTBEAT: armed; ``system_status`` is ArduPlane's ``is_flying()`` estimate, ACTIVE when flying,
  STANDBY before. ArduPlane (Plane::update_is_flying_5Hz) counts as flying an airspeed estimate of
  at least 0.75 * ARSPD_FBW_MIN (default 9 m/s), or a confirmed GNSS ground speed. Here the FC's
  own airspeed is the true airspeed from its SCALED_PRESSURE (differential and static pressure,
  temperature: v = sqrt(2 q / rho), rho = p / (R_d T)); without a pitot sample it says STANDBY.
- EKF status: attitude ok; ``horiz_pos_ok`` clears at the GNSS loss the FC sees (the scenario's
  GNSS fault, which the simulator reports on the wire as EKF_STATUS_REPORT).
"""
from __future__ import annotations

import math

import numpy as np

STATUS_PERIOD_S = 1.0
MAV_STATE_STANDBY = 3
MAV_STATE_ACTIVE = 4
MAV_TYPE_FIXED_WING = 1
ARSPD_FBW_MIN_M_S = 9.0
"""ArduPlane's default minimum airspeed (ARSPD_FBW_MIN, m/s)."""
IS_FLYING_AIRSPEED_M_S = 0.75 * ARSPD_FBW_MIN_M_S
"""ArduPlane's is_flying() airspeed threshold: 0.75 * ARSPD_FBW_MIN = 6.75 m/s."""
R_DRY_AIR_J_KG_K = 287.058


def fc_airspeed_m_s(press_abs_pa: np.ndarray, press_diff_pa: np.ndarray, temperature_k: np.ndarray) -> np.ndarray:
    """True airspeed from the FC's pitot: v = sqrt(2 q / rho), rho = p / (R_d T); NaN without a pitot."""
    rho = np.asarray(press_abs_pa, float) / (R_DRY_AIR_J_KG_K * np.asarray(temperature_k, float))
    q = np.maximum(np.asarray(press_diff_pa, float), 0.0)
    return np.sqrt(2.0 * q / rho)


def fc_status_items(run, t_from_s: float, period_s: float = STATUS_PERIOD_S) -> list:
    """FcHeartbeat + FcEkfStatus every ``period_s`` from ``t_from_s`` to the run's end (receive
    time = FC time). Reads the FC's pressure samples and the GNSS fault time only."""
    from mavlink_io.samples import FcEkfStatus, FcHeartbeat
    t_end = float(run.time_s[-1])
    loss = run.gnss_lost_time_s
    v = fc_airspeed_m_s(run.press_abs_pa, run.press_diff_pa, run.temperature_k)
    bt = np.asarray(run.baro_time_s, float)
    out = []
    for t in np.arange(t_from_s, t_end, period_s).tolist():
        k = int(np.searchsorted(bt, t, side="right")) - 1      # the FC's latest pressure sample
        flying = k >= 0 and math.isfinite(v[k]) and v[k] >= IS_FLYING_AIRSPEED_M_S
        out.append(FcHeartbeat(t, 1, 1, "ardupilot", MAV_TYPE_FIXED_WING, 129, 0,
                               MAV_STATE_ACTIVE if flying else MAV_STATE_STANDBY, True))
        out.append(FcEkfStatus(t, True, loss is None or t < loss, 0, "ekf_status_report", t))
    return out


def merged_items(run, t_from_s: float, cut=lambda t: False) -> list:
    """bench/sitl.py's ``pipeline_inputs`` with the status messages merged in time order (status
    first at equal times), from ``t_from_s``, without the items whose receive time ``cut`` says."""
    from sitl import pipeline_inputs
    extra = fc_status_items(run, t_from_s)
    items = pipeline_inputs(run)
    merged = sorted([(it.time_rx_s, 0, i, it) for i, it in enumerate(extra)]
                    + [(it.time_rx_s, 1, i, it) for i, it in enumerate(items)], key=lambda x: x[:3])
    return [x[3] for x in merged if x[0] >= t_from_s and not cut(x[0])]


def feed(pipeline, item):
    """One item to the Pipeline as the daemon dispatches it; returns on_imu's solution or None."""
    from mavlink_io.samples import FcAttitude, FcEkfStatus, FcHeartbeat, ImuSample, PressureSample
    c = type(item)
    if c is ImuSample:
        sol = pipeline.on_imu(item)
        pipeline.drain_events()
        return sol
    if c is PressureSample:
        pipeline.on_pressure(item)
    elif c is FcAttitude:
        pipeline.on_fc_attitude(item)
    elif c is FcHeartbeat:
        pipeline.on_fc_heartbeat(item)
    elif c is FcEkfStatus:
        pipeline.on_fc_ekf_status(item)
    else:
        raise TypeError(f"not a Pipeline input: {c.__name__}")
    return None
