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
2. **Reboot (backward jump)**: a stream whose (unwrapped) time goes back by more than
   ``reboot_jump_s``, or goes back at all while lagging the local-clock prediction by more than
   2 ``reboot_jump_s`` (a reboot that took about as long as the uptime before it), or moves
   forward but lags the prediction by more than ``reboot_lag_s`` (a reboot during a link outage
   longer than the uptime before it), means the FC rebooted. Reported as ``fc_reboot``; every stream is reset and
   the output time continues monotonically: the new boot's time ``t_raw`` is mapped to
   ``t_last_out + (rx_now - rx_last)`` (elapsed local time across the reboot), so estimators are
   never handed a backward time. Smaller backward steps (reordered or duplicated packets) are
   dropped and counted (``stale``), never passed on.
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
    """A stream's time that moved forward but lags the local-clock prediction by more than this
    (s) means the FC rebooted while the link was silent (e.g. up 30 s, reboot, 60 s outage)."""
    wrap_tolerance_s: float = 2.0
    """A wrap is accepted when the unwrapped time is within this (s) of the time predicted from
    the local clock (plus 0.1 % of the local time elapsed since the reference sample)."""

    def __post_init__(self) -> None:
        if not self.reboot_jump_s > 0:
            raise ValueError(f"reboot_jump_s must be > 0, got {self.reboot_jump_s}")
        if not self.reboot_lag_s > 0:
            raise ValueError(f"reboot_lag_s must be > 0, got {self.reboot_lag_s}")
        if not 0 < self.wrap_tolerance_s < 600.0:
            raise ValueError(f"wrap_tolerance_s must be in (0, 600), got {self.wrap_tolerance_s}")


@dataclass(slots=True)
class _Stream:
    last_raw_s: float
    last_out_s: float


@dataclass(slots=True)
class TimebaseEvent:
    kind: str
    """"time_wrap", "fc_reboot" or "time_gap"."""
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
        if st is not None:
            back_s = st.last_raw_s - t_raw
            # how far behind the local-clock prediction: ~0 for a reordered or duplicated packet,
            # ~ the FC's uptime before the reboot for a restarted clock, whatever the silence
            deficit_s = self.t_ref_s + max(0.0, rx_s - self.rx_ref_s) - t_raw
            if back_s >= 0.0:
                if back_s <= self.params.reboot_jump_s and deficit_s <= 2.0 * self.params.reboot_jump_s:
                    self.stale += 1
                    return None, events
                rebooted = True
            elif deficit_s > self.params.reboot_lag_s:
                rebooted = True  # forward, yet far behind the local clock: rebooted during a silence
        if rebooted:
            # FC clock restarted: continue our output time across the reboot with local time
            last_out = self.last_out_s if self.last_out_s is not None else st.last_out_s
            elapsed_s = max(rx_s - (self.last_rx_s if self.last_rx_s is not None else rx_s), 1e-3)
            self.offset_s = last_out + elapsed_s - t_raw
            self.reboots += 1
            how = (f"went back {back_s:.3f} s" if back_s >= 0 else
                   f"lags the local clock by {deficit_s:.3f} s")
            events.append(TimebaseEvent(
                "fc_reboot", f"{stream} time {how} (from {st.last_raw_s:.3f} s to {t_raw:.3f} s since "
                             f"boot): FC rebooted; FC time continues at {t_raw + self.offset_s:.3f} s"))
            self.reset()
            t_raw = self._unwrap(int(raw) % MS_WRAP if unit == "ms" else int(raw), unit, rx_s, events)
            st = None
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
        else:
            self.streams[stream] = _Stream(t_raw, t_out)
        if self.t_ref_s is None or t_raw > self.t_ref_s:
            self.t_ref_s = t_raw
            self.rx_ref_s = rx_s
        if self.last_out_s is None or t_out > self.last_out_s:
            self.last_out_s = t_out
        self.last_rx_s = rx_s
        return t_out, events
