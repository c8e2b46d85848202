"""IMU input checks at the Pipeline's edge: bad values are detected, counted, reported once, and
kept away from the estimators (issue 10).

One ``ImuInputChecks`` per Pipeline; ``check(sample)`` is called first in ``Pipeline.on_imu`` and
returns a ``Verdict``:

- ``reject``: the reason the sample must not reach the estimators (None = use it);
- ``reset``: see ``time_reset`` below;
- ``events``: ``(kind, detail)`` pairs for the events topic and the log. Each kind is reported
  at its first occurrence and then at most once per ``report_interval_s`` (receive time) with
  the count since the last report: a NaN at 400 Hz is one line, not a flood.

The kinds (``counts`` keeps how many samples each hit, for the ``health`` topic):

``non_finite``      NaN/inf in gyro, accel or the time: rejected.
``time_backwards``  FC time not after the last used sample: rejected. When the time stays more
                    than ``reset_jump_s`` behind for ``reset_after_samples`` consecutive samples
                    that advance among themselves, the clock restarted: reported once as
                    ``time_reset`` and still rejected; when the new clock passes the old one the
                    first sample comes with ``reset`` (the Pipeline restarts its integration, as
                    after an FC reboot: the interval between was never seen). (In the daemon
                    this does not happen: the link's timebase maps an FC reboot onto a time that
                    continues and the Pipeline gets ``on_fc_reboot``. Re-timing here would leave
                    the pressure and FC-attitude streams on the old clock, so a log replayed
                    across a reboot without that mapping loses the samples until then.)
``out_of_range``    |gyro| > ``gyro_max_rad_s`` or |accel| > ``accel_max_m_s2`` on an axis: beyond
                    the range of any IMU we support (2000 deg/s, 40 g): rejected.
``saturated``       an axis at the int16 limit of RAW_IMU / SCALED_IMU (32767 mrad/s or mG), or an
                    axis above ``clip_gyro_rad_s`` / ``clip_accel_m_s2`` that repeats bit for bit
                    for ``clip_repeats`` samples on that axis (a sensor clipped at its range): rejected while it
                    lasts; the strapdown sees a gap and does not integrate across it.
``frozen``          all six gyro/accel values bit-identical for ``frozen_s`` and at least
                    ``frozen_min_samples`` samples, after a live sensor (values changing on nearly
                    every sample, ``frozen_live_fraction``): a stuck driver resending its last
                    sample; real noise at the RAW_IMU quantum makes the run impossible. Rejected
                    until a value changes (``frozen_end``).
``gap``             FC time advanced by more than ``gap_s`` since the last good sample: reported
                    (the sample is used; the strapdown and the filters refuse to integrate over a
                    step longer than their ``max_dt_s`` and restart from it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mavlink_io.samples import ImuSample

G0_M_S2 = 9.80665
INT16_MAX = 32767
RAW_GYRO_LIMIT_RAD_S = INT16_MAX * 1e-3
"""RAW_IMU / SCALED_IMU carry mrad/s in an int16."""
RAW_ACCEL_LIMIT_M_S2 = INT16_MAX * 1e-3 * G0_M_S2
"""RAW_IMU / SCALED_IMU carry mG in an int16."""
_INT16_SOURCES = ("RAW_IMU", "SCALED_IMU")
LIVE_ALPHA = 0.02
"""EWMA weight of one sample in the "values change from sample to sample" fraction."""

KINDS = ("non_finite", "time_backwards", "time_reset", "out_of_range", "saturated", "frozen", "gap")


@dataclass(frozen=True)
class InputCheckParams:
    gyro_max_rad_s: float = math.radians(2000.0) * 1.05
    """Above this on any axis: not a rate any supported IMU measures (rad/s)."""
    accel_max_m_s2: float = 40.0 * G0_M_S2 * 1.05
    """Above this on any axis: not a specific force any supported IMU measures (m/s^2)."""
    clip_gyro_rad_s: float = math.radians(900.0)
    """An axis above this that repeats exactly ``clip_repeats`` times is clipped (rad/s)."""
    clip_accel_m_s2: float = 8.0 * G0_M_S2
    """An axis above this that repeats exactly ``clip_repeats`` times is clipped (m/s^2)."""
    clip_repeats: int = 20
    """Consecutive bit-identical values on one large axis that mean clipped (with RAW_IMU's 1 mrad/s
    / 1 mG quantum and real noise, 20 equal values in a row do not happen by chance)."""
    frozen_s: float = 0.5
    """All six gyro/accel values identical for this long (FC time, s) = frozen sensor."""
    frozen_min_samples: int = 20
    frozen_live_fraction: float = 0.8
    """Only a sensor that was alive is frozen: before the run, at least this fraction of its samples
    (EWMA over ~50 samples) differed from the one before (real noise: nearly all; noise-free
    synthetic data or a piecewise-constant test signal: few, and it is never called frozen)."""
    gap_s: float = 0.5
    """A step in FC time above this is a gap (the daemon passes ``mavlink.imu_gap_s``), s."""
    reset_jump_s: float = 1.0
    """Time back by more than this, consistently, = the FC clock restarted (s)."""
    reset_after_samples: int = 10
    report_interval_s: float = 60.0
    """A kind is reported at most this often (receive time, s), with the count in between."""

    def __post_init__(self) -> None:
        for name in ("gyro_max_rad_s", "accel_max_m_s2", "clip_gyro_rad_s", "clip_accel_m_s2", "frozen_s",
                     "gap_s", "reset_jump_s", "report_interval_s"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"InputCheckParams.{name} must be a finite number > 0, got {v!r}")
        if not isinstance(self.frozen_live_fraction, (int, float)) or not 0.0 < self.frozen_live_fraction <= 1.0:
            raise ValueError("InputCheckParams.frozen_live_fraction must be in (0, 1], "
                             f"got {self.frozen_live_fraction!r}")
        for name in ("clip_repeats", "frozen_min_samples", "reset_after_samples"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"InputCheckParams.{name} must be an integer >= 1, got {v!r}")


@dataclass(frozen=True, slots=True)
class Verdict:
    reject: str | None = None
    events: tuple = ()
    reset: bool = False
    """The samples resume after a restarted clock: the Pipeline restarts its integration
    (``on_fc_reboot``) instead of integrating across the unseen interval."""


_OK = Verdict()


@dataclass
class ImuInputChecks:
    """The state of the checks for one IMU stream; ``check(sample) -> Verdict`` per sample, in
    FC-time order as received. ``counts``: samples per kind (KINDS), for the health topic."""
    params: InputCheckParams = field(default_factory=InputCheckParams)
    counts: dict = field(default_factory=lambda: {k: 0 for k in KINDS})
    _last_t: float | None = None
    _behind_n: int = 0
    _behind_last_t: float | None = None
    _restarted: bool = False
    _prev: tuple | None = None
    _same_n: int = 0
    _same_since_t: float | None = None
    _frozen: bool = False
    _live: float = 0.0
    _live_at_run: float = 0.0
    _clip_prev: np.ndarray | None = None
    _clip_n: int = 0
    _clip_run: np.ndarray = field(default_factory=lambda: np.zeros(6, int))
    _reported_s: dict = field(default_factory=dict)
    _unreported: dict = field(default_factory=dict)

    def check(self, s: ImuSample) -> Verdict:
        p = self.params
        g, a, t = s.gyro_rad_s, s.accel_m_s2, s.time_fc_s
        events: list = []
        if not (math.isfinite(t) and np.all(np.isfinite(g)) and np.all(np.isfinite(a))):
            return self._bad("non_finite", "non-finite IMU sample", "NaN or inf in gyro, accel or time", s, events)

        if self._last_t is not None and t <= self._last_t:
            behind = self._last_t - t
            if behind > p.reset_jump_s and (self._behind_last_t is None or t > self._behind_last_t):
                self._behind_n += 1
                self._behind_last_t = t
            else:
                self._behind_n, self._behind_last_t = 0, None
            if self._behind_n == p.reset_after_samples:
                self._restarted = True
                self.counts["time_reset"] += 1
                self._report("time_reset", f"FC clock restarted without a reboot event ({self._last_t:.3f} s -> "
                                           f"{t:.3f} s for {self._behind_n} samples): its samples are rejected "
                                           "until their time passes the last used one", s, events)
            return self._bad("time_backwards", "IMU time not increasing",
                             f"FC time {t:.6f} s not after the last sample's {self._last_t:.6f} s", s, events)
        self._behind_n, self._behind_last_t = 0, None
        if self._restarted:  # the restarted clock passed the old one: the interval between is unseen
            self._restarted = False
            events.append(("imu_input", "time_reset_end: samples used again; integration restarts (not "
                                        "integrated across the unseen interval)"))
            self._last_t = t
            v = self._values(s, events)
            return Verdict(v.reject, v.events, reset=True)
        if self._last_t is not None and t - self._last_t > p.gap_s:
            self.counts["gap"] += 1
            self._report("gap", f"IMU gap of {t - self._last_t:.3f} s (> {p.gap_s:g} s): not integrated across",
                         s, events)
        self._last_t = t
        return self._values(s, events)

    # --- internals ----------------------------------------------------------------------------

    def _values(self, s: ImuSample, events: list) -> Verdict:
        p = self.params
        g, a, t = s.gyro_rad_s, s.accel_m_s2, s.time_fc_s
        ag, aa = np.abs(g), np.abs(a)
        if np.any(ag > p.gyro_max_rad_s) or np.any(aa > p.accel_max_m_s2):
            return self._bad("out_of_range", "IMU value out of range",
                             f"|gyro| {np.max(ag):.2f} rad/s, |accel| {np.max(aa):.1f} m/s^2 beyond any IMU's range",
                             s, events)
        v = np.concatenate((g, a))
        big = np.concatenate((ag >= p.clip_gyro_rad_s, aa >= p.clip_accel_m_s2))
        same = big & (v == self._clip_prev) if self._clip_prev is not None else np.zeros(6, bool)
        self._clip_run = np.where(same, self._clip_run + 1, big.astype(int))  # per-axis runs
        self._clip_n = int(np.max(self._clip_run))
        self._clip_prev = v
        at_int16 = s.source in _INT16_SOURCES and (np.any(ag >= RAW_GYRO_LIMIT_RAD_S - 1e-9)
                                                   or np.any(aa >= RAW_ACCEL_LIMIT_M_S2 - 1e-6))
        if at_int16 or self._clip_n >= p.clip_repeats:
            why = "at the int16 limit of " + s.source if at_int16 else \
                f"an axis above the clip threshold repeated {self._clip_n} times"
            return self._bad("saturated", "IMU saturated", f"IMU saturated: {why}", s, events)

        key = tuple(v.tolist())
        if key == self._prev:
            self._same_n += 1
        else:
            if self._frozen:
                self._frozen = False
                events.append(("imu_input", f"frozen_end: IMU values changing again after {self._same_n} "
                                            "identical samples"))
            if self._prev is not None:  # how often the values changed, before this run (EWMA)
                # (same_n - 1) unchanged samples, then this changed one
                self._live = (1.0 - LIVE_ALPHA) ** self._same_n * self._live + LIVE_ALPHA
                self._live_at_run = self._live
            self._prev, self._same_n, self._same_since_t = key, 1, t
        if self._same_n >= p.frozen_min_samples and t - self._same_since_t >= p.frozen_s \
                and self._live_at_run >= p.frozen_live_fraction:
            self._frozen = True
            return self._bad("frozen", "IMU frozen",
                             f"IMU frozen: {self._same_n} identical samples over {t - self._same_since_t:.2f} s",
                             s, events)
        return Verdict(events=tuple(events)) if events else _OK

    def _bad(self, kind: str, reason: str, detail: str, s: ImuSample, events: list) -> Verdict:
        self.counts[kind] += 1
        self._report(kind, detail, s, events)
        return Verdict(reason, tuple(events))

    def _report(self, kind: str, detail: str, s: ImuSample, events: list) -> None:
        now = s.time_rx_s if math.isfinite(s.time_rx_s) else 0.0
        last = self._reported_s.get(kind)
        if last is not None and now - last < self.params.report_interval_s:
            self._unreported[kind] = self._unreported.get(kind, 0) + 1
            return
        n = self._unreported.pop(kind, 0)
        self._reported_s[kind] = now
        events.append(("imu_input", f"{kind}: {detail}" + (f" ({n} more since the last report)" if n else "")))


class CoreImuInputChecks:
    """``ImuInputChecks`` with the per-sample decisions in the compiled core (core/input_checks.hpp,
    estimators._core.InputChecks): the same ``check(sample) -> Verdict``, ``params`` and ``counts``
    (tests/test_core_input_checks.py proves them equal). What a bad sample says (the event text,
    the counts, the report rate limit) is the reference's code, run only on a bad sample."""

    def __init__(self, params: InputCheckParams = InputCheckParams()):
        from estimators import core
        p = params
        self.params = p
        self.counts = {k: 0 for k in KINDS}
        self._c = core.input_checks_core(
            p.gyro_max_rad_s, p.accel_max_m_s2, p.clip_gyro_rad_s, p.clip_accel_m_s2,
            RAW_GYRO_LIMIT_RAD_S - 1e-9, RAW_ACCEL_LIMIT_M_S2 - 1e-6, p.frozen_s, p.gap_s, p.reset_jump_s,
            p.frozen_live_fraction, LIVE_ALPHA, p.clip_repeats, p.frozen_min_samples, p.reset_after_samples)
        # the reference's reporting (rate limit per kind) on a reference object that never checks
        self._say = ImuInputChecks(p)
        self._say.counts = self.counts

    def check(self, s: ImuSample) -> Verdict:
        g, a = s.gyro_rad_s, s.accel_m_s2
        if type(g) is not np.ndarray or type(a) is not np.ndarray:   # lists, tuples: as the reference takes them
            g, a = np.asarray(g, dtype=float), np.asarray(a, dtype=float)
        (gx, gy, gz), (ax, ay, az) = g.tolist(), a.tolist()
        r = self._c.step(gx, gy, gz, ax, ay, az, s.time_fc_s, s.source in _INT16_SOURCES)
        return _OK if r == 0 else self._words(r, s)

    def _words(self, r: int, s: ImuSample) -> Verdict:
        """The reference's verdict and events for a step that was not plainly OK (same order)."""
        from estimators import _core as c
        last_t, max_g, max_a, at16, clip_n, behind_n, same_n, same_s, end_n = self._c.detail()
        code, t, say, events = r & 0xF, s.time_fc_s, self._say, []
        if code == 1:
            return say._bad("non_finite", "non-finite IMU sample", "NaN or inf in gyro, accel or time", s, events)
        if code == 2:
            if r & c.IC_FLAG_TIME_RESET:
                self.counts["time_reset"] += 1
                say._report("time_reset", f"FC clock restarted without a reboot event ({last_t:.3f} s -> "
                                          f"{t:.3f} s for {behind_n} samples): its samples are rejected "
                                          "until their time passes the last used one", s, events)
            return say._bad("time_backwards", "IMU time not increasing",
                            f"FC time {t:.6f} s not after the last sample's {last_t:.6f} s", s, events)
        if r & c.IC_FLAG_RESET_END:
            events.append(("imu_input", "time_reset_end: samples used again; integration restarts (not "
                                        "integrated across the unseen interval)"))
        if r & c.IC_FLAG_GAP:
            self.counts["gap"] += 1
            say._report("gap", f"IMU gap of {t - last_t:.3f} s (> {self.params.gap_s:g} s): not integrated across",
                        s, events)
        v = _OK
        if code == 3:
            v = say._bad("out_of_range", "IMU value out of range",
                         f"|gyro| {max_g:.2f} rad/s, |accel| {max_a:.1f} m/s^2 beyond any IMU's range", s, events)
        elif code == 4:
            why = "at the int16 limit of " + s.source if at16 else \
                f"an axis above the clip threshold repeated {clip_n} times"
            v = say._bad("saturated", "IMU saturated", f"IMU saturated: {why}", s, events)
        else:
            if r & c.IC_FLAG_FROZEN_END:
                events.append(("imu_input", f"frozen_end: IMU values changing again after {end_n} "
                                            "identical samples"))
            if code == 5:
                v = say._bad("frozen", "IMU frozen", f"IMU frozen: {same_n} identical samples over {same_s:.2f} s",
                             s, events)
            elif events:
                v = Verdict(events=tuple(events))
        return Verdict(v.reject, v.events, reset=True) if r & c.IC_FLAG_RESET_END else v

    def __reduce__(self):  # copy.deepcopy / pickle: the core's state as a tuple
        return _restore_core_checks, (self.params, dict(self.counts), self._c.get_state(),
                                      dict(self._say._reported_s), dict(self._say._unreported))


def _restore_core_checks(params, counts, core_state, reported_s, unreported) -> CoreImuInputChecks:
    c = CoreImuInputChecks(params)
    c.counts.update(counts)
    c._c.set_state(core_state)
    c._say._reported_s, c._say._unreported = reported_s, unreported
    return c
