"""The FC's accepted messages -> typed samples (mavlink_io.samples), on the FC's own clock.

The unit conversions are :mod:`mavlink_io.decode`'s pure functions; this module adds what needs
state: the FC time of every stamped message through :class:`~mavlink_io.timebase.FcTimebase`
(unwrap, reboot, gap, backlog: reported as LinkEvents, never integrated blindly), the choice of one
IMU stream and one pressure stream (``imu_source``: ArduPilot RAW_IMU > HIGHRES_IMU > SCALED_IMU,
others HIGHRES_IMU first; a lower-priority source is used while no higher one was seen within
link_timeout_s), and STATUSTEXT chunk assembly.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

from mavlink_io import decode as dec
from mavlink_io.link_config import FcPeer, LinkConfig
from mavlink_io.samples import FcAttitude, ImuSample, PressureSample
from mavlink_io.stats import LinkStats
from mavlink_io.timebase import FcTimebase, TimebaseParams

_IMU_PRIORITY = {"ardupilot": ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU"),
                 None: ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU")}
_PRESSURE_PRIORITY = ("SCALED_PRESSURE", "HIGHRES_IMU")
_NAN = float("nan")


def _stamped_pressure(p: PressureSample, t: float) -> PressureSample:
    # the samples at the input rates are rebuilt directly: dataclasses.replace costs ~4x more
    # (tests/test_mavlink_sample_fields.py keeps these field lists in step with samples.py)
    return PressureSample(t, p.time_rx_s, p.press_abs_pa, p.press_diff_pa, p.temperature_k, p.source)


def fc_stamp_s(msg) -> float | None:
    """A message's FC time stamp in seconds (time_usec, else time_boot_ms), None when it has none:
    the link's rates are measured in the sender's clock (stats.FcRateWindow)."""
    us = getattr(msg, "time_usec", None)
    if isinstance(us, int) and us > 0:
        return us * 1e-6
    ms = getattr(msg, "time_boot_ms", None)
    if isinstance(ms, int) and ms > 0:
        return ms * 1e-3
    return None


class SampleDecoder:
    """Decodes the autopilot's messages for one link.

    fc: the autopilot (its family picks the IMU priority); seen_s: message name -> local time last
    received (the link fills it); event(kind, detail, now, items): the link's events;
    on_fc_reboot(rx_s, items): the FC clock restarted (the link re-requests its streams)."""

    def __init__(self, cfg: LinkConfig, stats: LinkStats, fc: FcPeer, seen_s: dict[str, float],
                 event: Callable[[str, str, float, list | None], None],
                 on_fc_reboot: Callable[[float, list], None]):
        self.cfg = cfg
        self.stats = stats
        self.fc = fc
        self._seen_s = seen_s
        self._event = event
        self._on_fc_reboot = on_fc_reboot
        self.timebase = FcTimebase(TimebaseParams(reboot_jump_s=cfg.reboot_jump_s))
        self._statustext = dec.StatusTextAssembler()

    def decode(self, mtype: str, msg, rx_s: float, items: list):
        """Append the samples of ``msg`` (and clock events) to ``items``. STATUSTEXT, PARAM_VALUE
        and COMMAND_ACK are returned instead (the link acts on them, then appends them); None for
        everything else. Raises dec.NonFiniteField (and AttributeError/TypeError/ValueError for a
        malformed field): the link counts it."""
        if mtype in ("RAW_IMU", "SCALED_IMU"):
            fn = dec.decode_raw_imu if mtype == "RAW_IMU" else dec.decode_scaled_imu
            imu = fn(msg, _NAN, rx_s)
            if self._imu_wanted(mtype, imu.imu_id, rx_s):
                self._emit_imu(imu, mtype, msg, rx_s, items)
        elif mtype == "HIGHRES_IMU":
            opt = dec.OptionalFieldCounter()
            imu, press = dec.decode_highres_imu(msg, _NAN, rx_s, opt)
            self.stats.non_finite_optional += opt.count
            if self._imu_wanted(mtype, imu.imu_id, rx_s):
                self._emit_imu(imu, mtype, msg, rx_s, items)
            if press is not None and imu.imu_id == self.cfg.imu_id \
                    and self._preferred("HIGHRES_IMU", _PRESSURE_PRIORITY, rx_s):
                t = self._fc_time("PRESSURE", mtype, msg, rx_s, items)
                if t is not None:
                    items.append(_stamped_pressure(press, t))
        elif mtype == "SCALED_PRESSURE":
            opt = dec.OptionalFieldCounter()
            press = dec.decode_scaled_pressure(msg, _NAN, rx_s, opt)
            self.stats.non_finite_optional += opt.count
            t = self._fc_time("PRESSURE", mtype, msg, rx_s, items)
            if t is not None:
                items.append(_stamped_pressure(press, t))
        elif mtype == "ATTITUDE":
            att = dec.decode_attitude(msg, _NAN, rx_s)
            t = self._fc_time("ATTITUDE", mtype, msg, rx_s, items)
            if t is not None:
                items.append(FcAttitude(t, att.time_rx_s, att.roll_rad, att.pitch_rad, att.yaw_rad, att.rates_rad_s))
        elif mtype == "HEARTBEAT":
            items.append(dec.decode_heartbeat(msg, rx_s))
        elif mtype == "EXTENDED_SYS_STATE":  # the FC's land detector: phase evidence
            items.append(dec.decode_extended_sys_state(msg, rx_s))
        elif mtype == "EKF_STATUS_REPORT":
            opt = dec.OptionalFieldCounter()
            items.append(dec.decode_ekf_status_report(msg, rx_s, opt))
            self.stats.non_finite_optional += opt.count
        elif mtype == "ESTIMATOR_STATUS":
            opt = dec.OptionalFieldCounter()
            st = dec.decode_estimator_status(msg, _NAN, rx_s, opt)
            self.stats.non_finite_optional += opt.count
            t = self._fc_time("ESTIMATOR_STATUS", mtype, msg, rx_s, items)
            if t is not None:
                items.append(dataclasses.replace(st, time_fc_s=t))
        elif mtype == "SYS_STATUS":
            items.append(dec.decode_sys_status(msg, rx_s))
        elif mtype == "STATUSTEXT":
            return dec.decode_statustext(msg, self._statustext, rx_s)
        elif mtype == "PARAM_VALUE":
            return dec.decode_param_value(msg, rx_s, bytewise=self.fc.autopilot == "px4")
        elif mtype == "COMMAND_ACK":
            return dec.decode_command_ack(msg, rx_s)
        return None

    def stamp_raw_imu(self, time_usec: int, imu_id: int, rx_s: float, items: list) -> float | None:
        """The batch path (mavlink_io.imu_batch): one RAW_IMU row's FC time, or None when the row
        is not used (another IMU instance, a preferred IMU stream present, a stale time). The same
        rules, counters and events, in the same order, as ``decode`` of that RAW_IMU message."""
        if not self._imu_wanted("RAW_IMU", imu_id, rx_s):
            return None
        return self._stamp("IMU", time_usec, "us", rx_s, items, self.cfg.imu_gap_s)

    def _fc_time(self, stream: str, mtype: str, msg, rx_s: float, items: list,
                 gap_s: float | None = None) -> float | None:
        fname, unit = dec.TIME_FIELD[mtype]
        return self._stamp(stream, int(getattr(msg, fname)), unit, rx_s, items, gap_s)

    def _stamp(self, stream: str, raw: int, unit: str, rx_s: float, items: list,
               gap_s: float | None) -> float | None:
        t, events = self.timebase.feed(stream, raw, unit, rx_s, gap_s)
        for ev in events:
            self._event(ev.kind, ev.detail, rx_s, items)
            if ev.kind == "fc_reboot":
                self.stats.fc_reboots += 1
                self._on_fc_reboot(rx_s, items)
            elif ev.kind == "time_gap":
                self.stats.time_gaps += 1
            elif ev.kind == "time_wrap":
                self.stats.time_wraps += 1
            elif ev.kind == "input_backlog":  # FC time lags, its clock did not restart: no reboot
                self.stats.input_backlogs += 1
        if t is None:
            self.stats.stale_time_drops += 1
        return t

    def _preferred(self, source: str, priority: tuple[str, ...], rx_s: float) -> bool:
        """True if no higher-priority source of the same kind was seen within link_timeout_s."""
        for other in priority:
            if other == source:
                return True
            seen = self._seen_s.get(other)
            if seen is not None and rx_s - seen <= self.cfg.link_timeout_s:
                return False
        return True

    def _imu_wanted(self, source: str, imu_id: int, rx_s: float) -> bool:
        if imu_id != self.cfg.imu_id:
            return False
        if self.cfg.imu_source != "auto":
            return source == self.cfg.imu_source
        prio = _IMU_PRIORITY["ardupilot" if self.fc.autopilot == "ardupilot" else None]
        return self._preferred(source, prio, rx_s)

    def _emit_imu(self, imu: ImuSample, mtype: str, msg, rx_s: float, items: list) -> None:
        t = self._fc_time("IMU", mtype, msg, rx_s, items, gap_s=self.cfg.imu_gap_s)
        if t is not None:
            items.append(ImuSample(t, imu.time_rx_s, imu.gyro_rad_s, imu.accel_m_s2, imu.mag_gauss, imu.source,
                                   imu.imu_id))
