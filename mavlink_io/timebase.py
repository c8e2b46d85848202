"""FC timestamps -> one monotonic FC time per stream: unwrap, reboot and gap detection.

The FC stamps its messages with time since boot, either ``time_usec`` (microseconds: RAW_IMU,
HIGHRES_IMU, ESTIMATOR_STATUS) or ``time_boot_ms`` (uint32 milliseconds: SCALED_IMU,
SCALED_PRESSURE, ATTITUDE). Two clocks wrap:

- ``time_boot_ms`` is uint32 ms: it wraps every 2^32 ms = 49.71 days;
- ArduPilot fills RAW_IMU.time_usec from ``AP_HAL::micros()``, a **uint32** microsecond counter,
  even though the field is uint64: it wraps every 2^32 us = 71.58 minutes of FC uptime. A 64-bit
  sender (PX4) simply never shows a value >= 2^32 that goes back, so the same rule is harmless.

This module turns them into ``time_fc_s`` with three guarantees:

1. **Wrap**: a raw value r (a clock with modulus M) is unwrapped to ``r + k M`` where k makes it
   closest to the *predicted* FC time ``t_pred = t_ref + (rx - rx_ref)`` (latest FC time on any
   stream plus the local time elapsed since it arrived). A change of k is accepted only when it
   lands within ``wrap_tolerance_s`` (+0.1 % of the elapsed local time, for clock drift) of
   t_pred, so a wrap is told from a reboot by the local clock, and still recognised after a
   long link loss. A new, higher k is reported once as ``time_wrap``.
2. **Reboot = the FC clock restarted.** A restarted clock goes back, or starts again near zero.
   Let ``back`` be how far a stream's (unwrapped) time went back, ``lag`` how far it lags
   the local-clock prediction t_pred, ``silence`` the local time since the previous sample
   (any stream) and ``since_boot`` the raw value itself (time since the FC's boot). The FC
   rebooted when:

   - its time went back by more than ``reboot_jump_s``; or
   - it went back by less (not a repeat), lags by more than 2 ``reboot_jump_s`` (a reboot that
     took about as long as the uptime before it), ``since_boot <= silence + restart_margin_s``
     (a clock that restarted during the silence), and the next sample on the stream goes on
     from it (a late packet in a backlog is followed by the old clock; the first sample is
     dropped as stale either way); or
   - it moved forward by more than ``reboot_jump_s``, lags by more than ``reboot_lag_s``, and
     ``since_boot <= silence + restart_margin_s`` (a reboot during a link outage longer than the
     uptime before it).

   A lag alone is no reboot. When a sender stalls (its clock paused, as the simulator's does
   when the machine starves it) or our read loop stalls (the queued samples all carry one late
   receive time), the FC time lags the local clock while staying monotonic and continuous;
   restarting the integration there would lose the attitude for nothing. A lag above
   ``backlog_report_s`` that is not a restart is reported as ``input_backlog`` with the lag and
   counted (``backlogs``); the sample is delivered (a time_gap too if the clock jumped).
   On a reboot (``fc_reboot``) every stream is reset and the output time continues
   monotonically: the new boot's time ``t_raw`` is mapped to ``t_last_out + (rx_now -
   rx_last)`` (elapsed local time across the reboot), so estimators are never handed a
   backward time. Smaller backward steps and repeats (reordered or duplicated packets) are
   dropped and counted (``stale``), never passed on.
   Ambiguous by nature: a reboot whose new clock lands within ``reboot_jump_s`` after the old
   one (taken for a backlog), a run of consecutive late packets within a stall longer than the
   FC's uptime (taken for a reboot); each needs a coincidence.
3. **Gap**: on streams given a gap threshold (the IMU), ``t - t_prev > gap_s`` is reported as
   ``time_gap`` (the sample itself is still delivered; the consumer decides to re-initialise).

Pure: no clocks, no I/O; the caller passes the local receive time.
"""
from __future__ import annotations

from dataclasses import dataclass, field

MS_WRAP = 1 << 32
"""time_boot_ms modulus (uint32 milliseconds)."""
US32_WRAP = 1 << 32
"""Modulus of a uint32 microsecond counter sent in a uint64 time_usec field (ArduPilot RAW_IMU)."""
_MOD_S = {"ms": MS_WRAP * 1e-3, "us": US32_WRAP * 1e-6}
_SCALE_S = {"ms": 1e-3, "us": 1e-6}


