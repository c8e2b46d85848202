"""SITL harness: the simulator and the daemon as separate OS processes over UDP on loopback.

Used by `make run` (bench/live_demo.py), the end-to-end tests and the benches. The harness, not
the daemon, reads the simulator's truth (its truth log): the daemon sees only MAVLink.

    with Sitl(scenario="inclined_rail", speed=1.0) as s:
        s.wait_for(lambda: len(s.listener.attitude) > 100, 30)
        ...
    truth = s.truth()          # after exit: the truth log the simulator wrote
"""
from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")   # small matrices: BLAS threads only spin on a shared machine (tests/conftest.py)
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE_CONFIG = ROOT / "systemd" / "azimuthd.toml"
OUR_COMPONENT = 191


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def write_config(path: Path, overrides: dict[str, dict], example: Path = EXAMPLE_CONFIG) -> Path:
    """The example config with some keys replaced (a config a user would write for this flight)."""
    with open(example, "rb") as f:
        cfg = tomllib.load(f)
    for section, keys in overrides.items():
        cfg.setdefault(section, {}).update(keys)
    lines = []
    for section, keys in cfg.items():
        lines.append(f"[{section}]")
        lines.extend(f"{k} = {_toml_value(v)}" for k, v in keys.items() if v is not None)
        lines.append("")
    path.write_text("\n".join(lines))
    return path


LAUNCH_CASE = {"rail": "inclined", "tube": "vertical", "runway": "aligned", "hand": "aligned",
               "multicopter": "aligned", "vtol": "aligned"}
"""[launch] case an operator configures for the scenario's launcher type (flight direction, METHODS.md A.3)."""
LAUNCH_VEHICLE = {"rail": "launcher", "tube": "launcher", "runway": "runway", "hand": "hand",
                  "multicopter": "multicopter", "vtol": "vtol"}
"""[launch] vehicle an operator configures for it (how it takes off: service/phases.py)."""


def scenario_site(scenario: str) -> dict:
    """The config an operator would write for this flight: site, date, launcher, IMU mount.

    The harness may read the scenario file (it is the operator's knowledge of the launch); the
    daemon gets only this config and MAVLink.
    """
    from sim.earth import decimal_year_from_date
    from sim.scenario import load_scenario
    sc = load_scenario(scenario)
    roll, pitch, yaw = sc["imu"]["mount_euler_deg"]
    launcher = sc["launcher"]["type"]
    out = {"site": {"lat_deg": float(sc["site"]["lat_deg"]), "lon_deg": float(sc["site"]["lon_deg"]),
                    "alt_m": float(sc["site"]["alt_m"]),
                    "decimal_year": float(decimal_year_from_date(sc["scenario"]["date"]))},
           "imu": {"mount_roll_deg": float(roll), "mount_pitch_deg": float(pitch), "mount_yaw_deg": float(yaw)},
           "launch": {"case": LAUNCH_CASE[launcher], "vehicle": LAUNCH_VEHICLE[launcher]}}
    return out


def pipeline_inputs(run) -> list:
    """The samples the daemon's link would hand a ``service.pipeline.Pipeline`` for a
    ``sim.offline`` SimRun, in time order: ImuSample (RAW_IMU), PressureSample, FcAttitude (yaw in
    (-pi, pi] as ATTITUDE carries it), each with receive time = FC time; at equal FC times the
    pressure and the FC attitude come before the IMU sample."""
    from mavlink_io.samples import FcAttitude, ImuSample, PressureSample
    items = []
    for t, g, a, m in zip(run.time_s.tolist(), run.gyro_rad_s, run.accel_m_s2, run.mag_gauss):
        items.append((t, 2, ImuSample(t, t, g.copy(), a.copy(), m.copy(), "RAW_IMU", 0)))
    for t, p, d, k in zip(run.baro_time_s.tolist(), run.press_abs_pa.tolist(), run.press_diff_pa.tolist(),
                          run.temperature_k.tolist()):
        items.append((t, 1, PressureSample(t, t, p, d, k)))
    for t, e in zip(run.fc_time_s.tolist(), run.fc_euler_rad):
        items.append((t, 0, FcAttitude(t, t, float(e[0]), float(e[1]), float(math.remainder(e[2], 2 * math.pi)),
                                       np.zeros(3))))
    items.sort(key=lambda x: (x[0], x[1]))
    return [x[2] for x in items]


