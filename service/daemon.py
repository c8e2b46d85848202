"""The daemon: link -> pipeline -> outputs, in one single-threaded loop.

One loop keeps latency low and the order of events obvious: poll the FC link for a few
milliseconds, hand each decoded sample to the Pipeline, send what is due, repeat. Nothing in the
loop may raise out of it because of bad input: the link counts bad bytes, the pipeline rejects
bad samples with a reason, the outputs count send failures, a Zenoh session that cannot open is
retried while MAVLink carries on.

systemd (Type=notify): READY=1 once the daemon is up (its link opened, before any FC answers: a
bench without an FC must not fail the unit's start), with STATUS="waiting for the flight controller
on URL" (also logged every WAITING_LOG_S) until the autopilot's HEARTBEAT; WATCHDOG=1 from this
loop, STATUS= with the phase and heading every few seconds. SIGHUP (systemctl reload) saves the
calibrations and checks the config file: a changed file is reported with the keys that differ and
applied by a restart; the daemon runs on with the config it started with (never stops on SIGHUP).
"""
from __future__ import annotations

import gc
import logging
import math
import os
import pathlib
import signal
import time
import traceback

from pymavlink.dialects.v20 import common as mavlink2

from mavlink_io import frame_pack
from mavlink_io.commands import CommandProtocol, CommandProtocolParams, statustext_message
from mavlink_io.decode import FcParam, FcStatusText
from mavlink_io.imu_batch import ImuBatch
from mavlink_io.link import LinkConfig, LinkEvent, MavlinkLink
from mavlink_io.outputs import CATCH_UP_MAX_LAG_S, OutputScheduler, _time_boot_ms, odometry_profile_for_autopilot
from mavlink_io.outputs import encode_attitude, encode_attitude_quaternion
from mavlink_io.output_gate import FcLagMeter, OutputLimits, gate_solution
from mavlink_io.samples import (CommandAck, FcAttitude, FcEkfStatus, FcFlightState, FcHeartbeat, FcSysStatus,
                                ImuSample, IncomingCommand, PressureSample)
from service import link_core, state_file
from service.calibration_keeper import CalibrationKeeper
from service.vehicle_type import param_names as vehicle_param_names
from service.command_server import MSG_ATTITUDE, MSG_ATTITUDE_QUATERNION, MSG_HEARTBEAT, CommandServer
from service.config import state_dir
from service.fc_yaw_guard import FcYawGuard
from service.link_health import InputLossMonitor
from service.logs import RateLimitedLog
from service.pipeline import Pipeline
from service.sdnotify import Notifier
from mavlink_io.navsolution import NavSolution

log = logging.getLogger("azimuthd.daemon")

ZENOH_RETRY_S = 30.0
HEALTH_PERIOD_S = 1.0
AIR_DATA_PERIOD_S = 0.5
FENCE_GEOMETRY_PERIOD_S = 5.0
"""The fence polygons ride on every geofence message this often (a dashboard that joins late
draws the fence within this time; they are too large to send at the state's 2 Hz)."""
_CALIBRATION_EVENTS = {"levelled": ("levelling", "done"), "declination": ("declination", "done"),
                       "deviation": ("mag_deviation", "converging")}
"""Pipeline events that are calibration steps: also published on the ``calibration`` topic."""
CALIBRATION_SAVE_S = 30.0
DEVIATION_FILE = "deviation.json"
DEVIATION_FORMAT = "azimuthd-magnetometer-deviation"
SIGNING_FILE = "signing.json"
SIGNING_FORMAT = "azimuthd-mavlink-signing-timestamp"
SIGNING_RESTART_MARGIN = 6_000_000
"""10-us units (60 s) added to the persisted signing timestamp at start: it is saved every
CALIBRATION_SAVE_S, and our timestamps may have advanced that much (plus 10 us per message sent)
since; a receiver rejects a timestamp that goes back."""
SD_STATUS_PERIOD_S = 5.0
WAITING_LOG_S = 10.0
"""Period of the "waiting for heartbeat" message until the FC's first HEARTBEAT."""
IMU_SILENCE_SHOWN_S = 1.0
FAULTS_BEFORE_REBUILD = 20
"""Consecutive inputs whose handling raised before the Pipeline is built afresh (``Daemon.dispatch``)."""
LOOP_MAX_WAIT_S = 0.1
"""The loop blocks on the FC link until input arrives or a timer is due (the link's own: heartbeat,
link timeout, rate and parameter retries; the next MAVLink output; the command protocol's next try),
and at most this long: the periodic work (watchdog, status, health, saves: periods >= 0.5 s) and a
stop or reload signal wait at most this when no input comes. It used to wake every 5 ms."""
_SHOWN_RATES = ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU", "SCALED_PRESSURE", "ATTITUDE")
_EVENT_SEVERITY = {"internal_fault": "error", "pipeline_rebuilt": "warning", "rates_limited": "warning", "link_lost": "warning", "fc_reboot": "warning", "time_gap": "warning",
                   "transport_error": "error", "not_still": "info", "strapdown": "warning",
                   "imu_input": "warning", "signature_rejected": "warning",
                   "unsigned_command_rejected": "warning", "input_overflow": "warning", "input_loss": "warning",
                   "loop_stall": "warning", "command": "info", "started_in_flight": "warning",
                   "input_backlog": "warning"}


def _snapshot_time_fc_s(snap) -> float:
    """The FC time of a Pipeline.propagated_snapshot that is not a NavSolution: (solution, (q, time_s,
    rx, gyro) of the output attitude, phase, gyro bias)."""
    return snap[1][1]


def _fmt_angle(rad: float | None, sigma: float | None, width: int = 6) -> str:
    if rad is None or not math.isfinite(rad):
        return "-".rjust(width) + "         "
    s = f"{math.degrees(rad):+{width}.1f}"
    if sigma is not None and math.isfinite(sigma):
        s += f" +/-{math.degrees(sigma):4.1f}"
    else:
        s += "         "
    return s


