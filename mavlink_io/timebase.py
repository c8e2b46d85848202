"""FC timestamps -> one monotonic FC time per stream: unwrap, reboot and gap detection.

The FC stamps its messages with time since boot, either ``time_usec`` (uint64 microseconds,
RAW_IMU, HIGHRES_IMU, ESTIMATOR_STATUS: never wraps in practice) or ``time_boot_ms`` (uint32
milliseconds, SCALED_IMU, SCALED_PRESSURE, ATTITUDE: wraps every 2^32 ms = 49.71 days). This
module turns them into ``time_fc_s`` with three guarantees:

1. **Wrap**: a ``time_boot_ms`` value is unwrapped against the latest FC time seen on any stream
   (``t_ref``): it takes the wrap count k that puts ``raw + k 2^32`` within ``wrap_window_s`` of
   ``t_ref``. A new k above every previous one is reported once as ``time_wrap``.
2. **Reboot (backward jump)**: a stream whose raw time goes back by more than ``reboot_jump_s``
   means the FC rebooted (its clock restarted). Reported as ``fc_reboot``; every stream is reset
   and the output time is continued monotonically: the new boot's time ``t_raw`` is mapped to
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


@dataclass(frozen=True, slots=True)
class TimebaseParams:
    reboot_jump_s: float = 1.0
    """A raw FC time going back by more than this (s) on one stream is an FC reboot."""
    wrap_window_s: float = 60.0
    """A time_boot_ms value is unwrapped only if it lands within this (s) of the latest FC time."""

    def __post_init__(self) -> None:
        if not self.reboot_jump_s > 0:
            raise ValueError(f"reboot_jump_s must be > 0, got {self.reboot_jump_s}")
        if not 0 < self.wrap_window_s < MS_WRAP / 2000.0:
            raise ValueError(f"wrap_window_s must be in (0, {MS_WRAP / 2000.0:g}), got {self.wrap_window_s}")


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
    wraps: int = 0
    """Highest time_boot_ms wrap count seen in the current boot."""
    t_ref_s: float | None = None
    """Latest raw (unwrapped, current boot) FC time seen on any stream, s."""
    offset_s: float = 0.0
    """Added to the current boot's raw time to keep the output monotonic across reboots, s."""
    last_out_s: float | None = None
    last_rx_s: float | None = None
    streams: dict[str, _Stream] = field(default_factory=dict)
    floors_s: dict[str, float] = field(default_factory=dict)
    """Last output time per stream, kept across reboots: the output never goes back."""
    stale: int = 0
    """Samples dropped because their time did not advance on their stream."""
    reboots: int = 0

    def _unwrap_ms(self, raw_ms: int, events: list[TimebaseEvent]) -> float:
        if self.t_ref_s is None:
            return raw_ms * 1e-3
        ref_ms = self.t_ref_s * 1000.0
        k = round((ref_ms - raw_ms) / MS_WRAP)
        k = max(k, 0)
        t_ms = raw_ms + k * MS_WRAP
        if abs(t_ms - ref_ms) > self.params.wrap_window_s * 1000.0:
            k = self.wraps  # no consistent unwrap: keep the current count, let jump logic judge
            t_ms = raw_ms + k * MS_WRAP
        elif k > self.wraps:
            self.wraps = k
            events.append(TimebaseEvent(
                "time_wrap", f"time_boot_ms wrapped (count {k}): raw {raw_ms} ms -> {t_ms * 1e-3:.3f} s"))
        return t_ms * 1e-3

    def reset(self) -> None:
        """Forget the FC clock entirely (e.g. a different FC). Output stays monotonic."""
        self.wraps = 0
        self.t_ref_s = None
        self.streams.clear()

    def feed(self, stream: str, raw: int, unit: str, rx_s: float,
             gap_s: float | None = None) -> tuple[float | None, list[TimebaseEvent]]:
        """One timestamp in; (monotonic FC time in s or None if dropped, events) out.

        stream: the message type (each stream is monotonic on its own); raw: the integer field;
        unit: "us" (time_usec) or "ms" (time_boot_ms); rx_s: local receive time, s;
        gap_s: report a time_gap when this stream advances by more than this (None: never).
        """
        events: list[TimebaseEvent] = []
        if unit == "us":
            t_raw = raw * 1e-6
        elif unit == "ms":
            t_raw = self._unwrap_ms(int(raw) % MS_WRAP, events)
        else:
            raise ValueError(f"unit must be 'us' or 'ms', got {unit!r}")
        st = self.streams.get(stream)
        if st is not None and t_raw <= st.last_raw_s:
            back_s = st.last_raw_s - t_raw
            if back_s <= self.params.reboot_jump_s:
                self.stale += 1
                return None, events
            # FC clock restarted: continue our output time across the reboot with local time
            last_out = self.last_out_s if self.last_out_s is not None else st.last_out_s
            elapsed_s = max(rx_s - (self.last_rx_s if self.last_rx_s is not None else rx_s), 1e-3)
            self.offset_s = last_out + elapsed_s - t_raw
            self.reboots += 1
            events.append(TimebaseEvent(
                "fc_reboot", f"{stream} time went back {back_s:.3f} s (from {st.last_raw_s:.3f} s to "
                             f"{t_raw:.3f} s since boot): FC rebooted; FC time continues at "
                             f"{t_raw + self.offset_s:.3f} s"))
            self.wraps = 0
            self.t_ref_s = None
            self.streams.clear()
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
        if self.last_out_s is None or t_out > self.last_out_s:
            self.last_out_s = t_out
        self.last_rx_s = rx_s
        return t_out, events
