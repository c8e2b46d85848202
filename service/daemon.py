"""The daemon: link -> pipeline -> outputs, in one single-threaded loop.

One loop keeps latency low and the order of events obvious: poll the FC link for a few
milliseconds, hand each decoded sample to the Pipeline, send what is due, repeat. Nothing in the
loop may raise out of it because of bad input: the link counts bad bytes, the pipeline rejects
bad samples with a reason, the outputs count send failures.
"""
from __future__ import annotations

import logging
import math
import signal
import sys
import time

from pymavlink.dialects.v20 import common as mavlink2

from mavlink_io.link import LinkConfig, LinkEvent, MavlinkLink
from mavlink_io.samples import FcAttitude, FcEkfStatus, FcHeartbeat, ImuSample, PressureSample
from service.logs import RateLimitedLog
from service.pipeline import Pipeline
from service.solution import NavSolution

log = logging.getLogger("azimuthd.daemon")


def _fmt_angle(rad: float | None, sigma: float | None, width: int = 6) -> str:
    if rad is None or not math.isfinite(rad):
        return "-".rjust(width) + "         "
    s = f"{math.degrees(rad):+{width}.1f}"
    if sigma is not None and math.isfinite(sigma):
        s += f" +/-{math.degrees(sigma):4.1f}"
    else:
        s += "         "
    return s


def status_line(sol: NavSolution | None, rates: dict[str, float], link_up: bool) -> str:
    """The one-line live status: phase, roll/pitch/heading with sigma, link rates."""
    if sol is None:
        head = "phase=boot"
    else:
        hdg = None
        if sol.heading_valid and sol.heading_rad is not None:
            hdg = _fmt_angle(sol.heading_rad, sol.heading_sigma_rad).replace("+", " ", 1)
        head = (f"phase={sol.phase:<9} roll={_fmt_angle(sol.roll_rad, sol.roll_sigma_rad)} "
                f"pitch={_fmt_angle(sol.pitch_rad, sol.pitch_sigma_rad)} "
                f"hdg={hdg if hdg else '     -         '} src={sol.heading_source}")
    r = " ".join(f"{k.lower()}={v:.0f}Hz" for k, v in sorted(rates.items()) if k in _SHOWN_RATES)
    return f"{head} | link={'up' if link_up else 'DOWN'} {r}"


_SHOWN_RATES = ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU", "SCALED_PRESSURE", "ATTITUDE")


