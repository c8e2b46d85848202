"""What the FC does with our ODOMETRY, read from its parameters: is the placeholder position safe to
send, and does the FC's yaw come from us (then it is no independent reference: the loop).

ArduPilot (source read at 4.7-dev; behaviour flown in ArduPlane SITL, docs/OUTPUTS.md 1.5):
AP_VisualOdom (VISO_TYPE > 0) consumes ODOMETRY and AP_AHRS::writeExtNavData hands every sample to
**both** EKF2 and EKF3, position included, with the position error clamped to at most 100 m
(AP_VisualOdom_MAV: posErr in [VISO_POS_M_NSE, 100]). EKF3 fuses the position only where a source
set names ExternalNav (EK3_SRCn_POSXY/VELXY/POSZ/VELZ = 6). EKF2 has no source selection: it starts
using external-nav position as soon as it has no GNSS ("EKF2 IMU0 is using external nav data"; SITL:
EKF2 took our placeholder at the GNSS cut). No encoding keeps the yaw for EKF3 and the position from
EKF2 (a quality below VISO_QUAL_MIN drops the whole sample; a NaN position makes EKF3 drop the yaw),
so the only safe ArduPilot is one without EKF2: EK2_ENABLE 0. Our yaw is EKF3's when VISO_TYPE > 0,
EKF3 runs and a source set's EK3_SRCn_YAW is 6 (any set: the active one can be switched in flight).

PX4 >= 1.14: EKF2_EV_CTRL bits 0 (horizontal position), 1 (vertical position), 2 (velocity) must be
off; bit 3 (yaw) on means the FC's yaw comes from us. PX4 <= 1.13 has no EKF2_EV_CTRL: its EKF2_AID_MASK
bits 3 (external-vision position) and 8 (velocity) must be off and EKF2_HGT_MODE not 3 (vision height);
bit 4 (external-vision yaw) on means the FC's yaw comes from us (PX4 ecl's fusion_mode masks). A PX4
that answers EKF2_EV_CTRL is judged on it alone, without waiting for the older names.

Anything else gets the spec-literal profile (NaN position: nothing finite to fuse) and its yaw is of
unknown origin ([heading] use_fc_yaw = false says it comes from us).

Pure: ``check_fc_yaw_feed(autopilot, params, missing) -> FcYawFeedCheck``.
"""
from __future__ import annotations

from dataclasses import dataclass

EXTNAV = 6
"""EK3_SRCn_* value for ExternalNav."""
EK3_SETS = (1, 2, 3)
EK3_POSITION_KINDS = ("POSXY", "VELXY", "POSZ", "VELZ")

ARDUPILOT_PARAMS = ("VISO_TYPE", "EK2_ENABLE", "EK3_ENABLE") + tuple(
    f"EK3_SRC{n}_{k}" for n in EK3_SETS for k in EK3_POSITION_KINDS + ("YAW",))
PX4_PARAMS = ("EKF2_EV_CTRL", "EKF2_AID_MASK", "EKF2_HGT_MODE")
PX4_EV_POSITION_BITS = 0b0111
PX4_EV_YAW_BIT = 0b1000
PX4_AID_EV_POSITION_BITS = (1 << 3) | (1 << 8)
"""EKF2_AID_MASK (PX4 <= 1.13): external-vision position (bit 3) and velocity (bit 8)."""
PX4_AID_EV_YAW_BIT = 1 << 4
PX4_HGT_MODE_VISION = 3


def params_for(autopilot: str | None) -> tuple[str, ...]:
    """The parameters ``check_fc_yaw_feed`` needs for this autopilot ("ardupilot", "px4", other)."""
    return {"ardupilot": ARDUPILOT_PARAMS, "px4": PX4_PARAMS}.get(autopilot, ())


@dataclass(frozen=True, slots=True)
class FcYawFeedCheck:
    placeholder_safe: bool | None
    """True: no estimator of the FC can fuse our placeholder position; False: one can (or it cannot
    be verified); None: parameters still being read."""
    fc_yaw_from_us: bool | None
    """True: the FC's yaw comes from our ODOMETRY (never a reference for us); None: unknown."""
    reason: str
    """One line: why, and which parameter to set."""


def _int(params: dict, name: str) -> int | None:
    v = params.get(name)
    return None if v is None else int(round(v))