def feed_pipeline(pipeline, items, events: list | None = None, timed_events: bool = False):
    """Feed ``items`` to ``pipeline`` by type, as the daemon's dispatch does: ImuSample -> ``on_imu``
    then ``drain_events``; PressureSample, FcAttitude, FcHeartbeat, FcFlightState, FcEkfStatus -> their
    handlers.
    Yields the solutions ``on_imu`` returns (None is not yielded); the drained events are appended
    to ``events`` when given, as (kind, detail), or (IMU time s, kind, detail) with ``timed_events``.
    A generator: nothing is fed until it is iterated (code between two solutions runs between them)."""
    from mavlink_io.samples import FcAttitude, FcEkfStatus, FcFlightState, FcHeartbeat, ImuSample, PressureSample
    on_imu, drain = pipeline.on_imu, pipeline.drain_events
    others = {PressureSample: pipeline.on_pressure, FcAttitude: pipeline.on_fc_attitude,
              FcHeartbeat: pipeline.on_fc_heartbeat, FcFlightState: pipeline.on_fc_flight_state,
              FcEkfStatus: pipeline.on_fc_ekf_status}
    for it in items:
        c = type(it)
        if c is ImuSample:
            sol = on_imu(it)
            drained = drain()
            if events is not None and drained:
                events += [(it.time_fc_s, k, d) for k, d in drained] if timed_events else drained
            if sol is not None:
                yield sol
        else:
            fn = others.get(c)
            if fn is None:
                raise TypeError(f"feed_pipeline: not a Pipeline input: {c.__name__}")
            fn(it)


@dataclass
class OutputListener:
    """Receives what the daemon sends to an extra output URL (as a ground station would)."""
    port: int
    attitude: list = field(default_factory=list)   # (time_boot_s, roll, pitch, yaw, rx_monotonic)
    named: list = field(default_factory=list)      # (name, value, rx_monotonic)
    heartbeats: int = 0
    messages: dict = field(default_factory=dict)

    def start(self) -> "OutputListener":
        from pymavlink import mavutil
        self._conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{self.port}", dialect="ardupilotmega")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self._conn.recv_match(blocking=True, timeout=0.2)
            if msg is None or msg.get_srcComponent() != OUR_COMPONENT:
                continue
            t = msg.get_type()
            self.messages[t] = self.messages.get(t, 0) + 1
            now = time.monotonic()
            if t == "ATTITUDE":
                self.attitude.append((msg.time_boot_ms / 1000.0, msg.roll, msg.pitch, msg.yaw, now))
            elif t == "NAMED_VALUE_FLOAT":
                self.named.append((msg.name, msg.value, now))
            elif t == "HEARTBEAT":
                self.heartbeats += 1

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._conn.close()


