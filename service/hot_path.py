"""The Pipeline's per-IMU-sample hot path behind ``Pipeline.on_imu_batch`` (issue 19 items 1, 3).

``Pipeline.on_imu`` stays the reference for every sample. With the compiled core
(``AZIMUTHD_CORE=core``), ``on_imu_batch`` hands a batch's rows (mavlink_io/imu_batch IMU_RECORD, one
float64 block) to ``estimators._core.hot_run`` (core/hot_path.hpp), which takes every QUIET sample
in C++ and stops at the first one that needs Python; ``on_imu`` handles that one (with the input
checks' verdict the core already reached on it: a check runs once per sample), then the batch
goes on. A quiet sample is one that on_imu takes through these steps only, none deciding
anything: the input checks pass with no event, finite and increasing FC time, the phase stays
IN_FLIGHT (phase_step does nothing there), method A propagates it and may store its magnetometer
sample with neither a solve, nor a solver submit (one the busy worker would refuse changes nothing:
``_submit_blocked``), nor a solver result due (its status cannot change then), the Pipeline's
strapdown integrates it (a gap is not quiet), the filter-rate accumulators take it with no filter
step due, and the output attitude is turned by it.

One state: the Pipeline's per-sample fields (``last_time_fc_s``, ``_last_rx_s``, ``_filter_due_s``,
``_acc_gyro``/``_acc_accel``/``_acc_n``/``_acc_mag``, ``_out``, ``_out_bias_body_rad_s``,
``_out_rx_s``/``_out_gyro_s``) are properties over ONE object, ``Pipeline._hs``: the core's
``_core.SampleState`` with the core, this module's :class:`SampleState` with the reference. The
strapdown and the input checks the core steps are the Pipeline's own held core objects
(HeldStrapdown, CoreImuInputChecks), stepped in place. Method A's state is an immutable
AzimuthState replaced per step (as ``azimuth_step`` does): a run takes it in as a core AzimuthRun
that the following runs go on with (``Pipeline._azimuth_held``) until Python reads or sets
``Pipeline.azimuth``, which takes the next AzimuthState back (a pure step over many samples); its
per-sample output is built when read (``Pipeline.azimuth_out``: ``azimuth_output_held``, its numbers from the
run's G and C in the core, core/azimuth_output.hpp, no take-back). The filter-step sample on_imu takes goes on
the held run too (``azimuth_held_step``: Pipeline._step_azimuth), so A's state comes back to Python only for a
solver submit, a solver result, a status change or a reader; the solver gets its samples as one array
(``SamplePack``, grown by the core's rows). ``counters.imu_samples`` gets the run's count of samples. What decides whether a run may start (the phase, pending events, A's
phase, a solver result waiting) changes only on a sample Python handles, so it is judged before
each run.

The ground (issue 19): before the take-off (phase PRE_LAUNCH) a quiet sample is one on which on_imu
passes the input checks with no event, steps the phases with no event and the phase staying
PRE_LAUNCH (every decision of theirs: a levelling, a take-off, the started-in-flight rule, a failed
still block, words an event), steps ``_step_azimuth``'s pre-launch branch (method A's delay line into
its levelling, method E's rest data: nothing decided), accumulates with no filter step due and turns
the output attitude; the core's ground run (core/hot_path.hpp ground_run) takes those. What it steps
lives in the core for the whole ground phase: the phases (HeldPhaseState), the Pipeline's
``GroundState`` (core/ground.hpp; this module's :class:`GroundState` with the reference): method E's
``rest`` and ``_rest_candidate`` (Pipeline properties over it), and method A's delay line and levelling
accumulator, taken in from the AzimuthState at the first ground step (``ground_take_in``) and given
back when Python reads ``Pipeline.azimuth`` (``ground_take_back``: at the take-off, and whatever else
reads it). ``on_imu`` steps the same object on the ground samples Python handles (``ground_step``).

The message path (``sample_step``, what ``Pipeline.step_imu`` and so the daemon call per RAW_IMU): the
Pipeline's bound hot path, ``_core.HotPath`` (core/bindings_hot_path.cpp), holds what stays fixed
(the per-sample state, the input checks, C_body_from_sensor, the two integration limits, the filter
period: bound at the first quiet sample, again when the input checks are replaced, and by a copy of
the Pipeline for itself); its ``flight``/``ground`` read the ImuSample's fields in C++ and run hot_run's
or ground_run's loop on that one row, with no row array and no generator built in Python (measured:
8.2-8.7 -> 3.7-4.1 us per quiet sample, the per-call minimum over 15 replays of a window, load 11).
A sample not in the link's form (not float64 (3,) arrays) is left unread and goes through a one-row
batch as before.
A backend whose hot_run is not the compiled one (a test's wrapper or mutant) gets every run through
that hot_run with every argument.
"""
from __future__ import annotations

