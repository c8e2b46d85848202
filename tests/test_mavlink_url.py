"""Connection URLs: the forms users write, and clear errors for the ones that are wrong."""
import pytest

from mavlink_io.url import parse_url


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
    ("udpbcast:1.2.3.4:14550", "unknown scheme 'udpbcast'"),
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