class UdpTap:
    """A UDP relay between the simulator and the daemon that decodes what the daemon sends.

    The simulator pushes to ``sim_side_port``; the tap forwards to the daemon's udpin port and
    relays the daemon's replies back to the simulator, recording every message the daemon sent
    (an observer outside both processes). With ``record_to_daemon`` (message types, e.g.
    ``("RAW_IMU",)``) it also decodes what the simulator sends and records when it forwarded each
    message of those types to the daemon: the same monotonic clock, read in the same thread, as
    the receive times in ``from_daemon`` (bench/speed.py's latency RAW_IMU -> ATTITUDE).

    Loss accounting (bench/speed.py ``--busy``): with ``record_to_daemon`` the tap also counts every
    simulator message by type (``received_by_type``: all it read; ``forwarded_by_type``: what it
    passed on) and keeps ``forwarded_by_type`` as it was when it forwarded the first HEARTBEAT
    (``forwarded_before_heartbeat``: what the daemon ignores as it does not know its FC yet).
    ``drop_to_daemon(msg_type) -> bool`` drops the datagrams it says (a loss made on purpose,
    counted in ``dropped_on_purpose`` by type; needs ``record_to_daemon``). ``rcvbuf_bytes``: the
    tap socket's SO_RCVBUF (None: the system default), so the harness itself does not overflow.
    """

    def __init__(self, daemon_port: int, record_to_daemon: tuple[str, ...] = (),
                 drop_to_daemon=None, rcvbuf_bytes: int | None = None):
        from pymavlink.dialects.v20 import ardupilotmega
        self.daemon_addr = ("127.0.0.1", daemon_port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        if rcvbuf_bytes is not None:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, int(rcvbuf_bytes))
        self.sock.bind(("127.0.0.1", 0))
        self.sim_side_port = self.sock.getsockname()[1]
        self.parser = ardupilotmega.MAVLink(None)
        self.parser.robust_parsing = True
        self.from_daemon: list[tuple[float, object]] = []
        """(receive monotonic s, message) of every message the daemon sent."""
        self.record_to_daemon = frozenset(record_to_daemon)
        self.to_daemon: list[tuple[float, object]] = []
        """(forward monotonic s, message) of the simulator's messages of the types in record_to_daemon."""
        self._sim_parser = None
        if self.record_to_daemon:  # decoding the 400 Hz stream costs this thread time: only on request
            self._sim_parser = ardupilotmega.MAVLink(None)
            self._sim_parser.robust_parsing = True
        if drop_to_daemon is not None and not self.record_to_daemon:
            raise ValueError("drop_to_daemon needs record_to_daemon (the tap decodes to know a datagram's type)")
        self.drop_to_daemon = drop_to_daemon
        self.forwarded = {"to_daemon": 0, "to_sim": 0}
        self.received_by_type: dict[str, int] = {}
        self.forwarded_by_type: dict[str, int] = {}
        self.dropped_on_purpose: dict[str, int] = {}
        self.forwarded_before_heartbeat: dict[str, int] | None = None
        self._sim_addr = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> "UdpTap":
        self._thread.start()
        return self

    def _run(self) -> None:
        self.sock.settimeout(0.2)
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(65536)
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            now = time.monotonic()  # receive time of a daemon message, forward time of a simulator one
            if addr == self.daemon_addr:
                if self._sim_addr is not None:
                    self.sock.sendto(data, self._sim_addr)
                    self.forwarded["to_sim"] += 1
                for msg in self.parser.parse_buffer(data) or []:
                    self.from_daemon.append((now, msg))
            else:
                self._sim_addr = addr
                if self._sim_parser is None:
                    self.sock.sendto(data, self.daemon_addr)
                    self.forwarded["to_daemon"] += 1
                    continue
                sent = self.drop_to_daemon is None
                if sent:  # forward first: the decode below does not delay the daemon's input
                    self.sock.sendto(data, self.daemon_addr)
                msgs = self._sim_parser.parse_buffer(data) or []
                types = [m.get_type() for m in msgs]
                for t in types:
                    self.received_by_type[t] = self.received_by_type.get(t, 0) + 1
                if not sent and any(self.drop_to_daemon(t) for t in types):
                    for t in types:
                        self.dropped_on_purpose[t] = self.dropped_on_purpose.get(t, 0) + 1
                    continue
                if not sent:
                    self.sock.sendto(data, self.daemon_addr)
                if self.forwarded_before_heartbeat is None and "HEARTBEAT" in types:
                    self.forwarded_before_heartbeat = dict(self.forwarded_by_type)
                self.forwarded["to_daemon"] += 1
                for msg, t in zip(msgs, types):
                    self.forwarded_by_type[t] = self.forwarded_by_type.get(t, 0) + 1
                    if t in self.record_to_daemon:
                        self.to_daemon.append((now, msg))

    def sent_by_daemon(self, mtype: str) -> list:
        return [m for _, m in self.from_daemon if m.get_type() == mtype]

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()


def udp_socket_state(port: int, host: str = "127.0.0.1") -> dict | None:
    """The kernel's view of the IPv4 UDP socket bound to ``host:port`` (/proc/net/udp, this network
    namespace): ``rx_queue_bytes`` (queued, not yet read by its owner), ``drops`` (datagrams the kernel
    dropped because its receive buffer was full, since the socket was opened) and ``inode``. None when
    no such socket is listed. An observer outside the socket's owner: a bench reads another process's
    socket with it (columns: net/ipv4/udp.c udp4_format_sock)."""
    want = "%08X:%04X" % (int.from_bytes(socket.inet_aton(host), "little"), int(port))
    try:
        lines = Path("/proc/net/udp").read_text().splitlines()[1:]
    except OSError:
        return None
    for line in lines:
        cols = line.split()
        if len(cols) > 12 and cols[1] == want:
            return {"rx_queue_bytes": int(cols[4].split(":")[1], 16), "drops": int(cols[12]),
                    "inode": int(cols[9])}
    return None


