"""``azimuthd web``: serve the dashboard page and stream the Zenoh state to it.

    azimuthd web                                   # Zenoh tcp/127.0.0.1:7447, page on http://127.0.0.1:8765/
    azimuthd web --connect tcp/10.0.0.2:7447 --connect tcp/10.0.0.3:7447 --listen 127.0.0.1:9000

The standard library only: ``http.server.ThreadingHTTPServer``; the live data as Server-Sent
Events (``GET /events``, one JSON message per event, see service/web/hub.py), which the browser's
EventSource reconnects by itself. The page, its script and style come from this package
(``static/``): no CDN, no internet. ``GET /api/state`` returns the current snapshot as JSON.

The page has no authentication: it listens on loopback unless told otherwise, and says so when
told otherwise.

Exit status: 0 on SIGINT/SIGTERM, 2 when the listen address or a Zenoh endpoint is unusable
(one line on stderr, no traceback).
"""
from __future__ import annotations

import argparse
import errno
import ipaddress
import json
import queue
import signal
import sys
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from service.watch import GONE_AFTER_S, WatchError, open_session, subscribe
from service.web.hub import Hub
from service.zenoh_bus import DEFAULT_LISTEN

DEFAULT_HTTP = "127.0.0.1:8765"
STATIC_DIR = Path(__file__).with_name("static")
STATIC_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml"}
KEEPALIVE_S = 10.0
"""An SSE comment line this often when there is nothing to send (proxies close idle streams)."""
TICK_S = 1.0


def parse_listen(text: str) -> tuple[str, int]:
    """'HOST:PORT' (or '[v6]:PORT') -> (host, port); ValueError with the expected form."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ValueError(f"--listen must be HOST:PORT with a port in 1..65535, e.g. {DEFAULT_HTTP}; got {text!r}")
    return host, int(port)


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def make_handler(hub: Hub, stopping: threading.Event):
    class Handler(BaseHTTPRequestHandler):
        server_version = "azimuthd-web"
        protocol_version = "HTTP/1.1"

        def log_message(self, *args) -> None:  # no access log on the terminal
            pass

        def _send(self, status: int, body: bytes, ctype: str) -> None:
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            path = self.path.split("?", 1)[0]
            if path in ("/", "/index.html"):
                path = "/static/index.html"
            elif path == "/favicon.ico":
                path = "/static/icon.svg"
            if path == "/events":
                self._events()
            elif path == "/api/state":
                self._send(200, json.dumps(hub.snapshot()).encode(), "application/json")
            elif path.startswith("/static/"):
                name = path[len("/static/"):]
                f = STATIC_DIR / name
                # only files of this package's static directory, by plain name
                if "/" in name or name.startswith(".") or f.suffix not in STATIC_TYPES or not f.is_file():
                    self._send(404, b"not found\n", "text/plain")
                else:
                    self._send(200, f.read_bytes(), STATIC_TYPES[f.suffix])
            else:
                self._send(404, b"not found\n", "text/plain")

        def _events(self) -> None:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.send_header("Connection", "close")
            self.end_headers()
            self.close_connection = True
            client = hub.connect()
            try:
                self.wfile.write(b"retry: 2000\n\n")
                while not stopping.is_set():
                    try:
                        line = client.queue.get(timeout=KEEPALIVE_S)
                    except queue.Empty:
                        self.wfile.write(b": keepalive\n\n")
                        self.wfile.flush()
                        continue
                    self.wfile.write(b"data: " + line.encode() + b"\n\n")
                    self.wfile.flush()
            except (BrokenPipeError, ConnectionResetError, TimeoutError):
                pass  # the browser went away
            finally:
                hub.disconnect(client)

    return Handler


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="azimuthd web",
                                 description="browser dashboard of azimuthd state over Zenoh (docs/DASHBOARD.md)")
    ap.add_argument("--connect", action="append", metavar="ENDPOINT",
                    help=f"Zenoh endpoint of a daemon or router (repeatable); default {DEFAULT_LISTEN[0]}")
    ap.add_argument("--mode", choices=("peer", "client"), default="peer",
                    help="Zenoh mode (client when connecting to a router); default peer")
    ap.add_argument("--listen", default=DEFAULT_HTTP, metavar="HOST:PORT",
                    help=f"where the page is served; default {DEFAULT_HTTP} (this machine only)")
    ap.add_argument("--vehicle", help="show only this vehicle")
    ap.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (tests)")
    args = ap.parse_args(argv)
    try:
        host, port = parse_listen(args.listen)
    except ValueError as exc:
        ap.error(str(exc))
    if args.duration is not None and not args.duration > 0:
        ap.error(f"--duration must be > 0 s, got {args.duration}")
    endpoints = args.connect or list(DEFAULT_LISTEN)

    stopping = threading.Event()
    hub = Hub(endpoints, args.vehicle)
    try:
        httpd = ThreadingHTTPServer((host, port), make_handler(hub, stopping))
    except OSError as exc:
        why = ("address already in use (another azimuthd web? choose another --listen HOST:PORT)"
               if exc.errno == errno.EADDRINUSE else exc.strerror or str(exc))
        print(f"azimuthd web: cannot listen on {host}:{port}: {why}", file=sys.stderr)
        return 2
    httpd.daemon_threads = True
    try:
        session = open_session(endpoints, args.mode)
    except WatchError as exc:
        httpd.server_close()
        print(f"azimuthd web: {exc}", file=sys.stderr)
        return 2
    subs = subscribe(session, hub.state, hub.on_sample, hub.on_liveliness)

    def on_signal(_signum, _frame) -> None:
        stopping.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_signal)
    shown = f"http://{'[' + host + ']' if ':' in host else host}:{httpd.server_address[1]}/"
    print(f"azimuthd web: serving {shown} (Zenoh {', '.join(endpoints)})", flush=True)
    if not _is_loopback(host):
        print(f"azimuthd web: warning: {host} is not loopback and the page has no authentication: "
              "anyone who can reach it sees the vehicles' state", file=sys.stderr, flush=True)
    server = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.2}, daemon=True)
    server.start()
    t_end = None if args.duration is None else time.monotonic() + args.duration
    said_none = False
    t_start = time.monotonic()
    try:
        while not stopping.is_set() and (t_end is None or time.monotonic() < t_end):
            stopping.wait(TICK_S)
            hub.tick()
            if not said_none and hub.state.no_daemon() and time.monotonic() - t_start > GONE_AFTER_S:
                said_none = True  # once on the terminal; the page keeps saying it
                print(f"azimuthd web: {hub.status()['message']}", file=sys.stderr, flush=True)
    finally:
        stopping.set()
        httpd.shutdown()
        httpd.server_close()
        for sub in subs:
            sub.undeclare()
        session.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
