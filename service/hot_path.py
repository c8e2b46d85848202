"""The Pipeline's per-IMU-sample hot path behind ``Pipeline.on_imu_batch`` (issue 19 items 1, 3).

``Pipeline.on_imu`` stays the reference for every sample. With the compiled core
(``AZIMUTHD_CORE=core``), ``on_imu_batch`` hands a batch's rows (mavlink_io/imu_batch IMU_RECORD, one
float64 block) to ``estimators._core.hot_run`` (core/hot_path.hpp), which takes every QUIET sample
in C++ and stops at the first one that needs Python; ``on_imu`` handles that one (with the input
checks' verdict the core already reached on it: a check runs once per sample), then the batch
goes on. A quiet sample is one that on_imu takes through these steps only, none deciding
anything: the input checks pass with no event, finite and increasing FC time, the phase stays
IN_FLIGHT (phase_step does nothing there), method A propagates it and may store its magnetometer
sample with neither a solve, nor a solver submit, nor a solver result due (its status cannot
change then), the Pipeline's strapdown integrates it (a gap is not quiet), the filter-rate
accumulators take it with no filter step due, and the output attitude is turned by it.

One state: the Pipeline's per-sample fields (``last_time_fc_s``, ``_last_rx_s``, ``_filter_due_s``,
``_acc_gyro``/``_acc_accel``/``_acc_n``/``_acc_mag``, ``_out``, ``_out_bias_body_rad_s``,
``_out_rx_s``/``_out_gyro_s``) are properties over ONE object, ``Pipeline._hs``: the core's
``_core.SampleState`` with the core, this module's :class:`SampleState` with the reference. The
strapdown and the input checks the core steps are the Pipeline's own held core objects
(HeldStrapdown, CoreImuInputChecks), stepped in place. Method A's state is an immutable
AzimuthState replaced per step (as ``azimuth_step`` does): a run takes it in as a core AzimuthRun
that the following runs go on with (``Pipeline._azimuth_held``) until Python reads or sets
``Pipeline.azimuth``, which takes the next AzimuthState back (a pure step over many samples); its
per-sample output is built when read (``Pipeline.azimuth_out``, estimators.azimuth.azimuth_output). ``counters.imu_samples`` gets the
run's count of samples. What decides whether a run may start (the phase, pending events, A's
phase, a solver result waiting) changes only on a sample Python handles, so it is judged before
each run.
"""
from __future__ import annotations

import math

import numpy as np

from estimators import core as _ec
from estimators.azimuth import MagRecord, azimuth_status
from estimators.output_propagation import output_step
from estimators.records import fast_replace
from estimators.strapdown import StrapdownState


class SampleState:
    """The Pipeline's per-sample fields, the reference's (the core's twin: _core.SampleState)."""
    __slots__ = ("last_time_fc_s", "last_rx_s", "filter_due_s", "acc_gyro", "acc_accel", "acc_n", "acc_mag",
                 "out", "out_bias_body_rad_s", "out_rx_s", "out_gyro_s")

    def __init__(self):
        self.last_time_fc_s: float | None = None
        self.last_rx_s: float | None = None
        self.filter_due_s = -math.inf
        self.acc_gyro, self.acc_accel, self.acc_n, self.acc_mag = np.zeros(3), np.zeros(3), 0, None
        self.out = None
        """estimators.output_propagation.OutputState: the last solution turned by the gyros since."""
        self.out_bias_body_rad_s = np.zeros(3)
        self.out_rx_s: float | None = None
        """The sample ``out`` was last turned to: its receive time and gyro (sensor axes)."""
        self.out_gyro_s: np.ndarray | None = None

    def accumulate(self, gyro_rad_s, accel_m_s2, mag_gauss, time_s: float, filter_period_s: float) -> bool:
        """The filters' accumulators take one sample; True when no filter step is due at time_s (its
        tolerance: timestamp jitter)."""
        self.acc_gyro += gyro_rad_s
        self.acc_accel += accel_m_s2
        self.acc_n += 1
        if mag_gauss is not None:
            self.acc_mag = mag_gauss
        return time_s < self.filter_due_s - 0.05 * filter_period_s

    def turn_output(self, time_s: float, gyro_body_rad_s, max_dt_s: float, time_rx_s: float, gyro_rad_s) -> None:
        """The output attitude turned by one sample between filter steps (estimators/output_propagation)."""
        if self.out is not None:
            self.out = output_step(self.out, time_s, gyro_body_rad_s, self.out_bias_body_rad_s, max_dt_s)
            self.out_rx_s, self.out_gyro_s = time_rx_s, gyro_rad_s

    def out_snapshot(self):
        """(q_nav_from_body, time_s, out_rx_s, out_gyro_s) of the output attitude as it is now (what
        Pipeline.propagated_solution reads), None without one: nothing here changes in place later."""
        o = self.out
        if o is None:
            return None
        return o.q_nav_from_body, o.time_s, self.out_rx_s, self.out_gyro_s


