"""Is the daemon keeping up? Loss counters turned into warnings an operator sees.

Three ways samples go missing before the estimators see them, each with its own cause:
- ``kernel_rx_drops``: the kernel dropped datagrams because our receive buffer was full. The
  daemon is not keeping up (CPU starved, a stall in the loop, a rate it cannot process);
- ``seq_lost``: MAVLink sequence gaps from the FC: lost on the wire (radio, serial noise) or by a
  full buffer somewhere upstream;
- a stalled loop: a main-loop iteration that took longer than ``stall_s`` (the watchdog fires at
  WatchdogSec; this says it earlier, with the figure).
Every ``window_s`` the monitor compares the counters with the window before and returns events
(kind, severity, detail): ``input_overflow`` and ``input_loss`` (warning) when a window lost
samples, ``loop_stall`` (warning), and ``input_ok`` (info) when a window is clean again after a
warning. A fault that persists is reported once per window (the daemon rate-limits logs further).
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LossParams:
    window_s: float = 10.0
    seq_loss_warn_fraction: float = 0.02
    """Warn when more than this fraction of the FC's messages in a window were lost by sequence."""
    stall_s: float = 0.5


class InputLossMonitor:
    def __init__(self, params: LossParams | None = None):
        self.p = params or LossParams()
        self._start_s: float | None = None
        self._base = (0, 0, 0)
        self._max_step_gap_s = 0.0
        self._warned = False
        self.windows_with_loss = 0

    def on_step_gap(self, gap_s: float) -> None:
        """The time between two loop iterations (the daemon measures it)."""
        if gap_s > self._max_step_gap_s:
            self._max_step_gap_s = gap_s

    def update(self, now_s: float, accepted: int, seq_lost: int, kernel_drops: int | None) -> list[tuple[str, str, str]]:
        kd = int(kernel_drops or 0)
        if self._start_s is None:
            self._start_s, self._base = now_s, (accepted, seq_lost, kd)
            return []
        if now_s - self._start_s < self.p.window_s:
            return []
        d_acc, d_lost, d_kd = accepted - self._base[0], seq_lost - self._base[1], kd - self._base[2]
        span = now_s - self._start_s
        self._start_s, self._base = now_s, (accepted, seq_lost, kd)
        stall, self._max_step_gap_s = self._max_step_gap_s, 0.0
        out = []
        if d_kd > 0:
            out.append(("input_overflow", "warning",
                        f"the kernel dropped {d_kd} MAVLink datagrams in {span:.0f} s (our receive buffer was full): "
                        "the daemon is not keeping up"))
        total = d_acc + d_lost
        if total > 0 and d_lost > self.p.seq_loss_warn_fraction * total:
            out.append(("input_loss", "warning",
                        f"{d_lost} of {total} messages from the FC lost in {span:.0f} s "
                        f"({100.0 * d_lost / total:.1f} %, MAVLink sequence gaps)"))
        if stall > self.p.stall_s:
            out.append(("loop_stall", "warning", f"the main loop stalled for {stall:.2f} s (samples queue meanwhile)"))
        if out:
            self.windows_with_loss += 1
            self._warned = True
        elif self._warned:
            self._warned = False
            out.append(("input_ok", "info", f"no input lost in the last {span:.0f} s"))
        return out
