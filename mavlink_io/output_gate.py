"""What may be published, and when: the solution brought to the send time, and meaningless parts cut.

The outputs go at their configured rates whatever the IMU rate (ArduPilot grants 25 Hz RAW_IMU at its
stock loop rate, 1 Hz without a request). The daemon keeps the last NavSolution and, each time a
message is due, publishes it *brought forward* to the send time:

    age = now - time_rx                  (local monotonic clock, s)
    q(t + age) = q(t) (x) dq,  dq = [cos(|w| age / 2), sin(|w| age / 2) w / |w|]

with w the bias-corrected body rates of the solution (a constant-rate rotation in the body frame: the
exact solution of q_dot = q (x) [0, w] / 2 for constant w), and the FC time stamp advanced by the same
age. Beyond ``max_extrapolation_s`` there is no valid solution and nothing is published: at a 1 Hz
IMU the outputs stop between samples instead of repeating a stale attitude.

``gate_solution`` then removes what its own sigma calls meaningless: roll/pitch with a 1-sigma above
``max_tilt_sigma_rad`` (no ATTITUDE, no quaternion, so no ATTITUDE_QUATERNION and no ODOMETRY: the
FC's EKF takes the yaw from the quaternion, which needs the tilt; hdg_deg still goes), a heading with a 1-sigma above ``max_heading_sigma_rad`` or without
a sigma (ATTITUDE yaw NaN, no ATTITUDE_QUATERNION, no ODOMETRY, no hdg_deg).

Pure functions, no clocks.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from mavlink_io.navsolution import NavSolution


@dataclass(frozen=True, slots=True)
class OutputLimits:
    max_tilt_sigma_rad: float = math.radians(10.0)
    """Roll/pitch 1-sigma above which no attitude is published (config [outputs] max_tilt_sigma_deg)."""
    max_heading_sigma_rad: float = math.radians(15.0)
    """Heading 1-sigma above which no heading is published (config [outputs] max_heading_sigma_deg)."""
    max_extrapolation_s: float = 0.15
    """Oldest solution published, brought forward by its body rates (config [outputs] max_extrapolation_s)."""

    def __post_init__(self):
        for name in ("max_tilt_sigma_rad", "max_heading_sigma_rad", "max_extrapolation_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0.0):
                raise ValueError(f"OutputLimits.{name} must be finite and > 0, got {v!r}")


ODOMETRY_MAX_LAG_S = 0.2
"""Oldest ODOMETRY sent, by its IMU sample against the FC's clock (s). ArduPilot dates an external-nav
sample from its time_usec only within 500 ms (GCS_MAVLINK's jitter correction clamps the lag there),
then EKF3 clamps it to its fusion horizon (its largest sensor delay, about 0.2 s): a yaw older than that
is fused as if it were recent. Flown (ArduPlane SITL, a daemon 26-74 s behind its input on a machine at
load 32): every VISP sample dated 0.55 s before its arrival, EKF3's yaw innovation 65-179 deg, all
rejected by its gate, and EKF3's yaw drifted to +9 deg in 80 s after the GNSS cut."""


@dataclass(slots=True)
class FcLagMeter:
    """How far a solution's FC time stamp lags the FC's clock, seen from the local clock.

    The FC-to-local clock offset is the smallest ``time_rx - time_fc`` seen (the sample that came
    with the least transport delay), as ArduPilot's own jitter correction does, relaxed upward by
    ``relax_s_per_s`` so that an FC clock a little slower than ours (SITL below its speedup) is not
    taken for a growing lag. lag(t_fc, now) = now - (t_fc + offset): 0 for a solution of the newest
    sample computed at once; the backlog when the daemon works through old input."""

    relax_s_per_s: float = 0.005
    """0.5 %: SITL held its speedup to 1.00 (1.99-2.0 at 2) in bench/ardupilot_sitl.py; a lag that lasts
    masks itself at this rate (a 30 s backlog after 6,000 s, a 0.3 s one after 20 s)."""
    offset_s: float | None = None
    _rx_s: float = 0.0

    def on_sample(self, time_fc_s: float, time_rx_s: float) -> None:
        off = time_rx_s - time_fc_s
        if not math.isfinite(off):
            return
        if self.offset_s is not None:
            off = min(off, self.offset_s + self.relax_s_per_s * max(0.0, time_rx_s - self._rx_s))
        self.offset_s, self._rx_s = off, time_rx_s

    def lag_s(self, time_fc_s: float, now_s: float) -> float:
        """0.0 before the first sample."""
        return 0.0 if self.offset_s is None else now_s - (time_fc_s + self.offset_s)

    def reset(self) -> None:
        """The FC rebooted (its clock restarted): learn the offset again."""
        self.offset_s = None


def _finite(x) -> bool:
    return x is not None and math.isfinite(x)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product, scalar first."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def _euler_zyx(q: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of q_nav_from_body, aerospace ZYX."""
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def extrapolate_solution(sol: NavSolution, now_s: float, max_age_s: float) -> NavSolution | None:
    """``sol`` brought forward to local time ``now_s`` (module docstring); None when it is older than
    ``max_age_s``. Sigmas are those of the sample (the rate error over <= max_age_s is far below them)."""
    age = now_s - sol.time_rx_s
    if not math.isfinite(age) or age > max_age_s:
        return None
    if age <= 0.0:
        return sol
    w = sol.rates_body_rad_s
    q = sol.q_nav_from_body
    if q is None or w is None or not np.all(np.isfinite(w)) or not np.all(np.isfinite(q)):
        return replace(sol, time_fc_s=sol.time_fc_s + age, time_rx_s=now_s)
    w = np.asarray(w, dtype=float)
    angle = float(np.linalg.norm(w)) * age
    if angle > 0.0:
        axis = w / np.linalg.norm(w)
        dq = np.concatenate(([math.cos(angle / 2.0)], math.sin(angle / 2.0) * axis))
        q = _quat_mul(np.asarray(q, dtype=float), dq)
        q = q / np.linalg.norm(q)
    roll, pitch, yaw = _euler_zyx(q)
    heading = (yaw % (2.0 * math.pi)) if (sol.heading_valid and _finite(sol.heading_rad)) else sol.heading_rad
    return replace(sol, time_fc_s=sol.time_fc_s + age, time_rx_s=now_s, q_nav_from_body=q,
                   roll_rad=roll if _finite(sol.roll_rad) else sol.roll_rad,
                   pitch_rad=pitch if _finite(sol.pitch_rad) else sol.pitch_rad, heading_rad=heading)


def gate_solution(sol: NavSolution, limits: OutputLimits) -> NavSolution:
    """``sol`` without the parts whose sigma says they are meaningless (module docstring); the reason
    is in ``flags["outputs"]``."""
    why = []
    tilt_sigmas = [s for s in (sol.roll_sigma_rad, sol.pitch_sigma_rad) if s is not None]
    tilt_bad = any(not math.isfinite(s) or s > limits.max_tilt_sigma_rad for s in tilt_sigmas)
    heading_bad = sol.heading_valid and not (_finite(sol.heading_sigma_rad)
                                             and sol.heading_sigma_rad <= limits.max_heading_sigma_rad)
    if not (tilt_bad or heading_bad):
        return sol
    changes = {}
    if tilt_bad:
        why.append(f"roll/pitch sigma {math.degrees(max(tilt_sigmas)):.1f} deg > "
                   f"{math.degrees(limits.max_tilt_sigma_rad):g}: no attitude")
        changes.update(roll_rad=None, pitch_rad=None, q_nav_from_body=None)
    if heading_bad:
        sigma = sol.heading_sigma_rad
        why.append(("heading sigma unknown" if not _finite(sigma) else
                    f"heading sigma {math.degrees(sigma):.1f} deg > {math.degrees(limits.max_heading_sigma_rad):g}")
                   + ": no heading")
        changes.update(heading_valid=False, heading_rad=None, heading_sigma_rad=None, heading_source="none")
    return replace(sol, flags={**sol.flags, "outputs": "; ".join(why)}, **changes)