def status_line(sol: NavSolution | None, rates: dict[str, float], link_up: bool,
                imu_silent_s: float | None = None) -> str:
    """The one-line live status: phase, roll/pitch/heading with sigma, link rates (wall-clock Hz over
    the last 2 s of receive time). imu_silent_s: time since the newest IMU sample handled was read;
    from IMU_SILENCE_SHOWN_S on, the line says so: the FC's sensor streams stopped, the sender
    stalled, or this loop is behind (a batch read at once is stamped with its read time), which is
    also when the rates read 0 Hz while the link is up."""
    if sol is None:
        head = "phase=boot"
    else:
        hdg = "     -         "
        if sol.heading_valid and sol.heading_rad is not None:
            hdg = f"{math.degrees(sol.heading_rad) % 360.0:6.1f}"
            hdg += (f" +/-{math.degrees(sol.heading_sigma_rad):4.1f}"
                    if sol.heading_sigma_rad is not None else "         ")
        head = (f"phase={sol.phase:<9} roll={_fmt_angle(sol.roll_rad, sol.roll_sigma_rad)} "
                f"pitch={_fmt_angle(sol.pitch_rad, sol.pitch_sigma_rad)} hdg={hdg} src={sol.heading_source}")
    r = " ".join(f"{k.lower()}={v:.0f}Hz" for k, v in sorted(rates.items()) if k in _SHOWN_RATES)
    silent = ""
    if link_up and imu_silent_s is not None and imu_silent_s >= IMU_SILENCE_SHOWN_S:
        silent = f" (last IMU read {imu_silent_s:.1f} s ago)"
    return f"{head} | link={'up' if link_up else 'DOWN'} {r}{silent}"


