"""The ``azimuthd`` command: run | sim | watch (DESIGN.md, "Command line")."""
from __future__ import annotations

import argparse
import os
import sys

# The estimators multiply 3x3 to 20x20 matrices: a threaded BLAS only adds locking and context
# switches (measured much slower on a busy 2-core machine). Set before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
from importlib.metadata import PackageNotFoundError, version


def _version() -> str:
    try:
        return version("azimuthd")
    except PackageNotFoundError:
        return "unknown"


def _cmd_run(argv: list[str]) -> int:
    from service.config import DEFAULT_CONFIG_PATH, ConfigError, load
    from service.logs import setup_logging

    ap = argparse.ArgumentParser(prog="azimuthd run", description="Run the daemon against a flight controller.")
    ap.add_argument("--config", default=DEFAULT_CONFIG_PATH, help=f"TOML config (default {DEFAULT_CONFIG_PATH})")
    ap.add_argument("--mavlink", metavar="URL", help="flight controller URL; overrides [mavlink] url")
    ap.add_argument("--status-interval", type=float, metavar="S",
                    help="print a status line every S seconds; overrides [outputs] status_interval_s")
    ap.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (tests, demos)")
    args = ap.parse_args(argv)
    try:
        cfg = load(args.config)
        if args.mavlink is not None:
            from mavlink_io.url import parse_url
            try:
                parse_url(args.mavlink)
            except ValueError as exc:
                raise ConfigError(f"--mavlink: {exc}") from None
            cfg["mavlink"]["url"] = args.mavlink
        if args.status_interval is not None:
            if not args.status_interval >= 0:
                raise ConfigError(f"--status-interval: must be >= 0, got {args.status_interval}")
            cfg["outputs"]["status_interval_s"] = args.status_interval
    except ConfigError as exc:
        print(f"azimuthd: config error: {exc}", file=sys.stderr)
        return 2
    setup_logging(cfg["service"]["log_level"])
    from service.daemon import Daemon
    try:
        daemon = Daemon(cfg)
    except ConfigError as exc:  # found while starting: e.g. the signing key file
        print(f"azimuthd: config error: {exc}", file=sys.stderr)
        return 2
    return daemon.run(duration_s=args.duration)


def _cmd_sim(argv: list[str]) -> int:
    from sim.cli import main as sim_main
    return sim_main(argv)


def _cmd_replay(argv: list[str]) -> int:
    from service.replay import main as replay_main
    return replay_main(argv)


def _cmd_watch(argv: list[str]) -> int:
    from service.watch import main as watch_main
    return watch_main(argv)


COMMANDS = {
    "run": (_cmd_run, "the daemon: estimate heading and attitude from a flight controller's sensors"),
    "sim": (_cmd_sim, "the bundled MAVLink flight simulator, as an autopilot"),
    "replay": (_cmd_replay, "a recorded flight log (.tlog, .bin, .ulg) through the same estimators, offline"),
    "watch": (_cmd_watch, "terminal dashboard over Zenoh"),
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(
        prog="azimuthd",
        description="GNSS-denied heading and attitude for UAVs, as a MAVLink companion-computer service.",
        epilog="Run 'azimuthd COMMAND --help' for a command's options.")
    ap.add_argument("--version", action="version", version=f"azimuthd {_version()}")
    ap.add_argument("command", choices=sorted(COMMANDS), metavar="COMMAND",
                    help="; ".join(f"{k}: {v[1]}" for k, v in COMMANDS.items()))
    if not argv or argv[0] in ("-h", "--help", "--version"):
        ap.parse_args(argv or ["--help"])
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        ap.print_usage(sys.stderr)
        print(f"azimuthd: unknown command {cmd!r} (choose from {', '.join(sorted(COMMANDS))})", file=sys.stderr)
        return 2
    try:
        return COMMANDS[cmd][0](rest)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
