"""The daemon runs unprivileged, as the systemd unit runs it (issue 10, Security).

systemd itself is not PID 1 on the test machine, so this reproduces what the unit gives the
daemon (systemd/azimuthd.service): a user that is not root and owns nothing else (here
``nobody``, standing in for the DynamicUser), no capabilities, no_new_privs, a private state
directory it owns (StateDirectory=, mode 0700), and the signing key presented the way
LoadCredential= presents it ($CREDENTIALS_DIRECTORY/<name>, owned by the service user, mode 0400).

GIVEN that setup and this test as the flight controller
THEN the daemon starts without the running-as-root warning, links up, signs what it sends,
writes its state (signing timestamp, calibration) into the state directory as that user, and
stops cleanly on SIGTERM; the process had no capabilities at all (read from /proc/<pid>/status).
The unit's own sandbox score is checked by tests/test_systemd_unit.py (systemd-analyze security).
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from test_security_signing_e2e import (KEY, ROOT, FakeFc, _wait_started, daemon_config, free_udp_port,  # noqa: E402
                                       independent_signature_ok, leaks)
from conftest import HANG_S  # noqa: E402

NOBODY = 65534

pytestmark = pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None,
                                reason="needs root (to drop to another user) and setpriv")


def _caps(pid: int) -> dict[str, int]:
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("Cap"):
            k, v = line.split(":")
            out[k] = int(v.strip(), 16)
        if line.startswith(("Uid:", "NoNewPrivs:")):
            k, v = line.split(":", 1)
            out[k] = v.split()
    return out


def test_daemon_runs_as_an_unprivileged_user_with_no_capabilities():
    top = Path(tempfile.mkdtemp(prefix="azimuthd-unpriv-"))
    try:
        os.chmod(top, 0o755)
        state = top / "state"
        state.mkdir(mode=0o700)
        os.chown(state, NOBODY, NOBODY)
        creds = top / "credentials"
        creds.mkdir(mode=0o500)
        key = creds / "mavlink_signing.key"
        key.write_text(KEY.hex())
        os.chmod(key, 0o400)
        os.chown(key, NOBODY, NOBODY)
        os.chown(creds, NOBODY, NOBODY)
        port = free_udp_port()
        cfg = daemon_config(top, port, {"signing_key_file": "${CREDENTIALS_DIRECTORY}/mavlink_signing.key"},
                            log_level="debug")
        # the state directory is where the unit's StateDirectory= would be, owned by the user
        assert (top / "state") == state
        os.chmod(cfg, 0o644)
        log = top / "daemon.log"
        env = dict(os.environ, CREDENTIALS_DIRECTORY=str(creds), PYTHONUNBUFFERED="1", HOME=str(state))
        with open(log, "wb") as out:
            p = subprocess.Popen(["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", "--clear-groups",
                                  "--no-new-privs", "--inh-caps=-all", "--bounding-set=-all",
                                  sys.executable, "-m", "service.cli", "run", "--config", str(cfg)],
                                 cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
        try:
            _wait_started(p, log)  # for as long as it works: its imports take > 60 s at load 20
            caps = _caps(p.pid)
            fc = FakeFc(port)
            # its signed frames once it has the FC (waited for while it works, not for a fixed time)
            msgs = fc.pump_until(lambda f: b"flight controller link up" in log.read_bytes()
                                 and any(m.get_srcComponent() == 191 for m in f), p, "no link up and no frame")
            p.send_signal(signal.SIGTERM)
            rc = p.wait(HANG_S)
        finally:
            if p.poll() is None:
                p.kill()
        text = log.read_bytes()
        assert rc == 0, text.decode()[-2000:]
        assert caps["Uid"] == [str(NOBODY)] * 4
        assert caps["CapEff"] == caps["CapPrm"] == caps["CapBnd"] == caps["CapAmb"] == 0
        assert caps["NoNewPrivs"] == ["1"]
        assert b"running as root" not in text
        assert b"flight controller link up" in text and b"mavlink signing on" in text
        ours = [m for m in msgs if m.get_srcComponent() == 191]
        assert ours and all(independent_signature_ok(bytes(m.get_msgbuf()), KEY)[0] for m in ours)
        written = {f.name: f.stat() for f in state.iterdir()}
        assert "signing.json" in written
        assert all(st.st_uid == NOBODY for st in written.values())
        assert leaks(text) == []
    finally:
        shutil.rmtree(top, ignore_errors=True)
