"""The ``azimuthd`` command: run | sim | watch (DESIGN.md, "Command line")."""
from __future__ import annotations

import argparse
import os
import sys

# The estimators multiply 3x3 to 20x20 matrices: a threaded BLAS only adds locking and context
# switches (measured much slower on a busy 2-core machine). Set before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version  # ~50 ms of imports: only for --version
    try:
        return version("azimuthd")
    except PackageNotFoundError:
        return "unknown"


class _VersionAction(argparse.Action):
    """argparse's "version" action with the version looked up only when asked for."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="show program's version number and exit"):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"azimuthd {_version()}")
        parser.exit()


DEFAULT_TTY_STATUS_INTERVAL_S = 1.0
"""Status line period when stdout is a terminal and neither --status-interval nor the config asks."""


def _run_parser(default_config: str) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="azimuthd run", description="Run the daemon against a flight controller.",
        epilog="URLs: udpin:ADDR:PORT, udpout:HOST:PORT, udp:HOST:PORT or HOST:PORT (listen for the FC, send for --out, "
               "as MAVProxy's --master/--out), tcp:HOST:PORT, tcpin:ADDR:PORT, serial:/dev/ttyACM0:57600, "
               "and MAVSDK's udp://:14540, udpin://, udpout://, tcp://, serial:///dev/ttyACM0:57600. "
               "SIGHUP saves the calibrations and checks the config file; it never stops the daemon "
               "(a changed config is applied by a restart).")
    ap.add_argument("--config", default=default_config, help=f"TOML config (default {default_config})")
    ap.add_argument("--mavlink", metavar="URL", help="flight controller URL; overrides [mavlink] url")
    ap.add_argument("--out", metavar="URL", action="append", default=[],
                    help="also send our outputs to this URL (a ground station), like MAVProxy's --out; "
                         "repeatable; added to [outputs] extra_mavlink_urls, e.g. --out udpout:127.0.0.1:14550")
    ap.add_argument("--status-interval", type=float, metavar="S",
                    help="print a status line every S seconds (0 = never); overrides [outputs] status_interval_s; "
                         f"default on a terminal: {DEFAULT_TTY_STATUS_INTERVAL_S:g}")
    ap.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (tests, demos)")
    return ap


def _apply_run_overrides(cfg: dict, args, stdout_is_tty: bool) -> None:
    """--mavlink, --out, --status-interval onto the loaded config; every URL's host resolved once.
    Raises ConfigError naming the option and the problem."""
    from mavlink_io.url import check_resolvable, parse_url
    from service.config import ConfigError
    if args.mavlink is not None:
        try:
            parse_url(args.mavlink, "fc")
        except ValueError as exc:
            raise ConfigError(f"--mavlink: {exc}") from None
        cfg["mavlink"]["url"] = args.mavlink
    for url in args.out:
        try:
            parse_url(url, "out")
        except ValueError as exc:
            raise ConfigError(f"--out: {exc}") from None
    cfg["outputs"]["extra_mavlink_urls"] = [*cfg["outputs"]["extra_mavlink_urls"], *args.out]
    checks = [("--mavlink" if args.mavlink is not None else "mavlink.url", cfg["mavlink"]["url"], "fc")]
    checks += [("--out" if u in args.out else "outputs.extra_mavlink_urls", u, "out")
               for u in cfg["outputs"]["extra_mavlink_urls"]]
    for where, url, role in checks:
        try:
            check_resolvable(parse_url(url, role))
        except ValueError as exc:
            raise ConfigError(f"{where}: {exc}") from None
    if args.status_interval is not None:
        if not args.status_interval >= 0:
            raise ConfigError(f"--status-interval: must be >= 0, got {args.status_interval}")
        cfg["outputs"]["status_interval_s"] = args.status_interval
    elif stdout_is_tty and cfg["outputs"]["status_interval_s"] == 0:
        cfg["outputs"]["status_interval_s"] = DEFAULT_TTY_STATUS_INTERVAL_S


def _cmd_run(argv: list[str]) -> int:
    import copy

    from service.config import DEFAULT_CONFIG_PATH, ConfigError, load
    from service.logs import setup_logging

    args = _run_parser(DEFAULT_CONFIG_PATH).parse_args(argv)
    try:
        file_cfg = load(args.config)
        cfg = copy.deepcopy(file_cfg)
        _apply_run_overrides(cfg, args, sys.stdout.isatty())
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
    daemon.config_file = (args.config, file_cfg)  # SIGHUP checks the file against what we started with
    return daemon.run(duration_s=args.duration)


def _cmd_sim(argv: list[str]) -> int:
    from sim.cli import main as sim_main
    return sim_main(argv)


def missing_extra(module: str, extra: str, what: str) -> str | None:
    """The one-line message for an optional dependency that is not installed, else None."""
    import importlib.util
    if importlib.util.find_spec(module) is not None:
        return None
    return (f"{what} needs {module}, an optional part of azimuthd: pip install 'azimuthd[{extra}]' "
            f"(into the same environment as azimuthd)")


def _cmd_replay(argv: list[str]) -> int:
    if any(a == "--plot" or a.startswith("--plot=") for a in argv):
        msg = missing_extra("matplotlib", "plot", "--plot")
        if msg:  # said before a long replay, not after it
            print(f"azimuthd replay: {msg}", file=sys.stderr)
            return 2
    from service.replay import main as replay_main
    return replay_main(argv)


def _cmd_watch(argv: list[str]) -> int:
    if "--json" not in argv and not any(a in ("-h", "--help") for a in argv):
        msg = missing_extra("rich", "tui", "the terminal dashboard")
        if msg:
            print(f"azimuthd watch: {msg}; or use --json", file=sys.stderr)
            return 2
    from service.watch import main as watch_main
    return watch_main(argv)


def _cmd_web(argv: list[str]) -> int:
    from service.web.server import main as web_main
    return web_main(argv)


COMMANDS = {
    "run": (_cmd_run, "the daemon: estimate heading and attitude from a flight controller's sensors"),
    "sim": (_cmd_sim, "the bundled MAVLink flight simulator, as an autopilot"),
    "replay": (_cmd_replay, "a recorded flight log (.tlog, .bin, .ulg) through the same estimators, offline"),
    "watch": (_cmd_watch, "terminal dashboard over Zenoh"),
    "web": (_cmd_web, "browser dashboard over Zenoh, served on localhost"),
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(
        prog="azimuthd",
        description="GNSS-denied heading and attitude for UAVs, as a MAVLink companion-computer service.",
        epilog="Run 'azimuthd COMMAND --help' for a command's options.")
    ap.add_argument("--version", action=_VersionAction)
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
