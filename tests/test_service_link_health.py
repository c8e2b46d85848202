"""The falling-behind monitor: loss counters become warnings once per window, and an all-clear."""
from __future__ import annotations

from service.link_health import InputLossMonitor, LossParams


def test_kernel_drops_sequence_loss_and_stalls_are_reported_per_window():
    mon = InputLossMonitor(LossParams(window_s=10.0, seq_loss_warn_fraction=0.02, stall_s=0.5))
    assert mon.update(0.0, accepted=0, seq_lost=0, kernel_drops=0) == []
    assert mon.update(5.0, 500, 0, 0) == []          # window not over yet
    assert mon.update(10.0, 1000, 10, 0) == []       # 1 % lost: under the threshold
    ev = mon.update(20.0, 2000, 60, 7)               # 50 of 1050 lost (4.8 %), 7 kernel drops
    kinds = [k for k, _s, _d in ev]
    assert kinds == ["input_overflow", "input_loss"]
    assert "dropped 7 MAVLink datagrams" in ev[0][2] and "50 of 1050" in ev[1][2]
    mon.on_step_gap(0.2)
    mon.on_step_gap(0.9)
    ev = mon.update(30.0, 3000, 60, 7)
    assert [k for k, _s, _d in ev] == ["loop_stall"] and "0.90 s" in ev[0][2]
    ev = mon.update(40.0, 4000, 60, 7)
    assert [(k, s) for k, s, _d in ev] == [("input_ok", "info")]
    assert mon.update(50.0, 5000, 60, 7) == []       # clean and already said so
    assert mon.windows_with_loss == 2


def test_unknown_kernel_counter_counts_as_zero():
    mon = InputLossMonitor()
    mon.update(0.0, 0, 0, None)
    assert mon.update(10.0, 1000, 0, None) == []
