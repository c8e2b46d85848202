"""Connection URLs: the forms users write, and clear errors for the ones that are wrong."""
import pytest

import socket

from mavlink_io.url import check_resolvable, parse_url


@pytest.mark.parametrize("url, kind, host, port, device, baud, pym", [
    ("udpin:0.0.0.0:14550", "udpin", "0.0.0.0", 14550, None, None, "udpin:0.0.0.0:14550"),
    ("udp:127.0.0.1:14550", "udpin", "127.0.0.1", 14550, None, None, "udpin:127.0.0.1:14550"),
    ("udpin::14550", "udpin", "0.0.0.0", 14550, None, None, "udpin:0.0.0.0:14550"),
    ("udpout:192.168.1.10:14555", "udpout", "192.168.1.10", 14555, None, None, "udpout:192.168.1.10:14555"),
    ("tcp:localhost:5760", "tcp", "localhost", 5760, None, None, "tcp:localhost:5760"),
    ("tcpin:0.0.0.0:5761", "tcpin", "0.0.0.0", 5761, None, None, "tcpin:0.0.0.0:5761"),
    ("udpin:[::]:14550", "udpin", "::", 14550, None, None, "udpin:[::]:14550"),
    ("serial:/dev/ttyAMA0:921600", "serial", None, None, "/dev/ttyAMA0", 921600, "/dev/ttyAMA0,921600"),
    ("/dev/ttyACM0:57600", "serial", None, None, "/dev/ttyACM0", 57600, "/dev/ttyACM0,57600"),
    ("/dev/ttyACM0,57600", "serial", None, None, "/dev/ttyACM0", 57600, "/dev/ttyACM0,57600"),
    ("/dev/ttyUSB0", "serial", None, None, "/dev/ttyUSB0", 115200, "/dev/ttyUSB0,115200"),
    ("serial:/dev/serial0", "serial", None, None, "/dev/serial0", 115200, "/dev/serial0,115200"),
])
def test_good_urls(url, kind, host, port, device, baud, pym):
    ep = parse_url(url)
    assert (ep.kind, ep.host, ep.port, ep.device, ep.baud, ep.pymavlink_url) == (kind, host, port, device, baud, pym)
    assert ep.url == url


@pytest.mark.parametrize("url, fragment", [
    ("", "empty"),
    ("foo:1.2.3.4:14550", "unknown scheme 'foo'"),
    ("udpbcast:1.2.3.4:14550", "UDP broadcast is not supported: send to the ground station's address with udpout:"),
    ("mcast:239.0.0.1:14550", "multicast is not supported"),
    ("tcp-l://0.0.0.0:5760", "write a TCP server as tcpin:HOST:PORT"),
    ("udp://0.0.0.0:14550@10.0.0.2:14550", "mavros' udp://BIND@REMOTE is not supported"),
    ("wss://gcs:443", "websockets are not supported"),
    ("http://127.0.0.1:14550", "unknown scheme 'http'"),
    ("udp://127.0.0.1", "missing port"),
    ("udpin:0.0.0.0", "missing port"),
    ("udpin:0.0.0.0:", "missing port"),
    ("tcp:localhost:http", "port 'http' is not a number"),
    ("tcp:localhost:-5", "port '-5' is not a number"),
    ("udpout:1.2.3.4:70000", "port 70000 out of range [1, 65535]"),
    ("udpout:1.2.3.4:0", "port 0 out of range [1, 65535]"),
    ("tcpin:0.0.0.0:65536", "port 65536 out of range [0, 65535]"),
    ("udpout::14550", "missing host"),
    ("tcp::5760", "missing host"),
    ("serial:/dev/ttyAMA0:921601", "baud rate 921601 is not a standard rate"),
    ("/dev/ttyACM0:fast", "baud rate 'fast' is not a positive integer"),
    ("serial:", "missing serial device"),
    ("serial:ttyS0:57600", "not an absolute path"),
    ("udpin:1:2:3", "too many ':'"),
    ("localhost", "no scheme"),
])
def test_bad_urls_name_the_url_and_the_problem(url, fragment):
    with pytest.raises(ValueError) as exc:
        parse_url(url)
    msg = str(exc.value)
    assert fragment in msg
    assert repr(url) in msg