@dataclass(frozen=True, slots=True)
class TimebaseParams:
    reboot_jump_s: float = 1.0
    """A raw FC time going back by more than this (s) on one stream is an FC reboot."""
    reboot_lag_s: float = 5.0
    """A stream's time that jumped forward but lags the local-clock prediction by more than this
    (s), with a time since boot that fits in the silence, means the FC rebooted while the link
    was silent (e.g. up 30 s, reboot, 60 s outage)."""
    restart_margin_s: float = 1.0
    """A restarted FC clock's first time since boot is at most the local silence before it plus
    this (s): transport latency and jitter between the two samples compared."""
    backlog_report_s: float = 1.0
    """A stream lagging the local-clock prediction by more than this (s) without a clock restart
    is reported as input_backlog (a stalled sender or a queued read), never as a reboot."""
    wrap_tolerance_s: float = 2.0
    """A wrap is accepted when the unwrapped time is within this (s) of the time predicted from
    the local clock (plus 0.1 % of the local time elapsed since the reference sample)."""

    def __post_init__(self) -> None:
        if not self.reboot_jump_s > 0:
            raise ValueError(f"reboot_jump_s must be > 0, got {self.reboot_jump_s}")
        if not self.reboot_lag_s > 0:
            raise ValueError(f"reboot_lag_s must be > 0, got {self.reboot_lag_s}")
        if not self.restart_margin_s >= 0:
            raise ValueError(f"restart_margin_s must be >= 0, got {self.restart_margin_s}")
        if not self.backlog_report_s > 0:
            raise ValueError(f"backlog_report_s must be > 0, got {self.backlog_report_s}")
        if not 0 < self.wrap_tolerance_s < 600.0:
            raise ValueError(f"wrap_tolerance_s must be in (0, 600), got {self.wrap_tolerance_s}")


@dataclass(slots=True)
class _Stream:
    last_raw_s: float
    last_out_s: float
    restart_candidate_s: float | None = None
    """A sample that may be a quick reboot's first (or a late packet): held until the next one."""


@dataclass(slots=True)
class TimebaseEvent:
    kind: str
    """"time_wrap", "fc_reboot", "input_backlog" or "time_gap"."""
    detail: str


