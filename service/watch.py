"""``azimuthd watch``: a terminal dashboard of every azimuthd on the Zenoh network.

Subscribes to ``azimuthd/*/**`` and to the liveliness tokens ``azimuthd/*/alive``, keeps the
latest payload of each topic per vehicle, checks each payload against the schema file, and
shows one row per vehicle (alive, phase, roll/pitch, heading +/- sigma and source, azimuth,
link, geofence, last event) plus the most recent events. Uses ``rich`` for the live view.

    azimuthd watch                                  # connect to tcp/127.0.0.1:7447 (the default)
    azimuthd watch --connect tcp/10.0.0.2:7447 --connect tcp/10.0.0.3:7447
    azimuthd watch --duration 5 --json              # 5 s, then the collected state as JSON
    azimuthd watch --once                           # first complete picture, print it, exit

A daemon is shown GONE when its liveliness token is withdrawn (it closed, or its process died
and the Zenoh transport lease expired), or when nothing has arrived from it for ``GONE_AFTER_S``
(a hung loop, a broken link); with no daemon heard at all the view says so and names the
endpoints it listens to.

Exit status: 0, 1 when --once/--duration ends without having received anything, 2 when the
Zenoh session cannot be opened (a malformed endpoint).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from service.schema import TOPICS, validate
from service.zenoh_bus import DEFAULT_LISTEN, KEY_PREFIX

MAX_EVENTS = 8
STALE_S = 3.0
"""A topic not heard from for this long is shown as stale."""
GONE_AFTER_S = 10.0
"""A vehicle that sent nothing for this long is GONE even with its token present: ten missed 1 Hz
health messages (a daemon starved of CPU for 6 s on the loaded test machine came back)."""


class WatchError(RuntimeError):
    """The Zenoh session could not be opened; one line for the user."""


def vehicle_status(alive: bool | None, last_rx_age_s: float | None) -> tuple[str, str]:
    """(status, why): "alive", "GONE" or "starting" from the liveliness token and the time since
    anything arrived from that vehicle."""
    if alive is False:
        return "GONE", "liveliness token withdrawn (daemon stopped or its process died)"
    if last_rx_age_s is not None and last_rx_age_s > GONE_AFTER_S:
        return "GONE", f"nothing received for {last_rx_age_s:.0f} s"
    if last_rx_age_s is None:
        return "starting", "liveliness token seen, no data yet" if alive else "no data yet"
    return "alive", ""


@dataclass
class VehicleState:
    name: str
    alive: bool | None = None
    latest: dict[str, dict] = field(default_factory=dict)
    rx_time_s: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    schema_errors: int = 0
    last_schema_error: str = ""


class WatchState:
    """Thread-safe store fed by Zenoh callbacks, read by the renderer."""

    def __init__(self, vehicle_filter: str | None = None, clock=time.monotonic):
        self.lock = threading.Lock()
        self.vehicles: dict[str, VehicleState] = {}
        self.events: list[tuple[str, dict]] = []
        self.filter = vehicle_filter
        self.clock = clock
        self.received = 0

    def _vehicle(self, name: str) -> VehicleState:
        if name not in self.vehicles:
            self.vehicles[name] = VehicleState(name)
        return self.vehicles[name]

    def on_sample(self, key: str, payload_text: str) -> None:
        parts = key.split("/")
        if len(parts) != 3 or parts[0] != KEY_PREFIX:
            return
        _, name, topic = parts
        if self.filter and name != self.filter:
            return
        try:
            payload = json.loads(payload_text)
        except ValueError:
            payload = None
        with self.lock:
            v = self._vehicle(name)
            if topic not in TOPICS or not isinstance(payload, dict):
                v.schema_errors += 1
                v.last_schema_error = f"{topic}: not a known topic or not a JSON object"
                return
            errors = validate(topic, payload)
            if errors:
                v.schema_errors += 1
                v.last_schema_error = errors[0]
            v.latest[topic] = payload
            v.rx_time_s[topic] = self.clock()
            v.counts[topic] = v.counts.get(topic, 0) + 1
            self.received += 1
            if topic == "events":
                self.events.append((name, payload))
                del self.events[:-MAX_EVENTS]

    def on_liveliness(self, key: str, alive: bool) -> None:
        parts = key.split("/")
        if len(parts) != 3 or parts[0] != KEY_PREFIX or parts[2] != "alive":
            return
        if self.filter and parts[1] != self.filter:
            return
        with self.lock:
            self._vehicle(parts[1]).alive = alive

    def no_daemon(self) -> bool:
        """Nothing at all heard yet: no token, no sample."""
        with self.lock:
            return not self.vehicles

    def complete(self) -> bool:
        """Every known vehicle has shown its liveliness, attitude, heading and azimuth."""
        with self.lock:
            return bool(self.vehicles) and all(
                v.alive is not None and {"attitude", "heading", "azimuth"} <= set(v.latest)
                for v in self.vehicles.values())

    def snapshot(self) -> dict[str, Any]:
        """JSON-able picture: per vehicle alive, counts, schema errors, latest payload per topic."""
        now = self.clock()
        with self.lock:
            out = {}
            for name, v in sorted(self.vehicles.items()):
                age = now - max(v.rx_time_s.values()) if v.rx_time_s else None
                status, why = vehicle_status(v.alive, age)
                out[name] = {"alive": v.alive, "status": status, "status_reason": why,
                             "last_rx_age_s": None if age is None else round(age, 3),
                             "counts": dict(v.counts), "schema_errors": v.schema_errors,
                             "last_schema_error": v.last_schema_error,
                             "age_s": {t: round(now - ts, 3) for t, ts in v.rx_time_s.items()},
                             "latest": dict(v.latest)}
            return {"vehicles": out, "events": [{"vehicle": n, **e} for n, e in self.events]}


def _fmt(value: Any, fmt: str = "{:.1f}", none: str = "-") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return none
    return fmt.format(value)


def _angle_sigma(value: Any, sigma: Any) -> str:
    if value is None:
        return "-"
    s = f"{value:6.1f}"
    return s + (f" ±{sigma:.1f}" if sigma is not None else "")


def render(state: WatchState, endpoints: list[str] | None = None):
    """A rich renderable of the current state."""
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    snap = state.snapshot()
    if not snap["vehicles"]:
        return Text(no_daemon_message(endpoints or list(DEFAULT_LISTEN)), "bold yellow")
    table = Table(title="azimuthd watch", expand=False)
    for col in ("vehicle", "alive", "phase", "roll°", "pitch°", "heading° (true)", "source",
                "azimuth°", "link", "geofence", "schema"):
        table.add_column(col)
    for name, v in snap["vehicles"].items():
        lat = v["latest"]
        att, hdg, az = lat.get("attitude", {}), lat.get("heading", {}), lat.get("azimuth", {})
        health, fence = lat.get("health", {}), lat.get("geofence", {})
        stale = any(age > STALE_S for t, age in v["age_s"].items() if t in ("attitude", "heading"))
        gone = v["status"] == "GONE"
        alive = {"alive": Text("yes", "green"), "GONE": Text("GONE: " + v["status_reason"][:28], "bold red"),
                 "starting": Text("starting", "yellow")}[v["status"]]
        heading = _angle_sigma(hdg.get("heading_true_deg"), hdg.get("heading_sigma_deg"))
        # what a GONE daemon last said is history, not its state now
        link = "-" if not health or gone else ("up" if health.get("link_up") else "DOWN")
        table.add_row(name, alive, att.get("phase") or hdg.get("phase") or "-",
                      _fmt(att.get("roll_deg"), "{:+.1f}"), _fmt(att.get("pitch_deg"), "{:+.1f}"),
                      Text(heading + (" (stale)" if stale else ""),
                           "yellow" if stale or not hdg.get("heading_valid") else "green"),
                      hdg.get("heading_source", "-"),
                      _angle_sigma(az.get("azimuth_true_deg"), az.get("azimuth_sigma_deg")),
                      link, fence.get("state", "-"),
                      "ok" if not v["schema_errors"] else Text(
                          f"{v['schema_errors']} bad: {v['last_schema_error'][:40]}", "red"))
    events = Table(title="events", expand=False, show_header=True)
    for col in ("vehicle", "severity", "kind", "detail"):
        events.add_column(col)
    for e in snap["events"]:
        events.add_row(e["vehicle"], e.get("severity", ""), e.get("kind", ""), e.get("detail", ""))
    return Group(table, events)


def no_daemon_message(endpoints: list[str]) -> str:
    return (f"no azimuthd found on {', '.join(endpoints)}: no liveliness token, no data. Is the daemon "
            f"running with [zenoh] enabled, and is this its listen endpoint ([zenoh] listen, "
            f"default {DEFAULT_LISTEN[0]})?")


def open_session(connect: list[str], mode: str):
    """A Zenoh session connected to ``connect``; WatchError with one line when it cannot open
    (a malformed endpoint). An endpoint with nobody behind it opens: Zenoh keeps retrying."""
    import zenoh

    conf = zenoh.Config()
    try:
        conf.insert_json5("mode", json.dumps(mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        raise WatchError(f"cannot open a Zenoh {mode} session to {', '.join(connect)}: "
                         f"{str(exc).split(' at /')[0].strip()}") from None


def subscribe(session, state: WatchState, on_sample=None, on_liveliness=None) -> list:
    """Subscribe ``state`` to every azimuthd key and liveliness token; the optional callbacks
    get (key, payload_text) and (key, alive) after the state has taken them."""
    import zenoh

    def sample(s):
        key, text = str(s.key_expr), s.payload.to_string()
        state.on_sample(key, text)
        if on_sample is not None:
            on_sample(key, text)

    def live(s):
        key, alive = str(s.key_expr), s.kind == zenoh.SampleKind.PUT
        state.on_liveliness(key, alive)
        if on_liveliness is not None:
            on_liveliness(key, alive)

    return [session.declare_subscriber(f"{KEY_PREFIX}/*/**", sample),
            session.liveliness().declare_subscriber(f"{KEY_PREFIX}/*/alive", live, history=True)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="azimuthd watch",
                                 description="terminal dashboard of azimuthd state over Zenoh")
    ap.add_argument("--connect", action="append", metavar="ENDPOINT",
                    help=f"Zenoh endpoint of a daemon or router (repeatable); "
                         f"default {DEFAULT_LISTEN[0]}")
    ap.add_argument("--mode", choices=("peer", "client"), default="peer",
                    help="Zenoh mode (client when connecting to a router); default peer")
    ap.add_argument("--vehicle", help="show only this vehicle")
    ap.add_argument("--once", action="store_true",
                    help="wait for a complete picture (or --duration, default 10 s), print, exit")
    ap.add_argument("--duration", type=float, metavar="S", help="run for S seconds, then exit")
    ap.add_argument("--json", action="store_true",
                    help="print the final state as JSON instead of the table (with --once/--duration)")
    args = ap.parse_args(argv)
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        ap.error(f"--duration must be > 0 s, got {args.duration}")
    if args.json and not (args.once or args.duration):
        ap.error("--json needs --once or --duration")

    endpoints = args.connect or list(DEFAULT_LISTEN)
    state = WatchState(args.vehicle)
    try:
        session = open_session(endpoints, args.mode)
    except WatchError as exc:
        print(f"azimuthd watch: {exc}", file=sys.stderr)
        return 2
    subs = subscribe(session, state)
    duration = args.duration if args.duration is not None else (10.0 if args.once else None)
    t_end = None if duration is None else time.monotonic() + duration
    try:
        if args.once or args.json or not sys.stdout.isatty():
            while t_end is None or time.monotonic() < t_end:
                if args.once and state.complete():
                    time.sleep(0.2)  # let the other topics of this burst arrive
                    break
                time.sleep(0.05)
        else:
            from rich.live import Live

            with Live(render(state, endpoints), refresh_per_second=4, screen=False) as live:
                while t_end is None or time.monotonic() < t_end:
                    time.sleep(0.25)
                    live.update(render(state, endpoints))
    except KeyboardInterrupt:
        pass
    finally:
        for sub in subs:
            sub.undeclare()
        session.close()
    if state.no_daemon():
        print(f"azimuthd watch: {no_daemon_message(endpoints)}", file=sys.stderr)
    if args.json:
        print(json.dumps(state.snapshot(), indent=1))
    elif args.once or not sys.stdout.isatty():
        from rich.console import Console

        Console(width=160).print(render(state, endpoints))
    return 0 if state.received else 1


if __name__ == "__main__":
    raise SystemExit(main())
