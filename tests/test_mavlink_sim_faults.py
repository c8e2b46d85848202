"""The link against the bundled simulator in its own process, with the simulator's link faults
switched on: dropped, corrupted, duplicated, reordered packets, NaN fields, an FC reboot and a
link outage. GIVEN that WHEN the link runs THEN nothing raises, every fault is counted, the reboot
and the outage are reported and followed by new rate requests, and the IMU time never goes back."""
from __future__ import annotations

import math
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from mavlink_io.link import LinkConfig, LinkEvent, MavlinkLink
from mavlink_io.samples import FcAttitude, ImuSample, PressureSample

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SPEED = 2.0
SIM_S = 18.0
HANG_S = 300.0
# sim seconds (wall = sim / SPEED): reboot at 6 (2 s of silence, streams back to defaults, the
# link finds them silent and asks again), outage 12..16 (2 s wall > link_timeout_s 1 s)
FAULTS = ["faults.drop_rate=0.02", "faults.corrupt_rate=0.02", "faults.duplicate_rate=0.01",
          "faults.reorder_rate=0.02", "faults.nan_rate=0.01", "faults.reboot_at_s=6.0",
          "faults.outages=[[12.0, 16.0]]"]


@pytest.fixture(scope="module")
def run():
    link = MavlinkLink(LinkConfig(url="udpin:127.0.0.1:0", link_timeout_s=1.0, reboot_jump_s=0.5))
    args = [sys.executable, "-m", "sim", "--scenario", "inclined_rail", "--seed", "5",
            "--mavlink", f"udpout:127.0.0.1:{link.local_address[1]}", "--speed", str(SPEED),
            "--duration", str(SIM_S)]
    for f in FAULTS:
        args += ["--set", f]
    proc = subprocess.Popen(args, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    items = []
    try:
        # until the simulator has flown its SIM_S (a busy machine runs it slower than SPEED: its
        # progress, not a fixed window, ends the read); HANG_S only catches a hung simulator
        t_end = time.monotonic() + HANG_S
        while time.monotonic() < t_end and proc.poll() is None:
            items += link.poll(0.01)
        items += link.poll(0.05)
        assert proc.poll() is not None, f"the simulator did not finish {SIM_S} s within {HANG_S} s"
        assert proc.wait(timeout=10) == 0, proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
        link.close()
    return items, link


def _events(items, kind):
    return [i for i in items if isinstance(i, LinkEvent) and i.kind == kind]


def test_faults_are_counted_not_raised(run):
    items, link = run
    s = link.stats
    assert link.fc_autopilot == "ardupilot"
    assert s.crc_errors > 0 and s.seq_lost > 0 and s.stale_time_drops > 0
    assert sum(s.non_finite_rejects.values()) > 0 and s.parser_errors == 0
    imu = [i for i in items if isinstance(i, ImuSample)]
    assert len(imu) > 0.5 * 200 * (SIM_S - 4.0 - 4.0)  # minus outage, reboot silence and re-request
    for x in imu:
        assert np.all(np.isfinite(x.gyro_rad_s)) and np.all(np.isfinite(x.accel_m_s2))
    for x in [i for i in items if isinstance(i, (FcAttitude, PressureSample))]:
        assert math.isfinite(x.time_fc_s)


def test_reboot_and_outage_reported_and_rates_rerequested(run):
    items, _ = run
    assert len(_events(items, "fc_reboot")) == 1
    assert len(_events(items, "link_lost")) >= 1 and len(_events(items, "link_restored")) >= 1
    reasons = [e.detail for e in _events(items, "rates_requested")]
    assert any("FC rebooted" in r or "silent" in r for r in reasons)
    assert any(r.startswith("link restored") for r in reasons)
    assert len(_events(items, "rates_acked")) >= 2


def test_time_never_goes_back(run):
    items, _ = run
    for cls in (ImuSample, PressureSample, FcAttitude):
        t = np.array([i.time_fc_s for i in items if isinstance(i, cls)])
        assert np.all(np.diff(t) > 0), cls.__name__
