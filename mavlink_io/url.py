"""Connection URLs, the way users already write them (MAVProxy / pymavlink / mavlink-router style).

Accepted forms (``HOST`` may be a name, an IPv4 address or a bracketed IPv6 address ``[::1]``):

=============================  ==============================================================
``udpin:HOST:PORT``            listen for UDP datagrams (``udp:`` is an alias, as in pymavlink);
                               an empty host means all interfaces; port 0 = any free port
``udpout:HOST:PORT``           send UDP datagrams to HOST:PORT, receive the replies
``tcp:HOST:PORT``              TCP client
``tcpin:HOST:PORT``            TCP server (one client at a time); port 0 = any free port
``serial:DEVICE[:BAUD]``       serial port, e.g. ``serial:/dev/ttyAMA0:921600``
``DEVICE[:BAUD]``              bare device path, e.g. ``/dev/ttyACM0:57600``; ``DEVICE,BAUD``
                               (pymavlink style) is accepted too
=============================  ==============================================================

The serial baud rate defaults to 115200 (pymavlink's default) when omitted; it must be one of the
standard POSIX rates in :data:`STANDARD_BAUDS`. Every error is a ``ValueError`` that names the URL
and what is wrong with it.
"""
from __future__ import annotations

from dataclasses import dataclass

SCHEMES = ("udpin", "udp", "udpout", "tcp", "tcpin", "serial")
"""URL schemes understood by :func:`parse_url` (plus bare device paths)."""

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


def parse_url(url: str) -> Endpoint:
    """Parse a MAVLink connection URL into an :class:`Endpoint`.

    Raises ValueError naming the URL and the problem (unknown scheme, missing or non-numeric port,
    port out of range, missing host, bad baud rate, ...).
    """
    if not isinstance(url, str):
        raise ValueError(f"bad MAVLink URL {url!r}: must be a string, got {type(url).__name__}")
    text = url.strip()
    if text == "":
        raise ValueError("bad MAVLink URL '': empty (expected e.g. udpin:0.0.0.0:14550)")
    if text.startswith("/"):
        return _parse_serial(url, text)
    if ":" not in text:
        raise _bad(url, "no scheme: expected one of "
                        f"{', '.join(s + ':' for s in SCHEMES)} or a device path like /dev/ttyACM0:57600")
    scheme, rest = text.split(":", 1)
    scheme_l = scheme.lower()
    if scheme_l not in SCHEMES:
        raise _bad(url, f"unknown scheme {scheme!r}: expected one of {', '.join(SCHEMES)} "
                        "or a device path like /dev/ttyACM0:57600")
    if scheme_l == "serial":
        return _parse_serial(url, rest)
    kind = "udpin" if scheme_l == "udp" else scheme_l
    host, port_text = _split_host_port(url, rest)
    port = _parse_port(url, port_text, allow_zero=kind in _LISTEN_KINDS)
    host = host.strip()
    if host == "":
        if kind in _LISTEN_KINDS:
            host = "0.0.0.0"
        else:
            raise _bad(url, f"missing host: {kind} needs HOST:PORT (e.g. {kind}:127.0.0.1:5760)")
    if any(c.isspace() for c in host) or "/" in host:
        raise _bad(url, f"host {host!r} is not a valid host name or address")
    shown_host = f"[{host}]" if ":" in host else host
    return Endpoint(kind, host, port, None, None, f"{kind}:{shown_host}:{port}", url)