def check_fc_yaw_feed(autopilot: str | None, params: dict, missing: set) -> FcYawFeedCheck:
    """The verdict from the FC's parameter values (``params``: name -> value; ``missing``: names it
    never answered, i.e. not on this firmware)."""
    wanted = params_for(autopilot)
    if not wanted:
        return FcYawFeedCheck(True, None, "autopilot not ArduPilot or PX4: ODOMETRY position sent as NaN; "
                                          "set [heading] use_fc_yaw = false if the FC's yaw comes from us")
    if autopilot == "px4":
        return _check_px4(params, missing)
    pending = [n for n in wanted if n not in params and n not in missing]
    if pending:
        return _pending(pending)
    viso = _int(params, "VISO_TYPE")
    if viso is None or viso == 0:
        return FcYawFeedCheck(True, False, ("VISO_TYPE not on this firmware" if viso is None else "VISO_TYPE 0")
                              + ": the FC ignores ODOMETRY (VISO_TYPE 1, EK3_SRC1_YAW 6 to fuse our heading)")
    ek2 = _int(params, "EK2_ENABLE")
    if ek2 not in (None, 0):
        return FcYawFeedCheck(False, None, f"EK2_ENABLE {ek2}: EKF2 fuses any external-nav position, our "
                                           "placeholder included (it has no source selection); set EK2_ENABLE 0 "
                                           "(AHRS_EKF_TYPE 3) and reboot; ODOMETRY not sent")
    ek3 = _int(params, "EK3_ENABLE")
    if ek3 == 0:
        return FcYawFeedCheck(True, False, "EK3_ENABLE 0 and no EKF2: no EKF consumes ODOMETRY")
    for n in EK3_SETS:
        for k in EK3_POSITION_KINDS:
            name = f"EK3_SRC{n}_{k}"
            v = _int(params, name)
            if v is None:
                return FcYawFeedCheck(False, None, f"{name} not on this firmware: cannot verify that EKF3 does "
                                                   "not fuse external-nav position; ODOMETRY not sent")
            if v == EXTNAV:
                return FcYawFeedCheck(False, None, f"{name} {EXTNAV} (ExternalNav): EKF3 would fuse our placeholder "
                                                   f"position; set {name} to another source; ODOMETRY not sent")
    yaw_sets = [n for n in EK3_SETS if _int(params, f"EK3_SRC{n}_YAW") == EXTNAV]
    if yaw_sets:
        return FcYawFeedCheck(True, True, "EKF3's yaw comes from our ODOMETRY (VISO_TYPE "
                              f"{viso}, " + ", ".join(f"EK3_SRC{n}_YAW 6" for n in yaw_sets) + ")")
    return FcYawFeedCheck(True, False, "no EK3_SRCn_YAW is 6: EKF3 does not fuse our yaw")


def _pending(names) -> FcYawFeedCheck:
    return FcYawFeedCheck(None, None, f"reading the FC's parameters ({', '.join(names)})")


def _check_px4(params: dict, missing: set) -> FcYawFeedCheck:
    ev = _int(params, "EKF2_EV_CTRL")
    if ev is not None:                                   # PX4 >= 1.14
        from_us = bool(ev & PX4_EV_YAW_BIT)
        if ev & PX4_EV_POSITION_BITS:
            return FcYawFeedCheck(False, from_us, f"EKF2_EV_CTRL {ev} fuses external-vision position/velocity "
                                                  "(bits 0-2): our placeholder would be fused; set EKF2_EV_CTRL 8 "
                                                  "(yaw only); ODOMETRY not sent")
        return FcYawFeedCheck(True, from_us, f"EKF2_EV_CTRL {ev}: " + ("PX4's yaw comes from our ODOMETRY"
                                                                       if from_us else "our yaw not fused"))
    legacy = ("EKF2_AID_MASK", "EKF2_HGT_MODE")
    pending = [n for n in ("EKF2_EV_CTRL",) + legacy if n not in params and n not in missing]
    if pending:
        return _pending(pending)
    mask, hgt = _int(params, "EKF2_AID_MASK"), _int(params, "EKF2_HGT_MODE")
    if mask is None or hgt is None:
        absent = " and ".join(n for n, v in zip(legacy, (mask, hgt)) if v is None)
        return FcYawFeedCheck(False, None, f"neither EKF2_EV_CTRL nor {absent} on this PX4: cannot verify that "
                                           "external-vision position is off; ODOMETRY not sent")
    from_us = bool(mask & PX4_AID_EV_YAW_BIT)
    if mask & PX4_AID_EV_POSITION_BITS:
        yaw_only = (mask & ~PX4_AID_EV_POSITION_BITS) | PX4_AID_EV_YAW_BIT
        return FcYawFeedCheck(False, from_us, f"EKF2_AID_MASK {mask} fuses external-vision position/velocity "
                                              f"(bits 3, 8): our placeholder would be fused; set EKF2_AID_MASK "
                                              f"{yaw_only} (vision yaw, no vision position or velocity); "
                                              "ODOMETRY not sent")
    if hgt == PX4_HGT_MODE_VISION:
        return FcYawFeedCheck(False, from_us, "EKF2_HGT_MODE 3 (vision) fuses our placeholder height; set it to "
                                              "0 (barometer); ODOMETRY not sent")
    return FcYawFeedCheck(True, from_us, f"EKF2_AID_MASK {mask}, EKF2_HGT_MODE {hgt} (PX4 <= 1.13): "
                          + ("PX4's yaw comes from our ODOMETRY" if from_us else "our yaw not fused"))