import math

import numpy as np

from estimators import core as _ec
from estimators.azimuth import (REC_COLUMNS, PackedSamples, azimuth_output, azimuth_prelaunch_step, azimuth_status,
                                output_from_numbers, pack_samples, record_of)
from estimators.core import HeldStrapdown
from estimators.declination import RestState
from estimators.output_propagation import output_step
from estimators.records import fast_replace
from estimators.strapdown import StrapdownState
from service.input_checks import _OK, CoreImuInputChecks
from service.phases import IN_FLIGHT, PRE_LAUNCH
from service.phases_core import HeldPhaseState


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


class GroundState:
    """The Pipeline's ground state, the reference's (the core's twin: _core.GroundState, which also
    holds method A's pre-launch part while it is taken in): method E's rest data."""
    __slots__ = ("rest", "rest_candidate")

    def __init__(self):
        self.rest = RestState()
        """The rest data of consecutive still blocks (what method E uses at launch)."""
        self.rest_candidate = RestState()
        """... with the still block filling now."""


def ground_field(name: str, doc: str = "") -> property:
    """A Pipeline attribute that is ``Pipeline._ground.<name>``."""
    return property(lambda self: getattr(self._ground, name), lambda self, v: setattr(self._ground, name, v),
                    doc=doc)


def ground_take_in(p) -> None:
    """Method A's pre-launch part (its delay line and levelling accumulator) from ``Pipeline.azimuth``
    into the core's GroundState (A in phase "prelaunch")."""
    st = p._azimuth
    if st.phase != "prelaunch":   # the reference's error (azimuth_prelaunch_step in another phase)
        azimuth_prelaunch_step(st, _ZERO3, _ZERO3, 0.0)
    rows = np.array([(t, *g.tolist(), *a.tolist()) for t, g, a in st.pending], dtype=np.float64).reshape(-1, 7)
    p._ground.set_azimuth(rows, _ec.levelling_pack(st.levelling), st.params.prelaunch_buffer_s)
    p._ground_a = True


def ground_take_back(p) -> None:
    """Method A's pre-launch part back from the core into ``Pipeline.azimuth`` (what reading it does)."""
    rows, lev = p._ground.take_azimuth()
    p._ground_a = False
    pending = tuple((t, r[1:4].copy(), r[4:7].copy()) for t, r in zip(rows[:, 0].tolist(), rows))
    p._azimuth = fast_replace(p._azimuth, pending=pending, levelling=_ec.levelling_unpack(lev))


def ground_step(p, gyro_rad_s, accel_m_s2, mag_gauss, time_s: float) -> None:
    """``Pipeline._step_azimuth``'s pre-launch branch in the core (the phases stepped on the sample):
    A's delay line, E's rest data and the end of a still block (core/ground.hpp ground_step)."""
    if not p._ground_a:
        ground_take_in(p)
    ph = p.phase
    p._ground.step(gyro_rad_s, accel_m_s2, mag_gauss, time_s, ph.block_start_s == time_s, ph.block_passed_s == time_s)