def changed_keys(old: dict, new: dict) -> list[str]:
    """'section.key' of every value that differs between two validated configs ('section' for a
    section that is not a table, e.g. geofence)."""
    out = []
    for sec in sorted(set(old) | set(new)):
        a, b = old.get(sec), new.get(sec)
        if isinstance(a, dict) and isinstance(b, dict):
            out += [f"{sec}.{k}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
        elif a != b:
            out.append(sec)
    return out


class Daemon:
    def __init__(self, cfg: dict, clock=time.monotonic):
        self.cfg = cfg
        self.clock = clock
        m = cfg["mavlink"]
        rates = {"RAW_IMU": m["imu_rate_hz"], "HIGHRES_IMU": m["imu_rate_hz"],
                 "SCALED_PRESSURE": m["pressure_rate_hz"], "ATTITUDE": m["attitude_rate_hz"],
                 "EKF_STATUS_REPORT": 2.0, "SYS_STATUS": 2.0,
                 "EXTENDED_SYS_STATE": 2.0}  # the FC's land detector: take-off evidence (service/phases.py)
        self.geofence_cfg = cfg.get("geofence")
        if self.geofence_cfg is not None:
            rates["GLOBAL_POSITION_INT"] = 5.0  # the FC's position while GNSS is healthy (DR start)
        self.signing_key = None
        self.signing_path = state_dir(cfg) / SIGNING_FILE
        floor = 0
        if m["signing_key_file"]:
            from service.signing_key import load_signing_key
            self.signing_key = load_signing_key(m["signing_key_file"])  # SigningKeyError: exit 2
            floor = self._load_signing_floor()
        self.link_cfg = LinkConfig(url=m["url"], component_id=m["component_id"],
                                   system_id=m["system_id"] or None, heartbeat_hz=m["heartbeat_hz"],
                                   link_timeout_s=m["link_timeout_s"], imu_gap_s=m["imu_gap_s"],
                                   stream_rates_hz=rates,
                                   signing_key=self.signing_key.secret if self.signing_key else None,
                                   sign_outgoing=m["sign_outgoing"], require_signed=m["require_signed"],
                                   signing_timestamp_floor=floor, udp_rcvbuf_bytes=m["udp_rcvbuf_bytes"],
                                   imu_batch=m["imu_batch"])  # a read's RAW_IMU samples as one ImuBatch
        self.calibration = CalibrationKeeper(state_dir(cfg), clock=time.time)
        kf1_learn, kf1_applied = self.calibration.start()
        self.kf1_loaded = kf1_applied is not None
        from service.solver import make_solver
        solver = make_solver(cfg["azimuth"]["solve_in_background"])
        self.deviation_path = state_dir(cfg) / DEVIATION_FILE
        self.pipeline = Pipeline(cfg, kf1_learn=kf1_learn, kf1_applied=kf1_applied, solver=solver,
                                 deviation=self._load_deviation())
        self._kf1_applied_at_start = kf1_applied
        self.internal_faults = 0
        """Inputs whose handling raised (a defect of ours, contained: see ``dispatch``)."""
        self.faults_in_row: dict[str, int] = {}
        """Per input type (ImuSample, PressureSample...): its inputs that failed since its last success."""
        self.pipeline_rebuilds = 0
        out = cfg["outputs"]
        self.scheduler = OutputScheduler({"ATTITUDE": out["attitude_hz"], "ATTITUDE_QUATERNION": out["attitude_hz"],
                                          "ODOMETRY": out["odometry_hz"],
                                          "NAMED_VALUE_FLOAT": out["named_value_hz"]})
        # outputs at their rates whatever the IMU rate: the last solution brought to the send time,
        # cut where its sigma says it is meaningless (mavlink_io/output_gate.py)
        self._last_solution_s = -math.inf
        self._last_sent_fc_s = -math.inf
        """FC time stamp of the last MAVLink output: a stamp never goes back (until an FC reboot)."""
        self._last_sent_sol = None
        """The solution last sent (the same one may fill a later slot with its own stamp)."""
        self._offered_sol = None
        """The solution last offered to the scheduler's FC-time slots (``_publish_due``)."""
        self._pending_prop = None
        """Pipeline.propagated_snapshot of the newest IMU sample, not built into a NavSolution yet:
        ``last_solution`` builds it when read (an output slot, a reader), most samples reach neither."""
        self._offered_snap = None
        """The pending snapshot last offered to the slots (``_publish_due``)."""
        self._last_solution: NavSolution | None = None
        self.output_limits = OutputLimits(math.radians(out["max_tilt_sigma_deg"]),
                                          math.radians(out["max_heading_sigma_deg"]), out["max_extrapolation_s"])
        self.attitude_to_fc = out["attitude_to_fc"]
        self.fc_lag = FcLagMeter()  # how late a solution is against the FC's clock (ODOMETRY held back)
        self.fc_yaw_guard = FcYawGuard()
        if not cfg["heading"].get("use_fc_yaw", True):
            self.fc_yaw_guard.configured_exclusion()
        self.scheduler.odometry_allowed = False  # until the FC's parameters say the placeholder is safe
        self.status_interval_s = out["status_interval_s"]
        self.link: MavlinkLink | None = None
        self.extra_ports: list = []
        self.bus = None
        self.notifier = Notifier.from_env()
        self.stop_requested = False
        self.last_solution: NavSolution | None = None
        self.rl = RateLimitedLog(log, 10.0, clock)
        self.sent: dict[str, int] = {}
        self.fc_heartbeat: FcHeartbeat | None = None
        self.ready_sent = False
        """True once the FC's first HEARTBEAT arrived (READY=1 itself is sent by open())."""
        self.config_file: tuple[str, dict] | None = None
        """(path, the config as that file said at start, before command-line overrides): SIGHUP
        re-reads the path and compares (service/cli.py sets it)."""
        self.reload_requested = False
        self._last_imu_rx_s: float | None = None
        self.started_s = clock()
        self.geofence = None
        self.commands: CommandProtocol | None = None
        self.gnss = {"sys": None, "ekf": None}
        self.command_server = CommandServer(m["accept_commands"], fence_configured=self.geofence_cfg is not None)
        self.loss_monitor = InputLossMonitor()
        self._last_step_s: float | None = None
        self._unsigned_seen = 0
        if self.geofence_cfg is not None:
            from service.geofence import GeofenceMonitor
            site = cfg["site"]
            self.geofence = GeofenceMonitor(self.geofence_cfg, site["lat_deg"], site["lon_deg"], site["alt_m"])
        self._next = {"status": 0.0, "extra_hb": 0.0, "health": 0.0, "sd_status": 0.0, "zenoh_retry": 0.0,
                      "geofence_state": 0.0, "calibration": clock() + CALIBRATION_SAVE_S, "waiting": 0.0,
                      "air_data": 0.0, "fence_geometry": 0.0}
        self._air_time_s: float | None = None

    # --- lifecycle ----------------------------------------------------------------------------

    def _on_signal(self, signum, _frame) -> None:
        log.info("signal received, shutting down", extra={"fields": {"signal": signal.Signals(signum).name}})
        self.stop_requested = True

    def _on_sighup(self, _signum, _frame) -> None:
        self.reload_requested = True  # handled in the loop (a signal handler must not do file I/O)

    def _reload(self) -> None:
        """SIGHUP: save what was learnt, then check the config file; never stop, never apply."""
        self.reload_requested = False
        kf1_saved = self.calibration.save(self.pipeline.kf1_estimate())
        self._save_deviation()
        self._save_signing_timestamp()
        log.info("SIGHUP: state saved", extra={"fields": {"mag_error_estimate_saved": kf1_saved}})
        if self.config_file is None:
            return
        from service.config import ConfigError, load
        path, started_with = self.config_file
        try:
            changed = changed_keys(started_with, load(path))
        except ConfigError as exc:
            log.error("SIGHUP: the config file is not valid; the daemon runs on with the config it started with",
                      extra={"fields": {"error": str(exc)}})
            return
        if changed:
            log.warning("SIGHUP: the config file changed: restart to apply (systemctl restart azimuthd); the "
                        "daemon runs on with the config it started with",
                        extra={"fields": {"changed": ",".join(changed), "config": path}})
        else:
            log.info("SIGHUP: the config file is unchanged", extra={"fields": {"config": path}})

    def open(self) -> None:
        self.link = MavlinkLink(self.link_cfg, clock=self.clock, frame_scan=link_core.frame_scan())
        for url in self.cfg["outputs"]["extra_mavlink_urls"]:
            from pymavlink import mavutil   # here: it loads pymavlink's "all" dialects (~0.4 s CPU)
            from mavlink_io.url import parse_url
            conn = mavutil.mavlink_connection(parse_url(url, "out").pymavlink_url, source_system=1,
                                              source_component=self.link_cfg.component_id, dialect="ardupilotmega")
            if self.signing_key is not None and self.link_cfg.sign_outgoing:
                # each output link its own signing link id (a receiver keeps one timestamp per link id)
                conn.setup_signing(self.signing_key.secret, sign_outgoing=True,
                                   initial_timestamp=self.link.signing_timestamp, link_id=len(self.extra_ports) + 1)
            self.extra_ports.append(conn)
        if self.geofence is not None:
            gf = self.geofence_cfg
            self.commands = CommandProtocol(
                self.link.send, lambda: (self.link.target_system, self.link.target_component),
                CommandProtocolParams(ack_timeout_s=gf.command_timeout_s, max_tries=gf.command_tries))
            self.link.subscribe(self._on_raw, types=("GLOBAL_POSITION_INT",))
        self._open_zenoh()
        self._log_security()
        log.info("started", extra={"fields": {"mavlink": self.link_cfg.url, "extra_outputs": len(self.extra_ports),
                                              "zenoh": self.bus is not None}})
        self.notifier.notify(f"READY=1\nSTATUS=waiting for the flight controller on {self.link_cfg.url}")

    def _open_zenoh(self) -> None:
        z = self.cfg["zenoh"]
        if not z["enabled"] or self.bus is not None:
            return
        from service.zenoh_bus import ZenohBus, ZenohBusError
        tls = {k: z[f"tls_{k}"] for k in ("root_ca", "cert", "key") if z[f"tls_{k}"]}
        try:
            self.bus = ZenohBus(self.cfg["vehicle"]["name"], mode=z["mode"], listen=z["listen"],
                                connect=z["connect"], tls=tls or None)
        except (ZenohBusError, ValueError) as exc:
            self.rl.log(logging.ERROR, "zenoh_open", "zenoh unavailable; MAVLink outputs continue, retrying",
                        error=str(exc), retry_s=ZENOH_RETRY_S)
            self._next["zenoh_retry"] = self.clock() + ZENOH_RETRY_S
            return
        self._publish_calibration_loaded()

    def _publish_calibration(self, kind: str, status: str, detail: str, **values) -> None:
        if self.bus is not None:
            from service.zenoh_bus import calibration_payload
            sol = self.last_solution
            self.bus.publish("calibration", calibration_payload(
                kind, status, detail, self.clock(), sol.time_fc_s if sol else None, **values))

    def _publish_calibration_loaded(self) -> None:
        """What the store handed this run: method B's magnetometer errors and method D's coefficients."""
        if self.kf1_loaded:
            self._publish_calibration("mag_error_kf1", "loaded", f"flight {self.calibration.flight_id}: "
                                      "magnetometer errors learnt on an earlier flight applied")
        else:
            self._publish_calibration("mag_error_kf1", "started", f"flight {self.calibration.flight_id}: "
                                      "no estimate from an earlier flight; learning on this one")
        if self.pipeline.deviation is not None and self.deviation_path.exists():
            self._publish_calibration("mag_deviation", "loaded", f"coefficients from {self.deviation_path}")

    def _log_security(self) -> None:
        m = self.cfg["mavlink"]
        granted = self.link.udp_rcvbuf_bytes_granted
        if granted is not None and granted // 2 < m["udp_rcvbuf_bytes"]:
            log.warning("the kernel capped the UDP receive buffer (net.core.rmem_max): a burst the daemon cannot "
                        "absorb is dropped and reported as input_overflow; docs/SECURITY.md says how to raise it",
                        extra={"fields": {"asked_bytes": m["udp_rcvbuf_bytes"], "effective_bytes": granted // 2}})
        if os.geteuid() == 0:
            log.warning("running as root: nothing in azimuthd needs it; the systemd unit runs it as an "
                        "unprivileged dynamic user (systemd/azimuthd.service)")
        if self.signing_key is not None:
            log.info("mavlink signing on", extra={"fields": {
                "key_fingerprint": self.signing_key.fingerprint, "sign_outgoing": m["sign_outgoing"],
                "require_signed": m["require_signed"]}})
        elif m["accept_commands"]:
            log.warning("mavlink signing off: anyone on the link can send commands to our component "
                        "(set [mavlink] signing_key_file, docs/SECURITY.md)")

    def _load_signing_floor(self) -> int:
        """The outgoing signing timestamp of the last run (+ margin): never sign backwards, even on a
        companion computer without a real-time clock."""
        payload, status = state_file.read_document(self.signing_path, SIGNING_FORMAT, 1, "signing")
        if status.startswith("corrupt"):
            log.error("signing timestamp file damaged, set aside", extra={"fields": {"status": status}})
        try:
            last = int(payload["timestamp_10us"]) if payload is not None else 0
        except (KeyError, TypeError, ValueError):
            last = 0
        return last + SIGNING_RESTART_MARGIN if last > 0 else 0

    def _save_signing_timestamp(self) -> None:
        ts = self.link.signing_timestamp if self.link is not None else None
        if ts is None:
            return
        err = state_file.write_document(self.signing_path, SIGNING_FORMAT, 1, {"timestamp_10us": int(ts)})
        if err:
            self.rl.log(logging.ERROR, "signing_save", "signing timestamp not saved", error=err)

    def _load_deviation(self):
        """Method D's coefficients from the state directory (a damaged file is set aside)."""
        from estimators.mag_deviation import DeviationState
        payload, status = state_file.read_document(self.deviation_path, DEVIATION_FORMAT, 1, "deviation")
        if status.startswith("corrupt"):
            log.error("deviation file damaged, set aside", extra={"fields": {"status": status}})
        if payload is None:
            return None
        try:
            return DeviationState.from_dict(payload["state"])
        except (KeyError, TypeError, ValueError) as exc:
            log.error("deviation file unusable, set aside", extra={"fields": {
                "error": str(exc), "moved_to": str(state_file.set_aside(self.deviation_path))}})
            return None

    def _save_deviation(self) -> None:
        dev = self.pipeline.deviation
        if dev is None or not self.cfg["deviation"]["calibrate"]:
            return
        err = state_file.write_document(self.deviation_path, DEVIATION_FORMAT, 1, {"state": dev.to_dict()})
        if err:
            self.rl.log(logging.ERROR, "deviation_save", "deviation coefficients not saved", error=err)

    def close(self) -> None:
        self.notifier.notify("STOPPING=1")
        self.calibration.save(self.pipeline.kf1_estimate(), final=True)
        self._save_deviation()
        self._save_signing_timestamp()
        self.pipeline.solver.close()
        if self.bus is not None:
            self.bus.close()
        if self.link is not None:
            self.link.close()
        for p in self.extra_ports:
            try:
                p.close()
            except OSError:
                pass
        c = self.pipeline.counters
        fields = {"imu_samples": c.imu_samples, "imu_rejected": c.imu_rejected, "sent": self.sent,
                  "internal_faults": self.internal_faults, "pipeline_rebuilds": self.pipeline_rebuilds,
                  # output slots not sent (late, gap) or filled on the local clock, e.g. slots_late_attitude
                  **{k.lower(): v for k, v in self._slot_counters().items()}}
        if self.link is not None:  # what the link saw, for the count in vs processed (RELIABILITY.md)
            ls = self.link.stats
            imu = sum(ls.messages_by_type.get(k, 0) for k in ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU"))
            fields.update(imu_messages=imu, link_accepted=ls.accepted, link_seq_lost=ls.seq_lost,
                          link_bad_data=ls.crc_errors + ls.framing_errors, link_stale_drops=ls.stale_time_drops,
                          link_losses=ls.link_losses, fc_reboots=ls.fc_reboots,
                          kernel_rx_drops=getattr(ls, "kernel_rx_drops", 0) or 0,
                          # every frame read, and those ignored as not from the FC (before its first
                          # HEARTBEAT the FC is not known): bench/speed.py --busy's loss accounting
                          link_messages_received=ls.messages_received, link_foreign=ls.foreign_messages,
                          link_non_finite=sum(ls.non_finite_rejects.values()))
        log.info("stopped", extra={"fields": fields})

    def run(self, duration_s: float | None = None) -> int:
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self._on_signal)
        signal.signal(signal.SIGHUP, self._on_sighup)
        self.open()
        self._freeze_heap()
        t_end = None if duration_s is None else self.clock() + duration_s
        try:
            while not self.stop_requested:
                self.step(self.loop_wait_s())
                if t_end is not None and self.clock() >= t_end:
                    break
        finally:
            self.close()
        return 0

    @staticmethod
    def _freeze_heap() -> None:
        """Everything built up to the loop (modules, the dialects, the Pipeline, the link) is kept for
        the process's life: collected once, then moved out of the cyclic collector's generations
        (gc.freeze), so its full collections no longer walk ~80k objects that never become garbage
        (in-process 400 Hz flight, bench/daemon_loop_cost.py's frames: GC 116 -> 26 ms per 26 s)."""
        gc.collect()
        gc.freeze()

    # --- the loop -----------------------------------------------------------------------------

    def step(self, timeout_s: float) -> None:
        t0 = self.clock()
        if self._last_step_s is not None:
            self.loss_monitor.on_step_gap(t0 - self._last_step_s - timeout_s)
        for item in self.link.poll(timeout_s=timeout_s):
            self.dispatch(item)
        now = self.clock()
        self._last_step_s = now
        self._publish_due(now)
        if self.commands is not None:
            for o in self.commands.poll(now):
                self._command_outcome(o, now)
        self._periodic(now)

    def loop_wait_s(self) -> float:
        """How long the next step may block on the link (it returns at once on input, and the link
        shortens the wait to its own next timer): until the next MAVLink output slot that no sample will
        fill (the FC's samples sparser than the slots: OutputScheduler.fill; with denser samples each
        slot is sent as its sample is handled), the command protocol's next try, else LOOP_MAX_WAIT_S.
        A time already past was declined by the step that just ran (an output: no fresh solution, FC
        time not past the last sent; a command: no target yet) and waits for input: never a busy loop."""
        now = self.clock()
        due = now + LOOP_MAX_WAIT_S
        # a slot between two sparse samples (OutputScheduler.fill); a pending solution is one (not built here)
        if self._last_solution is not None or self._pending_prop is not None:
            out_due = self.scheduler.next_fill_s()
            if out_due is not None and now < out_due < due \
                    and out_due - self._last_solution_s <= self.output_limits.max_extrapolation_s:
                due = out_due
        if self.commands is not None:
            cmd_due = self.commands.next_due_s()
            if cmd_due is not None and now < cmd_due < due:
                due = cmd_due
        return max(0.0, due - now)

    @property
    def last_solution(self) -> NavSolution | None:
        """The newest solution: the last filter step's, or it turned to the newest IMU sample (built
        here from ``_pending_prop`` when first read: the same NavSolution the sample made)."""
        if self._pending_prop is not None:
            snap, self._pending_prop = self._pending_prop, None
            self._last_solution = self.pipeline.solution_from_snapshot(snap)
            if snap is self._offered_snap:   # the one the slots were offered
                self._offered_sol = self._last_solution
        return self._last_solution

    @last_solution.setter
    def last_solution(self, sol: NavSolution | None) -> None:
        self._pending_prop = None
        self._last_solution = sol

    def _propagated(self, snap) -> None:
        """The newest IMU sample between filter steps: its propagated solution (a snapshot built when
        read, ``last_solution``) is the newest solution, its slots due (``_publish_due``)."""
        if type(snap) is NavSolution:   # the filter step's own solution (the sample turned nothing)
            self.last_solution = snap
        else:
            self._pending_prop = snap
        self._last_solution_s = self.clock()
        self._publish_due(self._last_solution_s)

    def _due(self, name: str, now: float, period_s: float) -> bool:
        if now < self._next[name]:
            return False
        self._next[name] = now + period_s
        return True

    def _imu_silent_s(self, now: float) -> float | None:
        return None if self._last_imu_rx_s is None else now - self._last_imu_rx_s

    def _periodic(self, now: float) -> None:
        if self.notifier.watchdog_due(now):
            self.notifier.notify("WATCHDOG=1")
        if self.reload_requested:
            self._reload()
        if not self.ready_sent and now - self.started_s >= 2.0 and self._due("waiting", now, WAITING_LOG_S):
            log.warning("waiting for heartbeat on %s (no flight controller has answered yet)", self.link_cfg.url,
                        extra={"fields": {"mavlink": self.link_cfg.url, "waited_s": round(now - self.started_s),
                                          "link_error": self.link.last_error or ""}})
        if self.extra_ports and self._due("extra_hb", now, 1.0 / self.cfg["mavlink"]["heartbeat_hz"]):
            # ground stations and MAVLink clients discover a component by its HEARTBEAT
            self._send_extra(self.link.heartbeat_message())
        line = None
        if self.status_interval_s > 0 and self._due("status", now, self.status_interval_s):
            line = status_line(self.last_solution, self.link.stats.rates_hz(), self.link.connected,
                               self._imu_silent_s(now))
            print(line, flush=True)
        if self.notifier.enabled and self._due("sd_status", now, SD_STATUS_PERIOD_S):
            line = line or status_line(self.last_solution, self.link.stats.rates_hz(), self.link.connected)
            self.notifier.notify("STATUS=" + line.split(" | ")[0])
        if self.bus is None and self.cfg["zenoh"]["enabled"] and now >= self._next["zenoh_retry"]:
            self._open_zenoh()
        if self.bus is not None and self._due("health", now, HEALTH_PERIOD_S):
            self._publish_health(now)
        if self._due("calibration", now, CALIBRATION_SAVE_S):
            if self.calibration.save(self.pipeline.kf1_estimate()):
                self._publish_calibration("mag_error_kf1", "saved", f"flight {self.calibration.flight_id}: "
                                          f"this flight's estimate saved to {self.calibration.store.path}")
            self._save_deviation()
            self._save_signing_timestamp()
        ls = self.link.stats
        if ls.unsigned_rejected > self._unsigned_seen:
            self._unsigned_seen = ls.unsigned_rejected
            if not self.link.connected and self.cfg["mavlink"]["require_signed"] == "all":
                self.rl.log(logging.WARNING, "unsigned_fc", "unsigned messages refused (require_signed = all) and no "
                            "signed autopilot heard: set up signing on the FC, or require_signed = \"commands\"",
                            unsigned_rejected=ls.unsigned_rejected)
        for kind, _sev, detail in self.loss_monitor.update(now, ls.accepted, ls.seq_lost,
                                                           getattr(ls, "kernel_rx_drops", None)):
            self._event(kind, detail)
        if self.bus is not None and self.geofence is not None and self._due("geofence_state", now, 0.5):
            payload = self.geofence.state()
            if self._due("fence_geometry", now, FENCE_GEOMETRY_PERIOD_S):
                from service.zenoh_bus import fence_geometry
                payload.update(fence_geometry(self.geofence_cfg, *self.geofence.home[:2]))
            self.bus.publish("geofence", payload)
        if self.bus is not None and self._due("air_data", now, AIR_DATA_PERIOD_S):
            self._publish_air_data(now)

    def dispatch(self, item) -> None:
        """One input through its handler. An exception there is a defect of ours, not the input's
        (a bad input gets its own error where it is decoded and checked): it is logged as
        ``internal_fault`` with where it was raised, counted, and that input dropped; the daemon
        keeps running and its outputs age out through the output gate. FAULTS_BEFORE_REBUILD
        faults in a row on one kind of input mean the estimators' state is broken: the Pipeline is
        built afresh (it finds itself in flight from its inputs, as after a restart in flight)."""
        try:
            self._dispatch(item)
        except Exception as exc:  # noqa: BLE001  (contained: logged, counted, recovered from)
            self._internal_fault(item, exc)
        else:
            self.faults_in_row.pop(type(item).__name__, None)

    def _internal_fault(self, item, exc: Exception) -> None:
        self.internal_faults += 1
        kind = type(item).__name__
        self.faults_in_row[kind] = self.faults_in_row.get(kind, 0) + 1
        frames = traceback.extract_tb(exc.__traceback__)
        where = f"{pathlib.Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else "?"
        self._event("internal_fault", f"{type(exc).__name__}: {exc} (at {where}, handling {type(item).__name__}): "
                    f"input dropped, the daemon continues ({self.internal_faults} so far)")
        if self.faults_in_row[kind] >= FAULTS_BEFORE_REBUILD:
            self.faults_in_row.clear()
            self._rebuild_pipeline(f"{FAULTS_BEFORE_REBUILD} inputs in a row failed, the last with "
                                   f"{type(exc).__name__} at {where}")

    def _rebuild_pipeline(self, why: str) -> None:
        """A fresh Pipeline from the same config, the same solver and the saved calibrations; the
        FC facts the daemon already knows (its parameters, a yaw excluded as ours) applied again."""
        old = self.pipeline
        # the calibration applied at start stays; this flight's KF1 learning starts over
        self.pipeline = Pipeline(self.cfg, kf1_learn=None, kf1_applied=self._kf1_applied_at_start,
                                 solver=old.solver, deviation=self._load_deviation())
        self.pipeline_rebuilds += 1
        if self.link is not None and self.link.fc_params:
            self.pipeline.on_fc_params(self.link.fc_params, True, self.clock())
        if not self.cfg["heading"].get("use_fc_yaw", True) or self.fc_yaw_guard.exclude_reason is not None:
            self.pipeline.exclude_fc_yaw(self.fc_yaw_guard.exclude_reason or "[heading] use_fc_yaw = false")
        self.last_solution = None
        self._event("pipeline_rebuilt", f"estimators started afresh: {why}")

    def _dispatch(self, item) -> None:
        if isinstance(item, ImuBatch):
            self._on_imu_batch(item)
        elif isinstance(item, ImuSample):
            self._last_imu_rx_s = item.time_rx_s
            self.fc_lag.on_sample(item.time_fc_s, item.time_rx_s)
            sol = self.pipeline.step_imu(item)   # on_imu, a quiet sample in the core's hot path
            if sol is not None:
                self.last_solution = sol
                self._last_solution_s = self.clock()
                # also here, not only once per poll: a poll that returns a burst (the loop behind)
                # would otherwise publish one message of each kind per burst
                self._publish_due(self._last_solution_s)
                self.publish(sol)
                if self.geofence is not None:
                    self._geofence_step(sol)
            else:
                # between filter steps: the last solution turned by the gyros to this sample, so the
                # MAVLink outputs carry the newest attitude (Zenoh and the geofence keep the filter rate)
                prop = self.pipeline.propagated_snapshot()
                if prop is not None:
                    self._propagated(prop)
            self._pipeline_events()
        elif isinstance(item, PressureSample):
            self.pipeline.on_pressure(item)
        elif isinstance(item, FcAttitude):
            self.pipeline.on_fc_attitude(item)
        elif isinstance(item, LinkEvent):
            self._event(item.kind, item.detail)
            if item.kind == "fc_reboot":
                self._last_sent_fc_s = -math.inf  # the FC clock restarted: stamps start again
                self.scheduler.restart_fc_clock()  # and its output slots
                self.fc_lag.reset()
                self.pipeline.on_fc_reboot()
                self._fc_yaw_feed_start()  # its parameters may have changed with the reboot
            elif item.kind == "autopilot_detected":
                self.scheduler.set_profile(odometry_profile_for_autopilot(self.link.fc_autopilot))
                self._fc_yaw_feed_start()
            elif item.kind == "params_read":
                self._fc_yaw_feed(self.fc_yaw_guard.on_params(self.link.fc_params, self.link.fc_params_missing))
                self.pipeline.on_fc_params(self.link.fc_params, True, self.clock())
        elif isinstance(item, FcParam):
            self._fc_yaw_feed(self.fc_yaw_guard.on_params(self.link.fc_params, self.link.fc_params_missing))
            self.pipeline.on_fc_params(self.link.fc_params, False, self.clock())
        elif isinstance(item, FcStatusText):
            self._fc_yaw_feed(self.fc_yaw_guard.on_statustext(item.text, self.sent.get("ODOMETRY", 0) > 0))
        elif isinstance(item, FcHeartbeat):
            self.fc_heartbeat = item
            self.pipeline.on_fc_heartbeat(item)
            if self.geofence is not None:
                self.geofence.on_heartbeat(item)
            if not self.ready_sent:
                self.ready_sent = True
                self.notifier.notify("STATUS=flight controller link up")
                log.info("flight controller link up", extra={"fields": {"autopilot": item.autopilot,
                                                                        "system_id": item.system_id}})
        elif isinstance(item, FcFlightState):
            self.pipeline.on_fc_flight_state(item)
        elif isinstance(item, FcEkfStatus):
            self.pipeline.on_fc_ekf_status(item)
            self.gnss["ekf"] = item.horiz_pos_ok
            self._gnss_health()
        elif isinstance(item, FcSysStatus):
            self.gnss["sys"] = item.gps_healthy
            self._gnss_health()
        elif isinstance(item, IncomingCommand):
            self._on_command(item)
        elif isinstance(item, CommandAck):
            if self.commands is not None:
                now = self.clock()
                for o in self.commands.on_command_ack(item, now):
                    self._command_outcome(o, now)

    def _on_imu_batch(self, batch: ImuBatch) -> None:
        """The RAW_IMU samples of one read (LinkConfig.imu_batch): the Pipeline's solutions are
        published and its events reported as for single samples (events after the batch's
        solutions); the MAVLink outputs are then due once, with the attitude at the batch's newest
        sample (a sample at a time, a burst sent the attitude of its first sample)."""
        times_fc, times_rx = batch.records["time_fc_s"].tolist(), batch.records["time_rx_s"].tolist()
        for t_fc, t_rx in zip(times_fc, times_rx):
            self.fc_lag.on_sample(t_fc, t_rx)
        self._last_imu_rx_s = times_rx[-1]
        sols = self.pipeline.on_imu_batch(batch)
        for sol in sols:
            self.last_solution = sol
            self._last_solution_s = self.clock()
            self._publish_due(self._last_solution_s)  # each solution its FC-time slots
            self.publish(sol)
            if self.geofence is not None:
                self._geofence_step(sol)
        prop = self.pipeline.propagated_snapshot()
        if prop is not None:
            self._propagated(prop)
        self._pipeline_events()

    def _pipeline_events(self) -> None:
        for kind, detail in self.pipeline.drain_events():
            self._event(kind, detail)
            if kind in _CALIBRATION_EVENTS:
                self._calibration_event(kind, detail)

    # --- commands to our component (service/command_server.py) ---------------------------------

    def _on_command(self, cmd: IncomingCommand) -> None:
        now = self.clock()
        d = self.command_server.decide(cmd, now, have_solution=self.last_solution is not None)
        msg = None
        if d.action == "request_message" and not d.repeat:
            msg = self._requested_message(d.message_id)
            if msg is None:  # e.g. ATTITUDE_QUATERNION while the heading is not valid
                d = self.command_server.revise(d, mavlink2.MAV_RESULT_TEMPORARILY_REJECTED, "not available now")
        ack = self.link.mav.command_ack_encode(cmd.command, d.result, 0, 0, cmd.source_system, cmd.source_component)
        self.link.send(ack)  # the ACK first, then what was asked for (MAVLink command protocol)
        if msg is not None:
            self._send(msg, to_fc=True)
        if d.action in ("fence_enable", "fence_disable") and not d.repeat and self.geofence is not None:
            self.geofence.actions_enabled = d.action == "fence_enable"
        self._event("command", f"{d.reason}: {d.result_name}")

    def _requested_message(self, message_id: int):
        if message_id == MSG_HEARTBEAT:
            return self.link.heartbeat_message()
        sol = self.last_solution
        if message_id == MSG_ATTITUDE:
            return encode_attitude(sol)
        if message_id == MSG_ATTITUDE_QUATERNION:
            return encode_attitude_quaternion(sol)
        return None

    # --- geofence (docs/GEOFENCE.md) ----------------------------------------------------------

    def _on_raw(self, msg) -> None:
        """Raw autopilot messages: GLOBAL_POSITION_INT (not decoded by the link) for the DR start."""
        if self.geofence is not None and msg.get_type() == "GLOBAL_POSITION_INT":
            self.geofence.on_fc_position(msg.time_boot_ms / 1e3, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt / 1e3,
                                         msg.vx / 100.0, msg.vy / 100.0)

    def _gnss_health(self) -> None:
        if self.geofence is not None:
            self.geofence.on_gnss_health(self.gnss["sys"] is True and self.gnss["ekf"] is not False)

    def _geofence_step(self, sol: NavSolution) -> None:
        now = self.clock()
        specs = self.geofence.step(sol, self.pipeline.air_data(), now)
        self.commands.input_delay_s = self.geofence.input_age_s  # an ACK sits behind our input backlog
        for spec in specs:
            for o in self.commands.submit(spec, now):
                self._command_outcome(o, now)
        self._geofence_events()

    def _command_outcome(self, outcome, now: float) -> None:
        log.info("command outcome", extra={"fields": {"command": outcome.name, "status": outcome.status,
                                                      "result": outcome.result_name, "tries": outcome.tries}})
        if self.geofence is not None:
            t = self.last_solution.time_fc_s if self.last_solution is not None else None
            for spec in self.geofence.on_command_outcome(outcome, t):
                for o in self.commands.submit(spec, now):
                    self._command_outcome(o, now)
            self._geofence_events()

    def _geofence_events(self) -> None:
        for ev in self.geofence.drain_events():
            level = logging.WARNING if ev.severity in ("warning", "critical", "error", "alert", "emergency") \
                else logging.INFO
            log.log(level, ev.text, extra={"fields": {"event": ev.kind}})
            self._send(statustext_message(ev.severity, ev.text))
            if self.bus is not None:  # the events schema: kind, severity (syslog names), detail
                from service.zenoh_bus import event_payload
                sev = "critical" if ev.severity in ("alert", "emergency") else ev.severity
                self.bus.publish("events", event_payload(ev.kind, sev, ev.text, time_rx_s=self.clock(),
                                                         time_fc_s=ev.time_fc_s))

    def _calibration_event(self, kind: str, detail: str) -> None:
        cal_kind, status = _CALIBRATION_EVENTS[kind]
        values = {}
        level = self.pipeline.phase.level
        if kind == "levelled" and level is not None:
            values = {"roll_deg": math.degrees(level.roll_rad), "pitch_deg": math.degrees(level.pitch_rad)}
            if level.gyro_bias_rad_s is not None:
                values["gyro_bias_rad_s"] = [float(v) for v in level.gyro_bias_rad_s]
        elif kind == "declination" and getattr(self.pipeline, "declination_rad", None) is not None:
            values = {"declination_deg": math.degrees(self.pipeline.declination_rad)}
        self._publish_calibration(cal_kind, status, detail, **values)

    def _event(self, kind: str, detail: str) -> None:
        severity = _EVENT_SEVERITY.get(kind, "info")
        level = {"info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}[severity]
        self.rl.log(level, f"event:{kind}:{detail[:40]}", detail, event=kind)
        if self.bus is not None:
            from service.zenoh_bus import event_payload
            self.bus.publish("events", event_payload(kind, severity, detail, time_rx_s=self.clock()))

    # --- outputs ------------------------------------------------------------------------------

    def _fc_yaw_feed_start(self) -> None:
        names, events = self.fc_yaw_guard.start(self.link.fc_autopilot)
        if self.pipeline.vehicle.pending:  # [launch] vehicle = "auto": how a fixed wing takes off
            names = tuple(names) + tuple(n for n in vehicle_param_names(self.link.fc_autopilot) if n not in names)
        if names:
            self.link.read_params(names)
        self._fc_yaw_feed(events)

    def _fc_yaw_feed(self, events: list) -> None:
        """Apply the guard's decisions (service/fc_yaw_guard.py) and report them."""
        self.scheduler.odometry_allowed = self.fc_yaw_guard.odometry_allowed
        if self.fc_yaw_guard.exclude_reason is not None and self.pipeline.use_fc_yaw:
            self.pipeline.exclude_fc_yaw(self.fc_yaw_guard.exclude_reason)
        for kind, severity, detail in events:
            level = {"info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}[severity]
            log.log(level, detail, extra={"fields": {"event": kind}})
            if self.bus is not None:
                from service.zenoh_bus import event_payload
                self.bus.publish("events", event_payload(kind, severity, detail, time_rx_s=self.clock()))

    def _publish_due(self, now: float) -> None:
        """MAVLink outputs at their own rates, on the FC's clock (mavlink_io/outputs.OutputScheduler): a new
        solution takes the slots its sample is the first to reach, and is sent as it is, with its own FC
        stamp and values (what the Pipeline produced and Zenoh published), so a backlog worked off at once
        sends each slot its own solution; slots older than CATCH_UP_MAX_LAG_S against the FC's clock are
        counted (ODOMETRY never sent; the others at most at their rate of the local clock). When the FC's samples are sparser than the slots, the slots between two
        samples are filled on the local clock with the newest solution while it is fresher than
        max_extrapolation_s (a slow IMU's outputs repeat it; nothing once it is older)."""
        sched = self.scheduler
        snap = self._pending_prop
        if snap is not None and snap is not self._offered_snap and self.link is not None:
            # a new propagated solution (not built yet): offered by its FC time, built if it takes a slot
            self._offered_snap = snap
            t_fc = _snapshot_time_fc_s(snap)
            if not sched.reaches_slot(t_fc):
                sched.note(t_fc, now)  # most samples: no slot, nothing to build
                return
            sol = self.last_solution  # built now: the offered one (_offered_sol)
            fill = False
        else:
            if self.link is None:
                return
            # a pending snapshot here was offered already and took no slot: it is the offered solution
            # (built now it would be _offered_sol), so only a fill can want it, and it is built only then
            sol = self._last_solution if snap is None else None
            if snap is None and sol is None:
                return
            if sol is not None and sol is not self._offered_sol:
                self._offered_sol = sol
                if not sched.reaches_slot(sol.time_fc_s):
                    sched.note(sol.time_fc_s, now)  # most samples: no slot, nothing to build
                    return
                fill = False
            else:
                due_s = sched.next_fill_s()
                if due_s is None or now < due_s or now - self._last_solution_s > self.output_limits.max_extrapolation_s:
                    return
                sol = self.last_solution  # the offered solution (a pending snapshot built now)
                fill = True
        # Not brought forward by its local age (output_gate.extrapolate_solution): when the daemon works off
        # a backlog that age is queueing delay, and a stamp pushed ahead of the FC stream held back every
        # real solution (e2e: 6 ATTITUDE in 5 s and 2-3 deg errors after a stall). Receivers never see time
        # go back, and two different attitudes never carry the same 1 ms time_boot_ms: an equal millisecond
        # only for the very same solution (a slot filled with the solution already sent).
        ms = _time_boot_ms(sol.time_fc_s)
        last_ms = _time_boot_ms(self._last_sent_fc_s) if math.isfinite(self._last_sent_fc_s) else -math.inf
        if ms < last_ms or (ms == last_ms and sol is not self._last_sent_sol):
            if not fill:
                sched.note(sol.time_fc_s, now)
            return
        # slots older than the FC's EKFs date a measurement are skipped (CATCH_UP_MAX_LAG_S)
        lag_s = self.fc_lag.lag_s(sol.time_fc_s, now)
        late = lag_s > CATCH_UP_MAX_LAG_S
        held, odometry_held = sum(sched.slots_late.values()), sched.odometry_late
        gated = gate_solution(sol, self.output_limits)
        msgs = sched.fill(gated, now, late=late) if fill else sched.messages(gated, now, late=late)
        if late and sum(sched.slots_late.values()) > held:
            self.rl.log(logging.WARNING, "outputs_late", f"outputs held back: our solution lags the FC's clock by "
                        f"{lag_s:.2f} s (> {CATCH_UP_MAX_LAG_S:g} s: the daemon is behind its input; the FC would "
                        "fuse a yaw misdated): no ODOMETRY, the rest at most at its rate; counted (slots_late)",
                        event="odometry_late" if sched.odometry_late > odometry_held else "outputs_late")
        if msgs:
            self._last_sent_fc_s, self._last_sent_sol = sol.time_fc_s, sol
        for msg in msgs:
            self._send(msg)

    def _send(self, msg, to_fc: bool = False) -> None:
        """To the FC link (ATTITUDE/ATTITUDE_QUATERNION only with [outputs] attitude_to_fc, or when
        ``to_fc``: an answer to a request) and every extra output."""
        t = msg.get_type()
        to_link = to_fc or self.attitude_to_fc or t not in ("ATTITUDE", "ATTITUDE_QUATERNION")
        if to_link:
            self.link.send(msg)  # ArduPilot forwards what we send it to every port (docs/OUTPUTS.md 1.6)
        self._send_extra(msg)
        if to_link or self.extra_ports:
            self.sent[t] = self.sent.get(t, 0) + 1

    def _send_extra(self, msg) -> None:
        for p in self.extra_ports:
            try:
                p.mav.srcSystem = self.link.mav.srcSystem
                frame_pack.send(p.mav, msg)
            except OSError as exc:
                self.rl.log(logging.WARNING, "extra_send", "extra output send failed", error=str(exc))

    def publish(self, sol: NavSolution) -> None:
        """A new solution: Zenoh at once; MAVLink from the loop at its own rates (_publish_due)."""
        now = sol.time_rx_s
        if self.bus is not None:
            self.bus.publish_solution(sol, now, getattr(self.pipeline, "aiding", None))

    _LINK_COUNTERS = ("seq_lost", "crc_errors", "framing_errors", "kernel_rx_drops", "signed_accepted",
                      "signature_bad", "signature_replay", "unsigned_rejected", "unsigned_commands_rejected",
                      "fc_reboots", "input_backlogs")

    def _link_counters(self) -> dict[str, int]:
        ls = self.link.stats
        return {f"link_{k}": int(getattr(ls, k) or 0) for k in self._LINK_COUNTERS if hasattr(ls, k)}

    def _slot_counters(self) -> dict[str, int]:
        """Per enabled message, the output slots not sent (``late``: the solution lagged the FC's clock over
        CATCH_UP_MAX_LAG_S, every ODOMETRY and the others beyond their rate on the local clock; ``gap``: no
        IMU sample in them), those sent although late (``behind``) and those filled on the local clock
        between sparse samples (``filled``)."""
        sc = self.scheduler
        return {f"slots_{kind}_{name}": counts[name]
                for kind, counts in (("late", sc.slots_late), ("behind", sc.slots_behind), ("gap", sc.slots_gap),
                                     ("filled", sc.slots_filled))
                for name in sc.rates_hz if sc.rates_hz[name] > 0}

    def _publish_air_data(self, now: float) -> None:
        """Method B's air data (ISA altitude, density, TAS) when it has a new sample."""
        air = self.pipeline.air_data()
        if air is None or air.time_s == self._air_time_s:
            return
        from service.zenoh_bus import air_data_payload
        self._air_time_s = air.time_s
        p = self.pipeline.pressure
        self.bus.publish("air_data", air_data_payload(air, now, p.press_abs_pa if p else None,
                                                      p.press_diff_pa if p else None))

    def _publish_health(self, now: float) -> None:
        from service.zenoh_bus import health_payload
        c = self.pipeline.counters
        sol = self.last_solution
        self.bus.publish("health", health_payload(
            self.link.connected, sol.phase if sol else "boot", now - self.started_s, self.link.stats.rates_hz(),
            {"imu_samples": c.imu_samples, "imu_rejected": c.imu_rejected,
             "pressure_samples": c.pressure_samples, **{f"sent_{k}": v for k, v in self.sent.items()},
             "odometry_late": self.scheduler.odometry_late,
             **self._slot_counters(),
             **{f"imu_input_{k}": v for k, v in self.pipeline.input_checks.counts.items()},
             **self._link_counters(),
             **{f"commands_{k.lower()}": v for k, v in self.command_server.counts.items()}},
            status=status_line(sol, self.link.stats.rates_hz(), self.link.connected).split(" | ")[0],
            autopilot=self.link.fc_autopilot, time_rx_s=now) | {"flags": self._health_flags()})

    def _health_flags(self) -> dict:
        """The heading feed's state and, per requested stream, asked / granted / achieved rates."""
        flags = self.fc_yaw_guard.flags()
        for name, r in self.link.stream_report().items():
            g = r["granted_hz"]
            flags[f"stream_{name}"] = (f"asked {r['asked_hz']:g} Hz, " + (f"granted {g:g} Hz" if g is not None
                                                                         else r["result"])
                                       + f", achieved {r['achieved_hz']:.1f} Hz")
        if self.link.rate_advice:
            flags["stream_advice"] = self.link.rate_advice
        # 'usable', or why the magnetometer is rejected (estimators/mag_usability via the Pipeline)
        flags["magnetometer"] = self.pipeline.mag_status
        ch = self.pipeline.vehicle.choice  # the take-off model ([launch] vehicle) and why
        flags["vehicle"] = "not known yet (auto: waiting for the FC)" if ch is None else \
            f"{ch.vehicle or 'none'}: {ch.reason}"
        return flags
