"""Connection URLs, the way users already write them (pymavlink / MAVProxy / MAVSDK / QGC).

Accepted forms (``HOST`` may be a name, an IPv4 address or a bracketed IPv6 address ``[::1]``):

=================================  ==========================================================
``udpin:HOST:PORT``                listen for UDP datagrams; an empty host means all
                                   interfaces; port 0 = any free port
``udpout:HOST:PORT``               send UDP datagrams to HOST:PORT, receive the replies
``udp:HOST:PORT``                  pymavlink / MAVProxy: listen (udpin) for the flight
                                   controller, send (udpout) for an output (``--out``)
``HOST:PORT``                      bare, as pymavlink and MAVProxy take it: the same as ``udp:``
``tcp:HOST:PORT``, ``tcpout:``     TCP client
``tcpin:HOST:PORT``                TCP server (one client at a time); port 0 = any free port
``serial:DEVICE[:BAUD]``           serial port, e.g. ``serial:/dev/ttyAMA0:921600``
``DEVICE[:BAUD]``                  bare device path, e.g. ``/dev/ttyACM0:57600``; ``DEVICE,BAUD``
                                   (pymavlink style) is accepted too
``udpin://HOST:PORT`` ...          MAVSDK / QGC style: ``udpin://``, ``udpout://``, ``tcpin://``,
                                   ``tcp://`` and ``tcpout://`` (client), ``serial:///dev/X:BAUD``;
                                   ``udp://:14540`` listens (as in MAVSDK) for the flight
                                   controller and is refused for an output (it would wait for the
                                   ground station to speak first): the error names ``udpout:``
=================================  ==========================================================

Forms azimuthd does not serve (UDP broadcast and multicast, websockets, unix sockets, mavros'
``udp://BIND@REMOTE``, ``tcp-l://``) are refused with the form to use instead. The serial baud
rate defaults to 115200 (pymavlink's default) when omitted; it must be one of the standard POSIX
rates in :data:`STANDARD_BAUDS`. Every error is a ``ValueError`` that names the URL and what is
wrong with it. :func:`check_resolvable` looks a host name up once (at start): a name that does not
resolve is an error then, not a link retried forever.
"""
from __future__ import annotations

from dataclasses import dataclass

SCHEMES = ("udpin", "udp", "udpout", "tcp", "tcpout", "tcpin", "serial")
"""URL schemes understood by :func:`parse_url` (plus bare device paths and ``HOST:PORT``)."""

ROLES = ("fc", "out")
"""What a URL is for: "fc" the flight controller link (``--mavlink``, ``[mavlink] url``); "out" an
output mirrored to a ground station (``--out``, ``[outputs] extra_mavlink_urls``)."""

_URL_STYLE = {"udpin": "udpin", "udpout": "udpout", "tcp": "tcp", "tcpout": "tcp", "tcpin": "tcpin",
              "serial": "serial", "udp": "udp"}
"""MAVSDK / QGC ``scheme://`` forms -> our kind ("udp" depends on the role)."""

_REFUSED = {
    "udpbcast": "UDP broadcast is not supported: send to the ground station's address with "
                "udpout:HOST:PORT (or listen with udpin:0.0.0.0:PORT)",
    "mcast": "multicast is not supported: use udpout:HOST:PORT or udpin:0.0.0.0:PORT",
    "udp-b": "UDP broadcast is not supported: use udpout:HOST:PORT",
    "udp-pb": "UDP broadcast is not supported: use udpout:HOST:PORT",
    "tcp-l": "write a TCP server as tcpin:HOST:PORT",
    "serial-hwfc": "hardware flow control is not supported: use serial:DEVICE:BAUD",
    "ws": "websockets are not supported: use udpout:HOST:PORT or tcp:HOST:PORT",
    "wss": "websockets are not supported: use udpout:HOST:PORT or tcp:HOST:PORT",
    "wsserver": "websockets are not supported: use udpin:0.0.0.0:PORT or tcpin:0.0.0.0:PORT",
    "uds": "unix sockets are not supported: use udpin:127.0.0.1:PORT",
    "unix": "unix sockets are not supported: use udpin:127.0.0.1:PORT",
}
"""Schemes other tools accept that we refuse, with the form to write instead."""

DEFAULT_BAUD = 115200
STANDARD_BAUDS = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000,
                  576000, 921600, 1000000, 1152000, 1500000, 2000000, 2500000, 3000000, 3500000,
                  4000000)
"""Baud rates a Linux serial port accepts (termios B* constants)."""