class Daemon:
    def __init__(self, cfg: dict, clock=time.monotonic):
        self.cfg = cfg
        self.clock = clock
        m = cfg["mavlink"]
        rates = {"RAW_IMU": m["imu_rate_hz"], "HIGHRES_IMU": m["imu_rate_hz"],
                 "SCALED_PRESSURE": m["pressure_rate_hz"], "ATTITUDE": m["attitude_rate_hz"],
                 "EKF_STATUS_REPORT": 2.0, "SYS_STATUS": 2.0}
        self.link_cfg = LinkConfig(url=m["url"], component_id=m["component_id"],
                                   system_id=m["system_id"] or None, heartbeat_hz=m["heartbeat_hz"],
                                   link_timeout_s=m["link_timeout_s"], imu_gap_s=m["imu_gap_s"],
                                   stream_rates_hz=rates)
        self.pipeline = Pipeline(cfg)
        self.link: MavlinkLink | None = None
        self.extra_ports: list = []
        self.stop_requested = False
        self.last_solution: NavSolution | None = None
        self.rl = RateLimitedLog(log, 10.0, clock)
        out = cfg["outputs"]
        self.attitude_period_s = 1.0 / out["attitude_hz"]
        self.status_interval_s = out["status_interval_s"]
        self._next_attitude_rx_s = 0.0
        self._next_status_s = 0.0
        self._next_extra_heartbeat_s = 0.0
        self.sent = {"ATTITUDE": 0}

    # --- lifecycle ----------------------------------------------------------------------------

    def _on_signal(self, signum, _frame) -> None:
        log.info("signal received, shutting down", extra={"fields": {"signal": signal.Signals(signum).name}})
        self.stop_requested = True

    def open(self) -> None:
        self.link = MavlinkLink(self.link_cfg, clock=self.clock)
        from pymavlink import mavutil
        for url in self.cfg["outputs"]["extra_mavlink_urls"]:
            conn = mavutil.mavlink_connection(url, source_system=1, source_component=self.link_cfg.component_id,
                                              dialect="ardupilotmega")
            self.extra_ports.append(conn)
        log.info("started", extra={"fields": {"mavlink": self.link_cfg.url,
                                              "extra_outputs": len(self.extra_ports)}})

    def close(self) -> None:
        if self.link is not None:
            self.link.close()
        for p in self.extra_ports:
            try:
                p.close()
            except OSError:
                pass
        log.info("stopped", extra={"fields": {"imu_samples": self.pipeline.counters.imu_samples,
                                              "imu_rejected": self.pipeline.counters.imu_rejected,
                                              "attitude_sent": self.sent["ATTITUDE"]}})

    def run(self, duration_s: float | None = None) -> int:
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self._on_signal)
        self.open()
        t_end = None if duration_s is None else self.clock() + duration_s
        try:
            while not self.stop_requested:
                self.step(0.005)
                if t_end is not None and self.clock() >= t_end:
                    break
        finally:
            self.close()
        return 0

    # --- the loop -----------------------------------------------------------------------------

    def step(self, timeout_s: float) -> None:
        for item in self.link.poll(timeout_s=timeout_s):
            self.dispatch(item)
        now = self.clock()
        if self.extra_ports and now >= self._next_extra_heartbeat_s:
            # ground stations and MAVLink clients discover a component by its HEARTBEAT
            self._next_extra_heartbeat_s = now + 1.0 / self.cfg["mavlink"]["heartbeat_hz"]
            self._send_extra(self.link.mav.heartbeat_encode(mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
                                                            mavlink2.MAV_AUTOPILOT_INVALID, 0, 0,
                                                            mavlink2.MAV_STATE_ACTIVE))
        if self.status_interval_s > 0 and now >= self._next_status_s:
            self._next_status_s = now + self.status_interval_s
            print(status_line(self.last_solution, self.link.stats.rates_hz(), self.link.connected),
                  flush=True)

    def dispatch(self, item) -> None:
        if isinstance(item, ImuSample):
            sol = self.pipeline.on_imu(item)
            if sol is not None:
                self.last_solution = sol
                self.publish(sol)
            for kind, detail in self.pipeline.drain_events():
                log.info(detail, extra={"fields": {"event": kind}})
        elif isinstance(item, PressureSample):
            self.pipeline.on_pressure(item)
        elif isinstance(item, FcAttitude):
            self.pipeline.on_fc_attitude(item)
        elif isinstance(item, LinkEvent):
            log.info(item.detail, extra={"fields": {"event": item.kind}})
            if item.kind == "fc_reboot":
                self.pipeline.on_fc_reboot()
        elif isinstance(item, (FcHeartbeat, FcEkfStatus)):
            pass

    # --- outputs ------------------------------------------------------------------------------

    def _send(self, msg) -> None:
        self.link.send(msg)
        self._send_extra(msg)

    def _send_extra(self, msg) -> None:
        for p in self.extra_ports:
            try:
                p.mav.srcSystem = self.link.mav.srcSystem
                p.mav.send(msg)
            except OSError as exc:
                self.rl.log(logging.WARNING, "extra_send", "extra output send failed", error=str(exc))

    def publish(self, sol: NavSolution) -> None:
        if sol.q_nav_from_body is None or sol.time_rx_s < self._next_attitude_rx_s:
            return
        self._next_attitude_rx_s = sol.time_rx_s + self.attitude_period_s * 0.98
        yaw = float("nan")
        if sol.heading_valid and sol.heading_rad is not None:
            yaw = math.remainder(sol.heading_rad, 2 * math.pi)  # MAVLink ATTITUDE yaw is in (-pi, pi]
        p, q, r = (float(v) for v in sol.rates_body_rad_s)
        msg = self.link.mav.attitude_encode(int(sol.time_fc_s * 1000) & 0xFFFFFFFF, sol.roll_rad, sol.pitch_rad,
                                            yaw, p, q, r)
        self._send(msg)
        self.sent["ATTITUDE"] += 1


def main() -> int:  # pragma: no cover - the console entry is service.cli
    from service.cli import main as cli_main
    return cli_main(["run", *sys.argv[1:]])