def _tri(x) -> int:
    """A FlightEvidence tri-state as core/phases.hpp Evidence takes it (the reference asks ``is True``)."""
    return 1 if x is True else (0 if x is False else -1)


_AIR_MAX_AGE_S = None


def _evidence(p) -> tuple:
    """What ``Pipeline._flight_evidence`` builds from, for a ground run: (armed, fc_reports_flying,
    fc_landed, has_air, air_time_s, air_max_age_s, airspeed_m_s, alt_rate_m_s) with the airspeed and
    altitude rate the air data gives while fresh (NaN: none). Fixed over a batch: the FC's messages
    and the pressure samples come between batches."""
    global _AIR_MAX_AGE_S
    if _AIR_MAX_AGE_S is None:
        from service.pipeline import AIR_EVIDENCE_MAX_AGE_S
        _AIR_MAX_AGE_S = AIR_EVIDENCE_MAX_AGE_S
    air = p.ahrs.air_last
    head = (_tri(p.fc_armed), _tri(p.fc_reports_flying), _tri(p.fc_landed))
    if air is None:
        return (*head, False, 0.0, _AIR_MAX_AGE_S, math.nan, math.nan)
    has_pitot = p.pressure is not None and p.pressure.press_diff_pa is not None
    speed = air.tas_m_s if has_pitot and not air.pitot_noisy else None
    rate = air.alt_rate_m_s if air.rate_valid else None
    return (*head, True, float(air.time_s), _AIR_MAX_AGE_S, math.nan if speed is None else float(speed),
            math.nan if rate is None else float(rate))


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


def _azimuth_run(p, t_last: float = math.inf):
    """Method A's part of a run from the Pipeline's state: the core's AzimuthRun (inactive when A is
    not stepped in flight), or None when A's next sample is not quiet. A run held since the last one
    (``Pipeline._azimuth_held``: A's state lives in the core while Python does not look at it) goes on.
    ``t_last``: the FC time of the run's last sample (inf: not known)."""
    held = p._azimuth_held
    if held is not None:   # (per sample on the message path: _solver_has_result written out)
        ready = getattr(p.solver, "ready", None)
        if ready is None or ready():   # a solver result to apply: Python takes the sample
            return None, False
        if t_last >= p._next_solve_s:   # a submit may come due on these samples
            _submit_blocked(p, held)
        return held, True
    if p.phase.started_in_flight or p._azimuth_off is not None or p.azimuth.phase == "prelaunch":
        return _ec.AzimuthRun(), False
    st = p.azimuth
    if _solver_has_result(p):   # a solver result to apply (or a solver that cannot say)
        return None, False
    if azimuth_status(st) != p._azimuth_status:   # its status changes on the next sample: an event
        return None, False
    if st.phase == "failed":       # stepped as the reference does: the same output, built when read
        return _ec.AzimuthRun(), True
    if st.phase != "flight" or (st.boost is not None and st.u_sf is None):   # the boost window: Python
        return None, False
    ap, sd = st.params, st.strapdown
    has = sd.time_s is not None and sd.gyro_prev_rad_s is not None
    run = _ec.AzimuthRun(
        sd.q_ref_from_sensor, has, float(sd.time_s) if has else 0.0, sd.gyro_prev_rad_s if has else _ZERO3,
        st.G_gyro, st.C_isf_sf, st.gyro_bias_rad_s, ap.strapdown.max_dt_s, st.launch_time_s,
        ap.mag_skip_after_launch_s, ap.mag_decimation_s, ap.max_fit_samples, len(st.samples), st.last_mag_s,
        st.last_solve_s, ap.resolve_period_s if st.solution is not None else ap.resolve_period_unsolved_s,
        p._next_solve_s, True)
    if t_last >= p._next_solve_s:
        _submit_blocked(p, run)
    return run, True


def _solver_has_result(p) -> bool:
    """A solver result waits to be applied (or the solver cannot say): on_imu takes the sample (it
    polls the result). Asked before ``_submit_blocked``: a solve that ends between the two calls leaves
    busy False (Python takes the submit), never a result unapplied."""
    ready = getattr(p.solver, "ready", None)
    return ready is None or ready()