def test_non_string_url():
    with pytest.raises(ValueError, match="must be a string"):
        parse_url(14550)


@pytest.mark.parametrize("url, role, kind, host, port, pym", [
    # pymavlink / MAVProxy: udp: and bare HOST:PORT listen for the FC (--master) and send for an output (--out)
    ("127.0.0.1:14550", "fc", "udpin", "127.0.0.1", 14550, "udpin:127.0.0.1:14550"),
    ("127.0.0.1:14550", "out", "udpout", "127.0.0.1", 14550, "udpout:127.0.0.1:14550"),
    ("udp:10.0.0.5:14555", "out", "udpout", "10.0.0.5", 14555, "udpout:10.0.0.5:14555"),
    ("localhost:14550", "fc", "udpin", "localhost", 14550, "udpin:localhost:14550"),
    ("[::1]:14550", "out", "udpout", "::1", 14550, "udpout:[::1]:14550"),
    ("udpin:0.0.0.0:14550", "out", "udpin", "0.0.0.0", 14550, "udpin:0.0.0.0:14550"),
    ("tcpout:127.0.0.1:5760", "fc", "tcp", "127.0.0.1", 5760, "tcp:127.0.0.1:5760"),
    # MAVSDK / QGC
    ("udp://:14540", "fc", "udpin", "0.0.0.0", 14540, "udpin:0.0.0.0:14540"),
    ("udp://127.0.0.1:14550", "fc", "udpin", "127.0.0.1", 14550, "udpin:127.0.0.1:14550"),
    ("udpin://0.0.0.0:14540", "fc", "udpin", "0.0.0.0", 14540, "udpin:0.0.0.0:14540"),
    ("udpout://192.168.1.20:14550", "out", "udpout", "192.168.1.20", 14550, "udpout:192.168.1.20:14550"),
    ("tcp://127.0.0.1:5760", "fc", "tcp", "127.0.0.1", 5760, "tcp:127.0.0.1:5760"),
    ("tcpout://127.0.0.1:5760/", "fc", "tcp", "127.0.0.1", 5760, "tcp:127.0.0.1:5760"),
    ("tcpin://:5761", "out", "tcpin", "0.0.0.0", 5761, "tcpin:0.0.0.0:5761"),
])
def test_forms_of_other_tools_by_role(url, role, kind, host, port, pym):
    ep = parse_url(url, role)
    assert (ep.kind, ep.host, ep.port, ep.pymavlink_url) == (kind, host, port, pym)


def test_mavsdk_serial_url():
    ep = parse_url("serial:///dev/ttyACM0:57600")
    assert (ep.kind, ep.device, ep.baud, ep.pymavlink_url) == ("serial", "/dev/ttyACM0", 57600, "/dev/ttyACM0,57600")


def test_mavsdk_udp_listen_refused_as_an_output_with_the_fix():
    """GIVEN MAVSDK's udp://HOST:PORT (it listens) as an output WHEN parsed THEN refused, naming udpout:HOST:PORT."""
    with pytest.raises(ValueError) as exc:
        parse_url("udp://127.0.0.1:14550", "out")
    assert "write udpout:127.0.0.1:14550" in str(exc.value)


def test_unknown_role():
    with pytest.raises(ValueError, match="role must be one of fc, out"):
        parse_url("udpin:0.0.0.0:14550", "gcs")


def test_host_that_does_not_resolve_is_an_error_naming_it(monkeypatch):
    """GIVEN udpin:notahost:14550 WHEN checked at start THEN one clear error naming the URL and the host."""
    def fail(*_a, **_k):
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")
    monkeypatch.setattr(socket, "getaddrinfo", fail)
    with pytest.raises(ValueError) as exc:
        check_resolvable(parse_url("udpin:notahost:14550"))
    assert str(exc.value) == ("bad MAVLink URL 'udpin:notahost:14550': host 'notahost' does not resolve "
                              "(Name or service not known): write an IP address or a name this machine resolves")


def test_addresses_and_serial_pass_the_resolution_check():
    check_resolvable(parse_url("udpin:127.0.0.1:14550"))
    check_resolvable(parse_url("udpout:[::1]:14550"))
    check_resolvable(parse_url("serial:/dev/does-not-exist:57600"))  # a USB device may appear later
