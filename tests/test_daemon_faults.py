"""A defect of ours in handling one input must not stop the daemon (DESIGN: the daemon keeps running,
logs why, and recovers). On 2026-12-02 a Pipeline step raised ValueError on the launcher (a turn speed
of 0 m/s from the air data) and the daemon died after 20 IMU messages, with a traceback for the user.
Now the input is dropped with an ``internal_fault`` error event that says what and where, counted;
FAULTS_BEFORE_REBUILD faults in a row rebuild the Pipeline, and the daemon flies on."""
from __future__ import annotations

from service.daemon import FAULTS_BEFORE_REBUILD
from test_fc_yaw_loop import daemon_on_sim


def _daemon(tmp_path):
    return daemon_on_sim(tmp_path, seed=3)


def _fly(ap, d, loop, until_s: float) -> int:
    """Feed the simulator's items to the daemon until ``until_s``; the solutions the daemon made."""
    made = 0
    while ap.t < until_s:
        loop.run(ap.t + 0.05)
        for it in loop.items:
            before = d.last_solution
            d.dispatch(it)   # never raises: the test fails on any exception escaping it
            made += d.last_solution is not before and d.last_solution is not None
        loop.items.clear()
        d._publish_due(ap.t)
    return made


class _Faulty:
    """Wraps the Pipeline's IMU entry the daemon calls (step_imu, the message path; on the ground
    it no longer reaches on_imu): raises on the samples whose FC time is in [t0, t1)."""

    def __init__(self, on_imu, t0: float, t1: float):
        self.on_imu, self.t0, self.t1, self.raised = on_imu, t0, t1, 0

    def __call__(self, sample):
        if self.t0 <= sample.time_fc_s < self.t1:
            self.raised += 1
            raise ValueError("manoeuvre_speed_m_s must be finite and > 0, got 0.0")
        return self.on_imu(sample)


def test_a_few_faulting_samples_are_dropped_logged_and_the_daemon_flies_on(tmp_path):
    # GIVEN a daemon whose Pipeline raises on three samples (3 IMU samples at 25 Hz from FC 2.0 s)
    ap, d, loop, events = _daemon(tmp_path)
    pipeline = d.pipeline
    faulty = _Faulty(pipeline.step_imu, 2.0, 2.11)
    pipeline.step_imu = faulty
    # WHEN it runs through them
    _fly(ap, d, loop, 2.5)
    assert faulty.raised >= 2
    # THEN each is one counted, logged internal fault saying what and where; the Pipeline is kept
    faults = [det for k, det in events if k == "internal_fault"]
    assert d.internal_faults == faulty.raised == len(faults)
    assert faults[0].startswith("ValueError: manoeuvre_speed_m_s must be finite and > 0, got 0.0 (at ")
    assert "test_daemon_faults.py:" in faults[0] and "input dropped, the daemon continues" in faults[0]
    assert d.pipeline is pipeline and d.pipeline_rebuilds == 0
    # AND the samples after them make solutions again
    assert _fly(ap, d, loop, 4.0) > 0
    assert d.internal_faults == faulty.raised and d.faults_in_row == {}
    d.pipeline.solver.close()


def test_faults_in_a_row_rebuild_the_pipeline_and_solutions_resume(tmp_path):
    # GIVEN a Pipeline that fails on every sample from FC 2 s on (a broken state)
    ap, d, loop, events = _daemon(tmp_path)
    broken = d.pipeline
    broken.step_imu = _Faulty(broken.step_imu, 2.0, 1e9)
    # WHEN FAULTS_BEFORE_REBUILD samples in a row fail (other inputs between them succeed)
    _fly(ap, d, loop, 2.0 + (FAULTS_BEFORE_REBUILD + 3) / 25.0)
    # THEN the daemon built a fresh Pipeline, said why, and it makes solutions from the next samples
    assert d.pipeline is not broken and d.pipeline_rebuilds == 1
    (why,) = [det for k, det in events if k == "pipeline_rebuilt"]
    assert f"{FAULTS_BEFORE_REBUILD} inputs in a row failed, the last with ValueError" in why
    assert _fly(ap, d, loop, ap.t + 1.5) > 0
    assert d.internal_faults == FAULTS_BEFORE_REBUILD
    d.pipeline.solver.close()