def _submit_blocked(p, run) -> None:
    """``run.submit_blocked``: a submit due on the run's samples would be refused, the worker solving
    (``busy``): the reference's submit then returns False and changes nothing, no schedule moved, so
    the core takes such a sample (else every sample of a solve's duration goes to on_imu; a slow
    worker on a busy machine sends them all there). Called when a submit may come due by the run's
    last sample (t >= Pipeline._next_solve_s): the core reads the flag only then (the run's
    next_solve_s is the Pipeline's, which moves only on a sample Python takes after taking A's state
    back)."""
    busy = getattr(p.solver, "busy", None)
    run.submit_blocked = busy is not None and busy()


_ZERO3 = np.zeros(3)


def azimuth_take_back(p) -> None:
    """Method A's state back from the core into ``Pipeline.azimuth`` (the AzimuthState of the held
    run's start, with the run's strapdown, G, C and stored samples): what reading or setting
    ``Pipeline.azimuth`` does first."""
    run, p._azimuth_held = p._azimuth_held, None
    _azimuth_back(p, run)


def _azimuth_back(p, run) -> None:
    """The AzimuthState after a run that stepped A: its strapdown, G, C and stored samples (their rows
    go on A's sample pack as the core packed them)."""
    q, t_prev, g_prev, G, C, last_mag_s, rec = run.result()
    st = p._azimuth
    upd = {"strapdown": StrapdownState(q, t_prev, g_prev), "G_gyro": G, "C_isf_sf": C}
    if len(rec):
        new = tuple(record_of(r) for r in rec)
        p._a_pack.extend(st.samples, rec, new)
        upd["samples"] = st.samples + new
        upd["last_mag_s"] = last_mag_s
    p._azimuth = fast_replace(st, **upd)


class SamplePack:
    """Method A's stored samples as rows (estimators.azimuth.REC_COLUMNS; what its re-solve and the
    solver's worker take: one array), kept beside ``Pipeline.azimuth``'s tuple of MagRecord and grown
    with it: by the core's rows of a held run, or by packing the records it has not seen (its last
    record's identity tells; another store is packed anew)."""
    __slots__ = ("rows", "n", "last")

    def __init__(self):
        self.rows = np.empty((0, REC_COLUMNS))
        self.n = 0
        self.last = None   # the MagRecord of row n - 1

    def _fits(self, samples) -> bool:
        n = self.n
        return n <= len(samples) and (n == 0 or samples[n - 1] is self.last)

    def _put(self, rows: np.ndarray, last) -> None:
        n, k = self.n, len(rows)
        if n + k > len(self.rows):
            grown = np.empty((max(2 * len(self.rows), n + k, 64), REC_COLUMNS))
            grown[:n] = self.rows[:n]
            self.rows = grown
        self.rows[n:n + k] = rows
        self.n, self.last = n + k, last

    def extend(self, samples, rows: np.ndarray, records: tuple) -> None:
        """``records`` (packed as ``rows``) appended to ``samples``."""
        if not self._fits(samples) or self.n != len(samples):
            self.n, self.last = 0, None
            self._put(pack_samples(samples), samples[-1] if samples else None)
        self._put(rows, records[-1])

    def of(self, samples) -> PackedSamples:
        """``samples`` (A's tuple of MagRecord) as PackedSamples over a copy of their rows."""
        if not self._fits(samples):
            self.n, self.last = 0, None
        if self.n < len(samples):
            self._put(pack_samples(samples[self.n:]), samples[-1])
        return PackedSamples(self.rows[:len(samples)].copy())


def azimuth_for_solver(p, st):
    """``st`` (Pipeline.azimuth) as the solver gets it: its samples as one packed array (PackedSamples)."""
    return fast_replace(st, samples=p._a_pack.of(st.samples))


