"""``azimuthd sim`` / ``python -m sim``: the simulated UAV as a MAVLink autopilot.

    azimuthd sim --scenario NAME_OR_FILE --mavlink URL [--mavlink URL ...] [--speed X] [--seed N]
                 [--imu-grade consumer|tactical] [--personality ardupilot|px4] [--truth-log FILE]
                 [--duration S] [--set SECTION.KEY=VALUE ...] [--list-scenarios] [-v]

URL is the autopilot side's endpoint: ``udpin:0.0.0.0:14560`` waits for a peer and answers it,
``udpout:127.0.0.1:14550`` pushes to a known peer, ``tcpin:0.0.0.0:5760`` serves TCP,
``serial:/dev/ttyUSB0:57600`` is a serial port (a pty for hardware-in-the-loop tests); the forms of
``azimuthd run`` (mavlink_io/url.py). Several ``--mavlink`` serve several ports at once, like a
flight controller's TELEM1/TELEM2: every port gets what the FC sends, and what arrives on one port
that is not addressed to the FC itself is forwarded to the others (sim/endpoints.py).
Exit codes: 0 done (scenario end, SIGINT/SIGTERM), 1 runtime failure, 2 bad arguments.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
import tomllib


def _parse_set(items: list[str]) -> dict:
    """--set a.b=VALUE (VALUE parsed as a TOML value, else a string) -> nested dict."""
    out: dict = {}
    for it in items:
        if "=" not in it:
            raise ValueError(f"--set wants SECTION.KEY=VALUE, got {it!r}")
        key, val = it.split("=", 1)
        try:
            v = tomllib.loads(f"v = {val}")["v"]
        except tomllib.TOMLDecodeError:
            v = val
        parts = key.strip().split(".")
        d = out
        for p in parts[:-1]:
            d = d.setdefault(p, {})
        d[parts[-1]] = v
    return out


DEFAULT_URL = "udpin:0.0.0.0:14560"


def parse_endpoints(urls: list[str]) -> list:
    """--mavlink values -> parsed endpoints (ValueError naming the bad one); hosts resolved once."""
    from mavlink_io.url import check_resolvable, parse_url
    out = []
    for u in urls:
        ep = parse_url(u, "fc")  # pymavlink's meanings: udp: and bare HOST:PORT listen
        check_resolvable(ep)
        out.append(ep)
    return out


def open_ports(ap, endpoints: list):
    """The autopilot's connection: pymavlink's own for one network endpoint (as before), else
    sim.endpoints.Ports over all of them (serial included)."""
    from sim.endpoints import Ports, open_endpoint
    if len(endpoints) == 1 and endpoints[0].is_network:
        ap.url = endpoints[0].pymavlink_url
        return ap.open()
    conns = []
    try:
        for ep in endpoints:
            conns.append(open_endpoint(ep, ap.sysid, ap.compid))
    except OSError:
        for c in conns:
            c.close()
        raise
    ap.conn = Ports(conns, ap.sysid, ap.compid)
    return ap.conn


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="azimuthd sim", description="The bundled simulated UAV, a MAVLink autopilot.")
    p.add_argument("--scenario", default="inclined_rail", help="scenario name (sim/scenarios/) or TOML file")
    p.add_argument("--mavlink", action="append", metavar="URL",
                   help=f"autopilot-side endpoint, repeatable (default {DEFAULT_URL}): udpin:HOST:PORT | "
                        "udpout:HOST:PORT | tcpin:HOST:PORT | tcp:HOST:PORT | serial:/dev/ttyX:BAUD")
    p.add_argument("--speed", type=float, default=1.0, help="time scale: 1 real time, X>1 faster, 0 as fast as possible")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--imu-grade", choices=("consumer", "tactical"), default="consumer")
    p.add_argument("--personality", choices=("ardupilot", "px4"), default=None,
                   help="default: the scenario's autopilot.personality (ardupilot)")
    p.add_argument("--truth-log", default=None, help="truth log file (.csv appended live, else .npz at exit)")
    p.add_argument("--truth-log-rate", type=float, default=100.0, help="truth log rows per simulated second")
    p.add_argument("--duration", type=float, default=None,
                   help="stop after this much simulated time, s (default the scenario's duration_s; 0 = never)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a scenario key (TOML value), repeatable, e.g. --set launcher.azimuth_deg=120")
    p.add_argument("--list-scenarios", action="store_true", help="print the shipped scenarios and exit")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    from sim.scenario import available_scenarios
    if args.list_scenarios:
        print("\n".join(available_scenarios()))
        return 0
    urls = args.mavlink or [DEFAULT_URL]
    try:
        endpoints = parse_endpoints(urls)
        overrides = _parse_set(args.set)
        from sim.autopilot import Autopilot, install_signal_handlers
        ap = Autopilot(args.scenario, endpoints[0].pymavlink_url, seed=args.seed, imu_grade=args.imu_grade,
                       personality=args.personality, speed=args.speed, truth_log=args.truth_log,
                       overrides=overrides, duration_s=args.duration, truth_log_rate_hz=args.truth_log_rate)
    except ValueError as exc:
        print(f"azimuthd sim: error: {exc}", file=sys.stderr)
        return 2
    try:
        open_ports(ap, endpoints)
    except OSError as exc:
        print(f"azimuthd sim: cannot open {' '.join(urls)}: {exc}", file=sys.stderr)
        return 1
    if len(endpoints) > 1 or not endpoints[0].is_network:
        logging.getLogger("azimuthd.sim").info("serving %d MAVLink ports: %s", len(endpoints), ", ".join(urls))
    install_signal_handlers(ap)
    wall0 = time.monotonic()
    try:
        rc = ap.run()
    except OSError as exc:
        print(f"azimuthd sim: link failure: {exc}", file=sys.stderr)
        return 1
    wall_s = time.monotonic() - wall0
    # what a harness (bench/live_demo.py) reads: how far and how fast the flight actually went
    logging.getLogger("azimuthd.sim").info(
        "sim stopped: simulated_s=%.3f wall_s=%.3f achieved_speed=%.3f sent=%s", ap.t, wall_s,
        ap.t / wall_s if wall_s > 0 else float("nan"), json.dumps(dict(sorted(ap.counts.items())), separators=(",", ":")))
    return rc