def sample_field(name: str, doc: str = "") -> property:
    """A Pipeline attribute that is ``Pipeline._hs.<name>``."""
    return property(lambda self: getattr(self._hs, name), lambda self, v: setattr(self._hs, name, v), doc=doc)


_INT16_SOURCES = ("RAW_IMU", "SCALED_IMU")   # service/input_checks.py's


def _rows(records: np.ndarray) -> np.ndarray:
    """IMU_RECORD rows as the (N, 12) float64 block they are (the last column: imu_id and padding)."""
    rec = np.ascontiguousarray(records)
    return rec.view(np.float64).reshape(len(rec), rec.dtype.itemsize // 8)


def _sample(records: np.ndarray, i: int, source: str):
    """Row i as the ImuSample ``ImuBatch.samples`` gives."""
    from mavlink_io.samples import ImuSample
    t_fc, t_rx, g, a, m, imu_id = records[i:i + 1].tolist()[0]
    return ImuSample(t_fc, t_rx, np.array(g), np.array(a), np.array(m) if m[0] == m[0] else None, source, imu_id)


def _azimuth_run(p):
    """Method A's part of a run from the Pipeline's state: the core's AzimuthRun (inactive when A is
    not stepped in flight), or None when A's next sample is not quiet. A run held since the last one
    (``Pipeline._azimuth_held``: A's state lives in the core while Python does not look at it) goes on."""
    held = p._azimuth_held
    if held is not None:
        ready = getattr(p.solver, "ready", None)
        if ready is None or ready():   # a solver result to apply: Python takes the sample
            return None, False
        return held, True
    if p.phase.started_in_flight or p._azimuth_off is not None or p.azimuth.phase == "prelaunch":
        return _ec.AzimuthRun(), False
    st = p.azimuth
    ready = getattr(p.solver, "ready", None)
    if ready is None or ready():   # a solver result to apply (or a solver that cannot say)
        return None, False
    if azimuth_status(st) != p._azimuth_status:   # its status changes on the next sample: an event
        return None, False
    if st.phase == "failed":       # stepped as the reference does: the same output, built when read
        return _ec.AzimuthRun(), True
    if st.phase != "flight" or (st.boost is not None and st.u_sf is None):   # the boost window: Python
        return None, False
    ap, sd = st.params, st.strapdown
    has = sd.time_s is not None and sd.gyro_prev_rad_s is not None
    return _ec.AzimuthRun(
        sd.q_ref_from_sensor, has, float(sd.time_s) if has else 0.0, sd.gyro_prev_rad_s if has else _ZERO3,
        st.G_gyro, st.C_isf_sf, st.gyro_bias_rad_s, ap.strapdown.max_dt_s, st.launch_time_s,
        ap.mag_skip_after_launch_s, ap.mag_decimation_s, ap.max_fit_samples, len(st.samples), st.last_mag_s,
        st.last_solve_s, ap.resolve_period_s if st.solution is not None else ap.resolve_period_unsolved_s,
        p._next_solve_s, True), True


_ZERO3 = np.zeros(3)


def azimuth_take_back(p) -> None:
    """Method A's state back from the core into ``Pipeline.azimuth`` (the AzimuthState of the held
    run's start, with the run's strapdown, G, C and stored samples): what reading or setting
    ``Pipeline.azimuth`` does first."""
    run, p._azimuth_held = p._azimuth_held, None
    _azimuth_back(p, run)


def _azimuth_back(p, run) -> None:
    """The AzimuthState after a run that stepped A: its strapdown, G, C and stored samples."""
    q, t_prev, g_prev, G, C, last_mag_s, rec = run.result()
    st = p._azimuth
    upd = {"strapdown": StrapdownState(q, t_prev, g_prev), "G_gyro": G, "C_isf_sf": C}
    if len(rec):
        upd["samples"] = st.samples + tuple(
            MagRecord(float(r[0]), r[1:4].copy(), r[4:13].reshape(3, 3).copy(), r[13:49].reshape(3, 12).copy())
            for r in rec)
        upd["last_mag_s"] = last_mag_s
    p._azimuth = fast_replace(st, **upd)


def hot_path_ready(p) -> bool:
    """The Pipeline runs the compiled core with a hot path (else on_imu_batch is a loop over on_imu)."""
    return getattr(p.core, "hot_run", None) is not None and not isinstance(p._hs, SampleState)


def batch_steps(p, batch, samples=None, rows=None, source: str | None = None):
    """Yields (row, on_imu's solution or None) for each row of ``batch`` Python handles, in order;
    the quiet rows between them are taken by the core and yield nothing (they give no solution and
    no event). ``samples``: the rows as ImuSample objects, when the caller has them (a replay).
    Without a batch: ``samples`` with their ``rows`` (float64, IMU_RECORD's first 11 columns) and
    their ``source`` (``sample_step``)."""
    from service.input_checks import _OK, CoreImuInputChecks
    from service.phases import IN_FLIGHT
    from estimators.core import HeldStrapdown
    if not hot_path_ready(p):   # the reference (or a core without the hot path): on_imu for every sample
        for i, s in enumerate(samples if samples is not None else batch.samples()):
            yield i, p.on_imu(s)
        return
    rec = batch.records if batch is not None else None
    n = len(rec) if rec is not None else len(samples)
    run = p.core.hot_run
    int16 = (batch.source if batch is not None else source) in _INT16_SOURCES
    i = 0
    on_imu = p.on_imu
    while i < n:
        verdict = None
        s = None
        if not (p.vehicle.pending or p._unseen_pending or p._fc_status_pending is not None) \
                and p.phase.phase == IN_FLIGHT \
                and not (p.phase.started_in_flight and p.polar_att_params.relevel_allowed) \
                and isinstance(p.input_checks, CoreImuInputChecks) \
                and (p.strapdown is None or isinstance(p.strapdown, HeldStrapdown)):
            arun, a_steps = _azimuth_run(p)
            if arun is not None:
                if rows is None:
                    rows = _rows(rec)
                sd = p.strapdown
                stop, code, checked, handled = run(
                    p._hs, p.input_checks._c, sd._c if sd is not None else None, arun, rows, i, p.gyro_bias_rad_s,
                    p.C_body_from_sensor, p.strapdown_params.max_dt_s, p.polar_att_params.max_dt_s,
                    p.filter_period_s, int16)
                if handled:
                    p.counters.imu_samples += handled
                    if a_steps:
                        if arun.active:   # A's state stays in the core until Python reads it
                            p._azimuth_held = arun
                            p._azimuth_out_due = (None, float(rows[stop - 1, 0]))
                        else:
                            p._azimuth_out_due = (p.azimuth, float(rows[stop - 1, 0]))
                i = stop
                if i >= n:
                    break
                if checked:
                    s = samples[i] if samples is not None else _sample(rec, i, batch.source)
                    verdict = _OK if code == 0 else p.input_checks._words(code, s)
        if s is None:
            s = samples[i] if samples is not None else _sample(rec, i, batch.source)
        yield i, (on_imu(s) if verdict is None else on_imu(s, verdict))
        i += 1


_NAN3 = (math.nan, math.nan, math.nan)


def sample_step(p, s):
    """``Pipeline.on_imu(s)`` for one sample as it comes from the link's message path, through the
    core's hot path when the sample is quiet (``batch_steps`` with one row: in flight, 7 of 8 samples
    at 400 Hz with the filters at 50 Hz), else on_imu itself: the same result, event and state."""
    from service.phases import IN_FLIGHT
    if p.phase.phase != IN_FLIGHT or not hot_path_ready(p):   # no run can start: on_imu
        return p.on_imu(s)
    m = s.mag_gauss
    try:
        row = np.array([[s.time_fc_s, s.time_rx_s, *s.gyro_rad_s, *s.accel_m_s2, *(m if m is not None else _NAN3)]],
                       dtype=np.float64)
    except (TypeError, ValueError):   # not 3 + 3 + 3 numbers: on_imu says what is wrong
        return p.on_imu(s)
    if row.shape != (1, 11):
        return p.on_imu(s)
    for _, sol in batch_steps(p, None, (s,), row, s.source):
        return sol
    return None


def batch_of(samples: list):
    """Consecutive ImuSample objects of one source as the ImuBatch of their rows (what a replay or a
    test hands ``on_imu_batch``; the link builds its batches from the wire: mavlink_io/imu_batch)."""
    from mavlink_io.imu_batch import IMU_RECORD, ImuBatch
    n = len(samples)
    rec = np.zeros(n, dtype=IMU_RECORD)
    f8 = rec.view(np.float64).reshape(n, IMU_RECORD.itemsize // 8)
    f8[:, 0] = [s.time_fc_s for s in samples]
    f8[:, 1] = [s.time_rx_s for s in samples]
    f8[:, 2:5] = [s.gyro_rad_s for s in samples]
    f8[:, 5:8] = [s.accel_m_s2 for s in samples]
    f8[:, 8:11] = [s.mag_gauss if s.mag_gauss is not None else _NAN3 for s in samples]
    rec["imu_id"] = [s.imu_id for s in samples]
    return ImuBatch(rec, samples[0].source)