def azimuth_held_step(p, gyro_rad_s, mag_gauss, time_s: float) -> bool:
    """``Pipeline._step_azimuth`` in flight on A's held run (its state stays in the core): the filter-step
    sample propagated and its magnetometer sample stored in C++ (AzimuthRun.step: hot_run's step of A),
    the output built when read (``azimuth_output_held``). False, nothing changed, when the reference takes
    the sample: a solver result to apply (or a solver that cannot say), a solve or a solver submit due on
    it (one the busy solver would refuse is not), a sample not integrated. Its status cannot change then: no
    event, as the reference."""
    if not _A_CORE or p.core.azimuth_output_numbers is not _ec.azimuth_output_numbers:
        return False
    if _solver_has_result(p):
        return False
    held = p._azimuth_held
    if time_s >= p._next_solve_s:
        _submit_blocked(p, held)
    if not held.step(time_s, gyro_rad_s, mag_gauss):
        return False
    p._azimuth_out_due = (None, float(time_s))
    return True


def azimuth_output_held(p, time_s: float):
    """``Pipeline.azimuth_out`` at the held run's last sample ``time_s`` without taking A's state back:
    the numbers from the run's G and C in the core (core/azimuth_output.hpp), the rest from the
    AzimuthState the run started from (it changes only by a take-back). A backend whose output numbers
    are not the core's: the state taken back and the reference's output."""
    run = p._azimuth_held
    if not _A_CORE or p.core.azimuth_output_numbers is not _ec.azimuth_output_numbers:
        return azimuth_output(p.azimuth, time_s, p.core.azimuth_output_numbers)
    st = p._azimuth
    if not run.output_set:   # fixed for the run: set at its first read
        run.set_output(_ec.azimuth_output_cfg(st))
    return output_from_numbers(st, time_s, run.n_samples, run.output(time_s))


_A_CORE = getattr(_ec, "AZIMUTH_OUTPUT_AVAILABLE", False)


def hot_path_ready(p) -> bool:
    """The Pipeline runs the compiled core with a hot path (else on_imu_batch is a loop over on_imu)."""
    return getattr(p.core, "hot_run", None) is not None and not isinstance(p._hs, SampleState)


def batch_steps(p, batch, samples=None, rows=None, source: str | None = None):
    """Yields (row, on_imu's solution or None) for each row of ``batch`` Python handles, in order;
    the quiet rows between them are taken by the core and yield nothing (they give no solution and
    no event). ``samples``: the rows as ImuSample objects, when the caller has them (a replay).
    Without a batch: ``samples`` with their ``rows`` (float64, IMU_RECORD's first 11 columns) and
    their ``source`` (``sample_step``)."""
    if not hot_path_ready(p):   # the reference (or a core without the hot path): on_imu for every sample
        for i, s in enumerate(samples if samples is not None else batch.samples()):
            yield i, p.on_imu(s)
        return
    rec = batch.records if batch is not None else None
    n = len(rec) if rec is not None else len(samples)
    run = p.core.hot_run
    hot = _bound(p)   # the Pipeline's bound hot path (False: a backend's own hot_run, called with every argument)
    int16 = (batch.source if batch is not None else source) in _INT16_SOURCES
    i = 0
    on_imu = p.on_imu
    while i < n:
        verdict = None
        s = None
        phase = p.phase.phase
        if not (p.vehicle.pending or p._unseen_pending or p._fc_status_pending is not None) \
                and phase == IN_FLIGHT \
                and not (p.phase.started_in_flight and p.polar_att_params.relevel_allowed) \
                and isinstance(p.input_checks, CoreImuInputChecks) \
                and (p.strapdown is None or isinstance(p.strapdown, HeldStrapdown)):
            arun, a_steps = _azimuth_run(p)
            if arun is not None:
                if rows is None:
                    rows = _rows(rec)
                sd = p.strapdown
                if hot:
                    stop, code, checked, handled = hot.run(rows, i, sd._c if sd is not None else None, arun,
                                                           p.gyro_bias_rad_s, int16)
                else:
                    stop, code, checked, handled = run(
                        p._hs, p.input_checks._c, sd._c if sd is not None else None, arun, rows, i,
                        p.gyro_bias_rad_s, p.C_body_from_sensor, p.strapdown_params.max_dt_s,
                        p.polar_att_params.max_dt_s, p.filter_period_s, int16)
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
        elif phase == PRE_LAUNCH and p._ground_core \
                and not (p.vehicle.pending or p._unseen_pending or p._fc_status_pending is not None) \
                and type(p.phase) is HeldPhaseState and not p.phase.started_in_flight \
                and isinstance(p.input_checks, CoreImuInputChecks) \
                and (p._azimuth_off is not None or p._ground_a or p._azimuth.phase == "prelaunch"):
            # the ground run: _step_azimuth steps A's delay line and the rest data unless A is off
            ground = None
            if p._azimuth_off is None:
                if not p._ground_a:
                    ground_take_in(p)
                ground = p._ground
            if rows is None:
                rows = _rows(rec)
            if hot:
                stop, code, checked, handled = hot.run_ground(rows, i, p.phase._c, p.phase._p(p.phase_params), ground,
                                                              _evidence(p), p.gyro_bias_rad_s, int16)
            else:
                stop, code, checked, handled = run(
                    p._hs, p.input_checks._c, None, _idle_run(), rows, i, p.gyro_bias_rad_s, p.C_body_from_sensor,
                    p.strapdown_params.max_dt_s, p.polar_att_params.max_dt_s, p.filter_period_s, int16,
                    p.phase._c, p.phase._p(p.phase_params), ground, _evidence(p))
            if handled:
                p.counters.imu_samples += handled
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


