"""Kinematic truth derived from the sampled trajectory states.

Per sample k at t_k (dt = t_k - t_{k-1}); the IMU sample k is the average over (t_{k-1}, t_k]
(what a delta-angle / delta-velocity IMU reports, divided by dt):

  q_k            = qz(psi) qy(gamma) qx(phi) qy(alpha)                      (q_nav_from_body)
  omega_nb_k     = rotvec(q_{k-1}* q_k) / dt                                (body rate w.r.t. NED)
  omega_ib_k     = omega_nb_k + C_body_from_nav (omega_ie + omega_en)       (what a gyro measures)
  f_nav_k        = (v_k - v_{k-1}) / dt + (2 omega_ie + omega_en) x v - g_nav,  g_nav = [0, 0, g]
  f_body_k       = C_body_from_nav f_nav_k                                  (at rest, level: [0, 0, -g])

with the frame rates and C_body_from_nav at the interval's midpoint. Integrating omega_nb with
the exact exponential reproduces q_k to rounding; integrating f_nav reproduces v_k.
"""
from __future__ import annotations

import numpy as np

from sim import earth
from sim.frames import dcm_from_q, q_axis, qconj, qmul, qnormalize, rotvec_from_q


def attitude_from_states(psi, gamma, phi, alpha) -> np.ndarray:
    q = qmul(qmul(q_axis(2, psi), q_axis(1, gamma)), qmul(q_axis(0, phi), q_axis(1, alpha)))
    return qnormalize(q)


class TruthDeriver:
    """Stateful (carries the previous sample across chunks) derivation of rates and forces."""

    def __init__(self):
        self.prev: dict | None = None

    def __call__(self, st: dict) -> dict:
        q = attitude_from_states(st["psi"], st["gamma"], st["phi"], st["alpha"])
        # keep quaternion sign continuous
        n = len(q)
        if n == 0:
            return {}
        prev = self.prev or {"q": q[0], "v": st["vel_ned_m_s"][0], "lat": st["lat_rad"][0],
                             "h": st["alt_m"][0], "t": st["time_s"][0] - (st["time_s"][1] - st["time_s"][0]
                                                                           if n > 1 else 0.005)}
        q_prev = np.vstack([prev["q"][None, :], q[:-1]])
        v = st["vel_ned_m_s"]
        v_prev = np.vstack([prev["v"][None, :], v[:-1]])
        t_prev = np.concatenate([[prev["t"]], st["time_s"][:-1]])
        dt = (st["time_s"] - t_prev)[:, None]
        lat_mid = 0.5 * (st["lat_rad"] + np.concatenate([[prev["lat"]], st["lat_rad"][:-1]]))
        h_mid = 0.5 * (st["alt_m"] + np.concatenate([[prev["h"]], st["alt_m"][:-1]]))
        v_mid = 0.5 * (v + v_prev)
        dq = qmul(qconj(q_prev), q)
        omega_nb = rotvec_from_q(dq) / dt
        sgn = np.where(np.sum(q * q_prev, axis=1) < 0, -1.0, 1.0)[:, None]
        q_mid = qnormalize(q_prev + sgn * q)
        C_nb_mid = dcm_from_q(q_mid)  # C_nav_from_body
        w_ie = earth.earth_rate_ned(lat_mid)
        w_en = earth.transport_rate_ned(lat_mid, h_mid, v_mid)
        w_in_body = np.einsum("nji,nj->ni", C_nb_mid, w_ie + w_en)
        omega_ib = omega_nb + w_in_body
        g = earth.gravity_m_s2(lat_mid, h_mid)
        f_nav = (v - v_prev) / dt + np.cross(2.0 * w_ie + w_en, v_mid)
        f_nav[:, 2] -= g
        f_body = np.einsum("nji,nj->ni", C_nb_mid, f_nav)
        self.prev = {"q": q[-1], "v": v[-1], "lat": st["lat_rad"][-1], "h": st["alt_m"][-1],
                     "t": st["time_s"][-1]}
        C_bn = dcm_from_q(q)
        air_body = np.einsum("nji,nj->ni", C_bn, st["air_ned_m_s"])
        return {"q_nav_from_body": q, "omega_nb_body_rad_s": omega_nb, "omega_body_rad_s": omega_ib,
                "f_body_m_s2": f_body, "gravity_m_s2": g, "air_body_m_s": air_body,
                "airspeed_m_s": np.linalg.norm(st["air_ned_m_s"], axis=1)}