@dataclass(slots=True)
class FcTimebase:
    """State of the FC clock reconstruction (one per link)."""
    params: TimebaseParams = field(default_factory=TimebaseParams)
    wraps: dict[str, int] = field(default_factory=lambda: {"ms": 0, "us": 0})
    """Wrap count of each clock ("ms": uint32 ms, "us": uint32 us) in the current boot."""
    t_ref_s: float | None = None
    """Latest raw (unwrapped, current boot) FC time seen on any stream, s."""
    rx_ref_s: float | None = None
    """Local receive time of that sample, s."""
    offset_s: float = 0.0
    """Added to the current boot's raw time to keep the output monotonic across reboots, s."""
    last_out_s: float | None = None
    last_rx_s: float | None = None
    streams: dict[str, _Stream] = field(default_factory=dict)
    floors_s: dict[str, float] = field(default_factory=dict)
    """Last output time per stream, kept across reboots: the output never goes back."""
    units_seen: set = field(default_factory=set)
    """Clocks ("ms", "us") seen in the current boot (a first sample's wrap count is not an event)."""
    stale: int = 0
    """Samples dropped because their time did not advance on their stream."""
    reboots: int = 0
    backlogs: int = 0
    """Samples that lagged the local clock by more than backlog_report_s without a clock restart."""
    backlog_max_s: float = 0.0
    """The largest such lag, s."""

    def _unwrap(self, raw: int, unit: str, rx_s: float, events: list[TimebaseEvent]) -> float:
        raw_s = raw * _SCALE_S[unit]
        if unit == "us" and raw >= US32_WRAP:
            return raw_s  # a 64-bit microsecond clock: nothing to unwrap
        k_now = self.wraps[unit]
        if self.t_ref_s is None:
            self.units_seen.add(unit)
            return raw_s + k_now * _MOD_S[unit]
        mod_s = _MOD_S[unit]
        elapsed_s = max(0.0, rx_s - self.rx_ref_s)
        t_pred = self.t_ref_s + elapsed_s
        k = max(0, round((t_pred - raw_s) / mod_s))
        if k != k_now:
            tol_s = self.params.wrap_tolerance_s + 1e-3 * elapsed_s
            if abs(raw_s + k * mod_s - t_pred) > tol_s:
                k = k_now  # not consistent with the local clock: keep the count, jump logic judges
            elif k > k_now and unit not in self.units_seen:
                self.wraps[unit] = k  # first sample of this clock: the FC was up long before we came
            elif k > k_now:
                self.wraps[unit] = k
                clock = "time_boot_ms (uint32 ms)" if unit == "ms" else "time_usec (uint32 us counter)"
                events.append(TimebaseEvent(
                    "time_wrap", f"{clock} wrapped (count {k}): raw {raw} -> {raw_s + k * mod_s:.6f} s"))
        self.units_seen.add(unit)
        return raw_s + k * mod_s

    def reset(self) -> None:
        """Forget the FC clock entirely (e.g. a different FC). Output stays monotonic."""
        self.wraps = {"ms": 0, "us": 0}
        self.t_ref_s = None
        self.rx_ref_s = None
        self.units_seen.clear()
        self.streams.clear()

    def feed(self, stream: str, raw: int, unit: str, rx_s: float,
             gap_s: float | None = None) -> tuple[float | None, list[TimebaseEvent]]:
        """One timestamp in; (monotonic FC time in s or None if dropped, events) out.

        stream: the message type (each stream is monotonic on its own); raw: the integer field;
        unit: "us" (time_usec) or "ms" (time_boot_ms); rx_s: local receive time, s;
        gap_s: report a time_gap when this stream advances by more than this (None: never).
        """
        events: list[TimebaseEvent] = []
        if unit not in _MOD_S:
            raise ValueError(f"unit must be 'us' or 'ms', got {unit!r}")
        t_raw = self._unwrap(int(raw) % MS_WRAP if unit == "ms" else int(raw), unit, rx_s, events)
        st = self.streams.get(stream)
        rebooted = False
        lag_s = 0.0
        if st is not None:
            back_s = st.last_raw_s - t_raw
            # how far behind the local-clock prediction: ~0 for a reordered or duplicated packet,
            # ~ the FC's uptime before the reboot for a restarted clock, the stall for a backlog
            lag_s = self.t_ref_s + max(0.0, rx_s - self.rx_ref_s) - t_raw
            # could the clock have restarted since the previous sample? its time since boot
            # (the raw value) must fit in the local time that passed meanwhile
            silence_s = max(0.0, rx_s - self.last_rx_s)
            since_boot_s = (int(raw) % MS_WRAP) * 1e-3 if unit == "ms" else int(raw) * 1e-6
            restart_fits = since_boot_s <= silence_s + self.params.restart_margin_s
            p = self.params
            if back_s > p.reboot_jump_s:
                rebooted = True
            elif back_s > 0.0 and lag_s > 2.0 * p.reboot_jump_s and restart_fits:
                # a quick reboot (a little back, its whole uptime behind) or a late packet in a
                # backlog: one sample cannot tell. A restarted clock goes on from there, a late
                # packet is followed by the old clock: confirmed by the next sample
                cand = st.restart_candidate_s
                if cand is None or not 0.0 < t_raw - cand <= p.reboot_jump_s:
                    st.restart_candidate_s = t_raw
                    self.stale += 1
                    return None, events
                rebooted = True
            elif back_s >= 0.0:
                self.stale += 1  # a repeat or a late packet, also when it arrives in a backlog
                return None, events
            elif -back_s > p.reboot_jump_s and lag_s > p.reboot_lag_s and restart_fits:
                rebooted = True  # forward, far behind the local clock: rebooted during a silence
        if rebooted:
            # FC clock restarted: continue our output time across the reboot with local time
            last_out = self.last_out_s if self.last_out_s is not None else st.last_out_s
            elapsed_s = max(rx_s - (self.last_rx_s if self.last_rx_s is not None else rx_s), 1e-3)
            self.offset_s = last_out + elapsed_s - t_raw
            self.reboots += 1
            how = (f"went back {back_s:.3f} s" if back_s >= 0 else
                   f"restarted within a {silence_s:.3f} s silence (lags the local clock by {lag_s:.3f} s)")
            events.append(TimebaseEvent(
                "fc_reboot", f"{stream} time {how} (from {st.last_raw_s:.3f} s to {t_raw:.3f} s since "
                             f"boot): FC rebooted; FC time continues at {t_raw + self.offset_s:.3f} s"))
            self.reset()
            t_raw = self._unwrap(int(raw) % MS_WRAP if unit == "ms" else int(raw), unit, rx_s, events)
            st = None
        elif lag_s > self.params.backlog_report_s:
            self.backlogs += 1
            self.backlog_max_s = max(self.backlog_max_s, lag_s)
            events.append(TimebaseEvent(
                "input_backlog", f"FC time lags the local clock (a stalled sender or a queued read, not "
                                 f"a reboot: the FC clock did not restart): {stream} by {lag_s:.3f} s, "
                                 f"its time went on by {-back_s:.3f} s to {t_raw:.3f} s since boot"))
        t_out = t_raw + self.offset_s
        floor = self.floors_s.get(stream)
        if floor is not None and t_out <= floor:
            self.stale += 1
            return None, events
        self.floors_s[stream] = t_out
        if st is not None:
            if gap_s is not None and t_raw - st.last_raw_s > gap_s:
                events.append(TimebaseEvent(
                    "time_gap", f"{stream} gap of {t_raw - st.last_raw_s:.3f} s (> {gap_s:g} s) "
                                f"at FC time {t_out:.3f} s"))
            st.last_raw_s = t_raw
            st.last_out_s = t_out
            st.restart_candidate_s = None
        else:
            self.streams[stream] = _Stream(t_raw, t_out)
        if self.t_ref_s is None or t_raw > self.t_ref_s:
            self.t_ref_s = t_raw
            self.rx_ref_s = rx_s
        if self.last_out_s is None or t_out > self.last_out_s:
            self.last_out_s = t_out
        self.last_rx_s = rx_s
        return t_out, events