_IDLE = []


def _idle_run():
    """An AzimuthRun that steps nothing (the ground run does not use it)."""
    if not _IDLE:
        _IDLE.append(_ec.AzimuthRun())
    return _IDLE[0]


class _Bound:
    """Holds a Pipeline's bound hot path (estimators._core.HotPath; False: its backend's hot_run is not
    the compiled one, a test's wrapper, called with every argument) and the input checks it was bound
    to. A copy of the Pipeline (copy.deepcopy, pickle) binds its own again."""
    __slots__ = ("hot", "checks", "core")

    def __init__(self):
        self.hot, self.checks, self.core = None, None, None

    def __deepcopy__(self, memo):
        return _Bound()

    def __reduce__(self):
        return _Bound, ()


def _bound(p):
    """The Pipeline's bound hot path (``_core.HotPath``: the per-sample state, the input checks,
    C_body_from_sensor, the two integration limits and the filter period, bound at the first run:
    the Pipeline's fixed config), or False when its backend's hot_run is another (a test's wrapper or
    mutant: every run calls it with every argument). Bound again when the input checks were replaced."""
    b = p._hot_bound
    if b is not None and b.checks is p.input_checks and b.core is p.core:
        return b.hot
    if b is None:
        b = p._hot_bound = _Bound()
    b.checks, b.core = p.input_checks, p.core
    b.hot = False
    if _HOT_PATH is not None and p.core.hot_run is _HOT_RUN and isinstance(p.input_checks, CoreImuInputChecks):
        b.hot = _HOT_PATH(p._hs, p.input_checks._c, p.C_body_from_sensor, p.strapdown_params.max_dt_s,
                          p.polar_att_params.max_dt_s, p.filter_period_s)
    return b.hot


_HOT_RUN = getattr(_ec, "hot_run", None)
_HOT_PATH = getattr(_ec, "HotPath", None)
_QUIET = getattr(_ec, "HOT_QUIET", -1)
_UNREAD = getattr(_ec, "HOT_UNREAD", -2)
_NAN3 = (math.nan, math.nan, math.nan)


