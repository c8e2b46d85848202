"""The daemon builds the solution propagated to an IMU sample between filter steps only when it is
read (issue 19: no per-sample NavSolution on the hot path).

GIVEN the recorded stream of tests/test_mavlink_imu_batch_daemon.py (RAW_IMU at 200 Hz, ATTITUDE
out at 50 Hz: most samples reach no output slot; a launch, an FC reboot, bad frames), fed in memory
to daemons on the message path (one datagram per frame) and on the batch path,
WHEN the daemon keeps each sample's propagated solution as a snapshot (Pipeline.propagated_snapshot)
and builds it only for an output slot or a reader (Daemon.last_solution), read after every read of
the link or never,
THEN every MAVLink message it sends and every solution it reads are those of the daemon that builds
the propagated solution for every sample (the former code, Daemon and Pipeline, patched in here),
field for field; and a
snapshot built wrongly (its time off by 1 us) fails the same comparison.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from estimators.rotations import euler_from_quat, wrap_2pi
from mavlink_io.link import MavlinkLink
from mavlink_io.outputs import OutputScheduler
from mem_transport import MemTransport
from test_mavlink_imu_batch_daemon import SCENARIO, _reads, _record, _same_solution, scenario_site


def _former_propagated_solution(p):
    """Pipeline.propagated_solution as it was (dataclasses.replace), for the comparison."""
    o, sol = p._out, p._out_sol
    if o is None or sol is None:
        return None
    if o.time_s == sol.time_fc_s:
        return sol
    q = np.array(o.q_nav_from_body)
    roll, pitch, yaw = euler_from_quat(q)
    return dataclasses.replace(sol, time_fc_s=o.time_s, time_rx_s=p._out_rx_s, phase=p.phase.phase,
                               q_nav_from_body=q, roll_rad=roll, pitch_rad=pitch,
                               heading_rad=wrap_2pi(yaw) if sol.heading_rad is not None else None,
                               rates_body_rad_s=p.C_body_from_sensor @ (p._out_gyro_s - p.gyro_bias_rad_s))


def _eager(self, snap) -> None:
    """The former Daemon code: the propagated solution built for every sample."""
    self.last_solution = _former_propagated_solution(self.pipeline)
    self._last_solution_s = self.clock()
    self._publish_due(self._last_solution_s)


def _fields(msg) -> tuple:
    return (msg.get_type(),) + tuple(
        tuple(v) if isinstance(v, (list, tuple)) else v for v in (getattr(msg, f) for f in msg.get_fieldnames()))


def _run(tmp_path, name: str, reads, batch: bool, mode: str, monkeypatch) -> dict:
    from service.config import validate
    from service.daemon import Daemon
    over = {k: dict(v) for k, v in scenario_site(SCENARIO).items()}
    over.update({"zenoh": {"enabled": False}, "service": {"state_dir": str(tmp_path / name)},
                 "azimuth": {"solve_in_background": False}})
    clock = [0.0]
    with monkeypatch.context() as mp:
        if mode == "eager":
            mp.setattr(Daemon, "_propagated", _eager)
        d = Daemon(validate(over), clock=lambda: clock[0])
        if mode == "wrong":
            real = d.pipeline.solution_from_snapshot

            def wrong(snap):
                sol = real(snap)
                if sol is not None and type(snap) is not type(sol):   # a built snapshot, not the solution
                    sol = dataclasses.replace(sol, time_fc_s=sol.time_fc_s + 1e-6)
                return sol
            d.pipeline.solution_from_snapshot = wrong
        tr = MemTransport(datagram=True)
        d.link = MavlinkLink(dataclasses.replace(d.link_cfg, imu_batch=batch), clock=lambda: clock[0], transport=tr)
        d._event = lambda kind, detail: None
        sent, read = [], []
        send = d._send
        d._send = lambda msg, to_fc=False: (sent.append(_fields(msg)), send(msg, to_fc))
        for t, datagrams in reads:
            clock[0] = t
            for dg in (datagrams if not batch else [None]):
                tr.inbox.extend([dg] if dg is not None else datagrams)
                for item in d.link.poll(0.0):
                    d.dispatch(item)
            d._publish_due(t)
            if mode in ("eager", "read", "wrong"):
                read.append(d.last_solution)
        d.pipeline.solver.close()
    return {"sent": sent, "read": read}


def _same(a, b) -> bool:
    if a is None or b is None:
        return a is b
    return _same_solution(a, b)


def _same_sent(a: list, b: list) -> bool:
    def norm(v):
        return "nan" if isinstance(v, float) and math.isnan(v) else v
    return len(a) == len(b) and all(tuple(map(norm, x)) == tuple(map(norm, y)) for x, y in zip(a, b))


@pytest.fixture(scope="module")
def reads():
    return _reads(_record(), packed=False)


@pytest.mark.parametrize("batch", [False, True], ids=["message path", "batch path"])
def test_lazy_propagated_solution_sends_and_reads_what_the_eager_one_did(reads, tmp_path, monkeypatch, batch):
    eager = _run(tmp_path, "eager", reads, batch, "eager", monkeypatch)
    read = _run(tmp_path, "read", reads, batch, "read", monkeypatch)
    unread = _run(tmp_path, "unread", reads, batch, "unread", monkeypatch)
    n_att = sum(m[0] == "ATTITUDE" for m in eager["sent"])
    assert n_att > 100, n_att   # the flight sent its outputs
    assert _same_sent(read["sent"], eager["sent"])
    assert _same_sent(unread["sent"], eager["sent"])
    assert sum(s is not None for s in eager["read"]) > 100
    assert len(read["read"]) == len(eager["read"])
    assert all(_same(a, b) for a, b in zip(read["read"], eager["read"]))


def test_a_wrongly_built_snapshot_fails_the_comparison(reads, tmp_path, monkeypatch):
    eager = _run(tmp_path, "eager", reads, False, "eager", monkeypatch)
    wrong = _run(tmp_path, "wrong", reads, False, "wrong", monkeypatch)
    assert not (_same_sent(wrong["sent"], eager["sent"])
                and all(_same(a, b) for a, b in zip(wrong["read"], eager["read"])))


SPARSE_IMU_HZ = 80.0
"""RAW_IMU sparser than half an ATTITUDE slot (12.5 ms > 10 ms at 50 Hz): the slots between two samples
are filled on the local clock (OutputScheduler.fill), and with the filters at 50 Hz some samples are
propagated between filter steps and take no slot of their own: a fill then sends that snapshot."""
WAKE_S = 0.002


@pytest.fixture(scope="module")
def sparse_reads():
    """One read per frame at its time, and the loop waking every WAKE_S in between without input."""
    import test_mavlink_imu_batch_daemon as rec
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(rec.RATES_HZ, 27, SPARSE_IMU_HZ)
        mp.setattr(rec, "FLIGHT_S", 14.0)   # the bad frames sit at the 900th RAW_IMU
        frames = rec._record()
    reads, t_prev = [], 0.0
    for t, f in frames:
        while t_prev + WAKE_S < t:
            t_prev += WAKE_S
            reads.append((t_prev, []))
        reads.append((t, [f]))
        t_prev = t
    return reads


def test_a_slot_filled_between_sparse_samples_sends_what_the_eager_daemon_did(sparse_reads, tmp_path, monkeypatch):
    fills = []
    real_fill = OutputScheduler.fill
    monkeypatch.setattr(OutputScheduler, "fill",
                        lambda self, sol, now_s, late=False: fills.append(real_fill(self, sol, now_s, late)) or fills[-1])
    eager = _run(tmp_path, "eager", sparse_reads, False, "eager", monkeypatch)
    n_eager_fills = sum(1 for f in fills if f)
    fills.clear()
    unread = _run(tmp_path, "unread", sparse_reads, False, "unread", monkeypatch)
    assert n_eager_fills > 50, n_eager_fills    # slots were filled between samples
    assert sum(1 for f in fills if f) == n_eager_fills
    assert _same_sent(unread["sent"], eager["sent"])