def _set_nice(value: int | None, group_nice: int | None = None):
    """A Popen preexec_fn that sets the child's absolute nice value and, for a child in a session
    of its own (start_new_session: setsid runs before the preexec_fn), its CPU group's nice
    (/proc/self/autogroup; below 0 needs root). None: that one unchanged."""
    if value is None and group_nice is None:
        return None

    def preexec() -> None:
        if value is not None:
            os.setpriority(os.PRIO_PROCESS, 0, int(value))
        if group_nice is not None:
            with open("/proc/self/autogroup", "w") as f:
                f.write(str(int(group_nice)))
    return preexec


UNIT_PATH = ROOT / "systemd" / "azimuthd.service"


def unit_nice(path: Path = UNIT_PATH) -> int:
    """The ``Nice=`` the systemd unit gives the daemon (0 when it sets none). Outside systemd a
    bench reproduces it as the nice of the daemon's own session's CPU group (autogroup), the
    stand-in for the unit's cgroup with its CPUWeight."""
    for line in path.read_text().splitlines():
        if line.strip().startswith("Nice="):
            return int(line.split("=", 1)[1])
    return 0


class Sitl:
    """Simulator + daemon as two processes; outputs mirrored to a local listener."""

    def __init__(self, scenario: str = "inclined_rail", speed: float = 1.0, seed: int = 1,
                 workdir: Path | None = None, config_overrides: dict | None = None,
                 sim_args: list[str] | None = None, daemon_args: list[str] | None = None,
                 status_interval_s: float = 0.0, capture_output: bool = True, tap: bool = False,
                 tap_record_to_daemon: tuple[str, ...] = (), sim_nice: int | None = None,
                 daemon_nice: int | None = None, daemon_own_session: bool = False,
                 daemon_group_nice: int | None = None, tap_drop_to_daemon=None,
                 tap_rcvbuf_bytes: int | None = None):
        """``sim_nice`` / ``daemon_nice``: the absolute nice value each process starts with (None:
        inherit this process's; below 0 needs root). ``daemon_own_session``: the daemon starts in
        a session of its own, as systemd starts a service; with the kernel's autogroup scheduling
        (/proc/sys/kernel/sched_autogroup_enabled) that is its own CPU group, and a nice value
        only orders processes within one group. ``daemon_group_nice``: that group's nice (with
        ``daemon_own_session``; as root below 0): ``unit_nice()`` runs it as the unit would.
        ``tap_drop_to_daemon``, ``tap_rcvbuf_bytes``: the tap's ``drop_to_daemon`` and
        ``rcvbuf_bytes`` (UdpTap)."""
        import tempfile
        self.scenario = scenario
        # no folder given: a new one under $AZIMUTHD_SITL_TMPDIR (the test suite's, pruned by pytest), else /tmp
        self.workdir = Path(workdir or tempfile.mkdtemp(prefix="azimuthd-sitl-",
                                                        dir=os.environ.get("AZIMUTHD_SITL_TMPDIR") or None))
        self.fc_port = free_udp_port()
        self.out_port = free_udp_port()
        self.truth_log = self.workdir / "truth.csv"
        overrides = {"mavlink": {"url": f"udpin:127.0.0.1:{self.fc_port}"},
                     "outputs": {"extra_mavlink_urls": [f"udpout:127.0.0.1:{self.out_port}"],
                                 "status_interval_s": status_interval_s},
                     "service": {"state_dir": str(self.workdir / "state")},
                     "zenoh": {"enabled": False}}
        for section, keys in scenario_site(scenario).items():
            overrides.setdefault(section, {}).update(keys)
        for section, keys in (config_overrides or {}).items():
            overrides.setdefault(section, {}).update(keys)
        self.config_path = write_config(self.workdir / "azimuthd.toml", overrides)
        self.tap = UdpTap(self.fc_port, tap_record_to_daemon, drop_to_daemon=tap_drop_to_daemon,
                          rcvbuf_bytes=tap_rcvbuf_bytes) if tap else None
        sim_port = self.tap.sim_side_port if self.tap else self.fc_port
        self.sim_cmd = [sys.executable, "-m", "service.cli", "sim", "--scenario", scenario,
                        "--mavlink", f"udpout:127.0.0.1:{sim_port}", "--speed", str(speed),
                        "--seed", str(seed), "--truth-log", str(self.truth_log), *(sim_args or [])]
        self.daemon_cmd = [sys.executable, "-m", "service.cli", "run", "--config", str(self.config_path),
                           *(daemon_args or [])]
        self.capture_output = capture_output
        self.sim_nice, self.daemon_nice, self.daemon_own_session = sim_nice, daemon_nice, daemon_own_session
        if daemon_group_nice is not None and not daemon_own_session:
            raise ValueError("daemon_group_nice needs daemon_own_session (a CPU group of its own)")
        self.daemon_group_nice = daemon_group_nice
        self.listener = OutputListener(self.out_port)
        self.sim: subprocess.Popen | None = None
        self.daemon: subprocess.Popen | None = None

    def __enter__(self) -> "Sitl":
        self.listener.start()
        if self.tap:
            self.tap.start()
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        out = (lambda name: open(self.workdir / name, "w")) if self.capture_output else (lambda name: None)
        self._daemon_out = out("daemon.log")
        self._sim_out = out("sim.log")
        self.daemon = subprocess.Popen(self.daemon_cmd, cwd=ROOT, env=env, stdout=self._daemon_out or None,
                                       stderr=subprocess.STDOUT if self._daemon_out else None,
                                       preexec_fn=_set_nice(self.daemon_nice, self.daemon_group_nice),
                                       start_new_session=self.daemon_own_session)
        # the simulator pushes (udpout) from its first second: start it only once the daemon
        # listens, or a slow daemon start (imports on a loaded machine) misses the launch; the
        # deadline only detects a hang (importing service.daemon took 34 s at load 13, 2026-12-02)
        if self._daemon_out:
            t_end = time.monotonic() + 300.0
            while time.monotonic() < t_end and "msg=started" not in self.log("daemon") \
                    and self.daemon.poll() is None:
                time.sleep(0.05)
        self.sim = subprocess.Popen(self.sim_cmd, cwd=ROOT, env=env, stdout=self._sim_out or None,
                                    stderr=subprocess.STDOUT if self._sim_out else None,
                                    preexec_fn=_set_nice(self.sim_nice))
        return self

    def wait_for(self, cond, timeout_s: float, poll_s: float = 0.05) -> bool:
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if cond():
                return True
            for p, name in ((self.sim, "simulator"), (self.daemon, "daemon")):
                if p is not None and p.poll() is not None:
                    raise RuntimeError(f"{name} exited with {p.returncode}; see {self.workdir}")
            time.sleep(poll_s)
        return cond()

    def stop(self) -> None:
        for p in (self.daemon, self.sim):
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in (self.daemon, self.sim):
            if p is not None:
                try:
                    p.wait(15)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(5)
        self.listener.stop()
        if self.tap:
            self.tap.stop()
        for f in (self._daemon_out, self._sim_out):
            if f:
                f.close()

    def __exit__(self, *exc) -> None:
        self.stop()

    def log(self, which: str) -> str:
        p = self.workdir / f"{which}.log"
        return p.read_text() if p.exists() else ""

    def truth(self) -> dict[str, np.ndarray]:
        """The simulator's truth log (columns of sim/truthlog.py), plus ``launch_time_boot_s``."""
        from sim.trajectory import PHASES
        from sim.truthlog import load_truth_log
        tr = load_truth_log(str(self.truth_log))
        moving = np.nonzero(tr["phase"] != PHASES.index("rest"))[0]
        tr["launch_time_boot_s"] = float(tr["time_boot_s"][moving[0]]) if moving.size else math.nan
        return tr


def angle_diff_rad(a, b):
    """a - b wrapped to (-pi, pi]."""
    return (np.asarray(a) - np.asarray(b) + math.pi) % (2 * math.pi) - math.pi