def sample_step(p, s):
    """``Pipeline.on_imu(s)`` for one sample as it comes from the link's message path: a quiet sample
    (in flight and on the ground, 7 of 8 samples at 400 Hz with the filters at 50 Hz) taken by the
    core's bound hot path (``_core.HotPath.flight`` / ``.ground``: hot_run on the sample's row, read
    from the ImuSample in C++), else on_imu itself, with the input checks' verdict when they ran: the
    same result, events and state. The conditions are batch_steps' (judged per sample)."""
    b = p._hot_bound   # the bound hot path while the backend and input checks it was bound to stay
    if b is not None and b.hot and b.checks is p.input_checks and b.core is p.core:
        hot = b.hot
    else:
        if not hot_path_ready(p):
            return p.on_imu(s)
        hot = _bound(p)
        if not hot:   # a backend's own hot_run: a batch of one row through batch_steps
            return _sample_step_rows(p, s)
    # the vehicle type, an FC estimator status or samples unseen, pending: on_imu words them
    if p.vehicle.pending or p._unseen_pending or p._fc_status_pending is not None:
        return p.on_imu(s)
    ph = p.phase
    phase = ph.phase
    if phase == IN_FLIGHT:
        if ph.started_in_flight and p.polar_att_params.relevel_allowed:   # on_imu turns C's re-levelling off
            return p.on_imu(s)
        sd = p.strapdown
        if sd is not None:
            if not isinstance(sd, HeldStrapdown):   # a strapdown the core does not hold
                return p.on_imu(s)
            sd = sd._c
        t = s.time_fc_s
        arun, a_steps = _azimuth_run(p, t if type(t) is float else math.inf)
        if arun is None:   # A's next sample is not quiet (a solver result, its status, its boost window)
            return p.on_imu(s)
        code = hot.flight(s, sd, arun, p.gyro_bias_rad_s)
        if code == _QUIET:
            p.counters.imu_samples += 1
            if a_steps:
                if arun.active:   # A's state stays in the core until Python reads it
                    p._azimuth_held = arun
                    p._azimuth_out_due = (None, float(t))
                else:
                    p._azimuth_out_due = (p.azimuth, float(t))
            return None
    elif phase == PRE_LAUNCH and p._ground_core and type(ph) is HeldPhaseState and not ph.started_in_flight \
            and (p._azimuth_off is not None or p._ground_a or p._azimuth.phase == "prelaunch"):
        ground = None   # _step_azimuth steps A's delay line and the rest data unless A is off
        if p._azimuth_off is None:
            if not p._ground_a:
                ground_take_in(p)
            ground = p._ground
        code = hot.ground(s, ph._c, ph._p(p.phase_params), ground, _evidence(p), p.gyro_bias_rad_s)
        if code == _QUIET:
            p.counters.imu_samples += 1
            return None
    else:
        return p.on_imu(s)
    if code == _UNREAD:   # not in the link's form (unchecked): its row built here, as before
        return _sample_step_rows(p, s)
    return p.on_imu(s, _OK if code == 0 else p.input_checks._words(code, s))


def _sample_step_rows(p, s):
    """``sample_step`` through batch_steps with the sample as a batch of one row (numpy converts what
    it can: lists, float32): a backend's own hot_run, or a sample not in the link's form."""
    ph = p.phase.phase
    if not (ph == IN_FLIGHT or (ph == PRE_LAUNCH and p._ground_core)):   # no run: on_imu
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


def batches_of(items, max_rows: int | None = None) -> list:
    """``items`` with each run of consecutive ImuSample (at most ``max_rows`` each) as one ImuBatch
    (``batch_of``), the other items kept in place: the sequence a reader of a single-source IMU
    stream hands the Pipeline (what the benches feed ``on_imu_batch``)."""
    from mavlink_io.samples import ImuSample
    plan, run = [], []
    for it in items:
        if type(it) is ImuSample:
            run.append(it)
            if max_rows is not None and len(run) >= max_rows:
                plan.append(batch_of(run))
                run = []
            continue
        if run:
            plan.append(batch_of(run))
            run = []
        plan.append(it)
    if run:
        plan.append(batch_of(run))
    return plan


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
