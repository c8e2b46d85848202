"""sd_notify: READY=1 / WATCHDOG=1 / STATUS reach a NOTIFY_SOCKET datagram socket we open."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import uuid

import pytest

from service import sdnotify


@pytest.fixture
def listener(tmp_path):
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(2.0)
    yield path, sock
    sock.close()


def test_ready_watchdog_status_to_path_socket(listener, monkeypatch):
    path, sock = listener
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    assert sdnotify.notify("READY=1")
    assert sock.recv(4096) == b"READY=1"
    assert sdnotify.notify("WATCHDOG=1")
    assert sock.recv(4096) == b"WATCHDOG=1"
    assert sdnotify.notify("STATUS=in-flight, heading 231.2 deg")
    assert sock.recv(4096) == b"STATUS=in-flight, heading 231.2 deg"


def test_abstract_socket_name():
    name = f"azimuthd-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"\0" + name.encode())
    sock.settimeout(2.0)
    try:
        n = sdnotify.Notifier.from_env({"NOTIFY_SOCKET": "@" + name})
        assert n.notify("READY=1")
        assert sock.recv(4096) == b"READY=1"
    finally:
        sock.close()


def test_from_a_child_process_like_systemd_runs_us(listener):
    """The daemon is a separate process: the env var is all it gets."""
    path, sock = listener
    env = dict(os.environ, NOTIFY_SOCKET=path, WATCHDOG_USEC="4000000")
    code = ("from service import sdnotify; n = sdnotify.Notifier.from_env(); "
            "assert n.watchdog_period_s == 2.0, n.watchdog_period_s; "
            "assert n.notify('READY=1'); assert n.watchdog_due(0.0) and n.notify('WATCHDOG=1')")
    subprocess.run([sys.executable, "-c", code], env=env, check=True, timeout=30)
    assert sock.recv(4096) == b"READY=1"
    assert sock.recv(4096) == b"WATCHDOG=1"


def test_noop_without_notify_socket(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert sdnotify.notify("READY=1") is False
    n = sdnotify.Notifier.from_env({})
    assert not n.enabled and n.watchdog_period_s is None and not n.watchdog_due(0.0)


def test_send_failure_is_counted_not_raised(tmp_path):
    n = sdnotify.Notifier(str(tmp_path / "nobody-listens.sock"))
    assert n.notify("WATCHDOG=1") is False
    assert n.errors == 1


def test_watchdog_interval_from_env():
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "10000000"}) == 5.0
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "0"}) is None
    assert sdnotify.watchdog_interval_s({"WATCHDOG_USEC": "junk"}) is None
    assert sdnotify.watchdog_interval_s({}) is None
    mine = {"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid())}
    assert sdnotify.watchdog_interval_s(mine) == 1.0
    other = {"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid() + 1)}
    assert sdnotify.watchdog_interval_s(other) is None


def test_watchdog_due_once_per_period():
    n = sdnotify.Notifier("/nonexistent", watchdog_period_s=2.0)
    assert n.watchdog_due(10.0)
    assert not n.watchdog_due(11.9)
    assert n.watchdog_due(12.0)
    assert not n.watchdog_due(13.0)