_LISTEN_KINDS = ("udpin", "tcpin")


@dataclass(frozen=True, slots=True)
class Endpoint:
    """A parsed connection URL.

    kind: "udpin" | "udpout" | "tcp" | "tcpin" | "serial".
    host/port: for network kinds (host "" never appears: listeners default to "0.0.0.0").
    device/baud: for serial.
    pymavlink_url: the same endpoint as pymavlink's ``mavlink_connection`` spells it (serial:
    ``DEVICE,BAUD``), for tools that use pymavlink's own transports.
    """
    kind: str
    host: str | None
    port: int | None
    device: str | None
    baud: int | None
    pymavlink_url: str
    url: str

    @property
    def is_listener(self) -> bool:
        """True when we wait for the peer to talk first (udpin, tcpin)."""
        return self.kind in _LISTEN_KINDS

    @property
    def is_network(self) -> bool:
        return self.kind != "serial"


def _bad(url: str, what: str) -> ValueError:
    return ValueError(f"bad MAVLink URL {url!r}: {what}")


def _split_host_port(url: str, rest: str) -> tuple[str, str]:
    """'host:port' or '[v6]:port' -> (host, port string)."""
    if rest.startswith("["):
        close = rest.find("]")
        if close < 0:
            raise _bad(url, "unclosed '[' in IPv6 host")
        host = rest[1:close]
        tail = rest[close + 1:]
        if not tail.startswith(":"):
            raise _bad(url, "missing port: expected [HOST]:PORT")
        return host, tail[1:]
    if ":" not in rest:
        raise _bad(url, "missing port: expected HOST:PORT")
    host, port = rest.rsplit(":", 1)
    if ":" in host:
        raise _bad(url, f"too many ':' in {rest!r}: expected HOST:PORT (bracket IPv6 hosts: [::1]:PORT)")
    return host, port


def _parse_port(url: str, text: str, allow_zero: bool) -> int:
    text = text.strip()
    if text == "":
        raise _bad(url, "missing port: expected HOST:PORT")
    if not text.isdigit():
        raise _bad(url, f"port {text!r} is not a number")
    port = int(text)
    lo = 0 if allow_zero else 1
    if not lo <= port <= 65535:
        raise _bad(url, f"port {port} out of range [{lo}, 65535]")
    return port


def _parse_baud(url: str, text: str) -> int:
    text = text.strip()
    if not text.isdigit():
        raise _bad(url, f"baud rate {text!r} is not a positive integer")
    baud = int(text)
    if baud not in STANDARD_BAUDS:
        raise _bad(url, f"baud rate {baud} is not a standard rate (one of "
                        f"{', '.join(str(b) for b in STANDARD_BAUDS)})")
    return baud


def _parse_serial(url: str, rest: str) -> Endpoint:
    if rest == "":
        raise _bad(url, "missing serial device, e.g. serial:/dev/ttyAMA0:921600")
    device, baud_text = rest, None
    if "," in rest:
        device, baud_text = rest.rsplit(",", 1)
    elif ":" in rest:
        head, tail = rest.rsplit(":", 1)
        # a trailing ':<digits>' (or ':<junk>' after a device path) is the baud rate
        device, baud_text = head, tail
    if device == "":
        raise _bad(url, "missing serial device, e.g. serial:/dev/ttyAMA0:921600")
    if not device.startswith("/") and not device.upper().startswith("COM"):
        raise _bad(url, f"serial device {device!r} is not an absolute path (e.g. /dev/ttyACM0)")
    baud = DEFAULT_BAUD if baud_text is None else _parse_baud(url, baud_text)
    return Endpoint("serial", None, None, device, baud, f"{device},{baud}", url)


def _network(url: str, kind: str, rest: str) -> Endpoint:
    host, port_text = _split_host_port(url, rest)
    port = _parse_port(url, port_text, allow_zero=kind in _LISTEN_KINDS)
    host = host.strip()
    if host == "":
        if kind in _LISTEN_KINDS:
            host = "0.0.0.0"
        else:
            raise _bad(url, f"missing host: {kind} needs HOST:PORT (e.g. {kind}:127.0.0.1:5760)")
    if any(c.isspace() for c in host) or "/" in host or "@" in host:
        raise _bad(url, f"host {host!r} is not a valid host name or address")
    shown_host = f"[{host}]" if ":" in host else host
    return Endpoint(kind, host, port, None, None, f"{kind}:{shown_host}:{port}", url)


