"""``azimuthd sim`` / ``python -m sim``: the simulated UAV as a MAVLink autopilot.

    azimuthd sim --scenario NAME_OR_FILE --mavlink URL [--speed X] [--seed N]
                 [--imu-grade consumer|tactical] [--personality ardupilot|px4] [--truth-log FILE]
                 [--duration S] [--set SECTION.KEY=VALUE ...] [--list-scenarios] [-v]

URL is the autopilot side's pymavlink endpoint: ``udpin:0.0.0.0:14560`` waits for a peer and
answers it, ``udpout:127.0.0.1:14550`` pushes to a known peer, ``tcpin:0.0.0.0:5760`` serves TCP.
Exit codes: 0 done (scenario end, SIGINT/SIGTERM), 1 runtime failure, 2 bad arguments.
"""
from __future__ import annotations

import argparse
import logging
import sys
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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="azimuthd sim", description="The bundled simulated UAV, a MAVLink autopilot.")
    p.add_argument("--scenario", default="inclined_rail", help="scenario name (sim/scenarios/) or TOML file")
    p.add_argument("--mavlink", default="udpin:0.0.0.0:14560",
                   help="autopilot-side endpoint: udpin:HOST:PORT | udpout:HOST:PORT | tcpin:HOST:PORT | tcp:HOST:PORT")
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
    try:
        overrides = _parse_set(args.set)
        from sim.autopilot import Autopilot, install_signal_handlers
        ap = Autopilot(args.scenario, args.mavlink, seed=args.seed, imu_grade=args.imu_grade,
                       personality=args.personality, speed=args.speed, truth_log=args.truth_log,
                       overrides=overrides, duration_s=args.duration, truth_log_rate_hz=args.truth_log_rate)
    except ValueError as exc:
        print(f"azimuthd sim: error: {exc}", file=sys.stderr)
        return 2
    try:
        ap.open()
    except OSError as exc:
        print(f"azimuthd sim: cannot open {args.mavlink}: {exc}", file=sys.stderr)
        return 1
    install_signal_handlers(ap)
    try:
        return ap.run()
    except OSError as exc:
        print(f"azimuthd sim: link failure: {exc}", file=sys.stderr)
        return 1