def _is_bare_host_port(text: str) -> bool:
    """'HOST:PORT' or '[V6]:PORT' with a numeric port and no scheme (pymavlink's bare UDP form)."""
    if text.startswith("["):
        close = text.find("]")
        return close > 0 and text[close + 1:close + 2] == ":" and text[close + 2:].strip().isdigit()
    return text.count(":") == 1 and text.rsplit(":", 1)[1].strip().isdigit()


def _udp_kind(role: str) -> str:
    return "udpin" if role == "fc" else "udpout"


def _parse_url_style(url: str, scheme: str, rest: str, role: str) -> Endpoint:
    """MAVSDK / QGC ``scheme://rest``."""
    kind = _URL_STYLE[scheme]
    if kind == "serial":
        return _parse_serial(url, rest)
    if kind == "udp":
        if "@" in rest:
            raise _bad(url, "mavros' udp://BIND@REMOTE is not supported: write udpin:BIND:PORT to listen "
                            "or udpout:REMOTE:PORT to send")
        if role == "out":
            raise _bad(url, "udp:// listens (MAVSDK's meaning) and a ground station does not speak "
                            f"first: to send to it write udpout:{rest or 'HOST:PORT'}")
        kind = "udpin"
    return _network(url, kind, rest.rstrip("/"))


def parse_url(url: str, role: str = "fc") -> Endpoint:
    """Parse a MAVLink connection URL into an :class:`Endpoint`.

    role: "fc" (the flight controller link) or "out" (an output to a ground station): ``udp:`` and
    bare ``HOST:PORT`` mean udpin for the FC and udpout for an output, as in MAVProxy's
    ``--master`` and ``--out``.
    Raises ValueError naming the URL and the problem (unknown scheme, missing or non-numeric port,
    port out of range, missing host, bad baud rate, a form we do not serve with the one to use).
    """
    if role not in ROLES:
        raise ValueError(f"parse_url: role must be one of {', '.join(ROLES)}, got {role!r}")
    if not isinstance(url, str):
        raise ValueError(f"bad MAVLink URL {url!r}: must be a string, got {type(url).__name__}")
    text = url.strip()
    if text == "":
        raise ValueError("bad MAVLink URL '': empty (expected e.g. udpin:0.0.0.0:14550)")
    if text.startswith("/"):
        return _parse_serial(url, text)
    if "://" in text:
        scheme, rest = text.split("://", 1)
        scheme_l = scheme.lower()
        if scheme_l in _REFUSED:
            raise _bad(url, _REFUSED[scheme_l])
        if scheme_l not in _URL_STYLE:
            raise _bad(url, f"unknown scheme {scheme!r}: expected one of "
                            f"{', '.join(s + '://' for s in _URL_STYLE)} or {', '.join(s + ':' for s in SCHEMES)}")
        return _parse_url_style(url, scheme_l, rest, role)
    if ":" not in text:
        raise _bad(url, "no scheme: expected one of "
                        f"{', '.join(s + ':' for s in SCHEMES)}, HOST:PORT or a device path like /dev/ttyACM0:57600")
    scheme, rest = text.split(":", 1)
    scheme_l = scheme.lower()
    if scheme_l in _REFUSED:
        raise _bad(url, _REFUSED[scheme_l])
    if scheme_l not in SCHEMES:
        if _is_bare_host_port(text):
            return _network(url, _udp_kind(role), text)
        raise _bad(url, f"unknown scheme {scheme!r}: expected one of {', '.join(SCHEMES)}, HOST:PORT "
                        "or a device path like /dev/ttyACM0:57600")
    if scheme_l == "serial":
        return _parse_serial(url, rest)
    kind = {"udp": _udp_kind(role), "tcpout": "tcp"}.get(scheme_l, scheme_l)
    return _network(url, kind, rest)


def check_resolvable(endpoint: Endpoint) -> None:
    """Look the endpoint's host up once; ValueError naming the URL when it does not resolve.

    Called at start, so that a mistyped host is a clear error there instead of a link that is
    retried for ever. Serial endpoints are not checked here (a device may appear later: USB)."""
    if not endpoint.is_network:
        return
    import socket
    try:
        socket.getaddrinfo(endpoint.host, endpoint.port, type=socket.SOCK_DGRAM
                           if endpoint.kind.startswith("udp") else socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as exc:
        reason = exc.strerror if isinstance(exc, socket.gaierror) and exc.strerror else str(exc)
        raise _bad(endpoint.url, f"host {endpoint.host!r} does not resolve ({reason}): "
                                 "write an IP address or a name this machine resolves") from None
