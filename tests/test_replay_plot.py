"""The replay plot's line handling: broken at time gaps and at the heading's 0/360 wrap, sigma
bands capped, the stretches whose heading uses the FC's own yaw found; the PNG is written."""
import numpy as np
import pytest

from service.replay import PLOT_SIGMA_CAP_DEG, ReplayResult, _breaks, _runs, plot


def test_breaks_at_gaps_and_wraps():
    t = np.array([0.0, 0.02, 0.04, 0.06, 2.0, 2.02])
    y = np.array([350.0, 355.0, 359.0, 3.0, 4.0, 5.0])
    tb, yb = _breaks(t, y, wrap_deg=360.0)
    # a NaN between 359 -> 3 (the wrap) and between 0.06 -> 2.0 s (the gap): nothing else
    assert np.isnan(yb).sum() == 2 and np.isnan(tb).sum() == 2
    assert list(np.nonzero(np.isnan(yb))[0]) == [3, 5]
    tb, yb = _breaks(t, np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]))
    assert list(np.nonzero(np.isnan(yb))[0]) == [4]  # the gap only


def test_runs():
    assert _runs(np.array([False, True, True, False, True])) == [(1, 3), (4, 5)]
    assert _runs(np.array([False, False])) == []


def test_plot_writes_a_png_with_capped_bands(tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    from matplotlib.figure import Figure
    saved = []
    real_savefig = Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda self, *a, **k: (saved.append(self), real_savefig(self, *a, **k)))
    n = 400
    res = ReplayResult()
    t = np.arange(n) * 0.02
    res.time_s = list(t)
    res.phase = ["pre-launch"] * n
    hdg = (350.0 + 0.1 * np.arange(n)) % 360.0
    res.cols = {"roll_deg": list(np.zeros(n)), "pitch_deg": list(np.zeros(n)), "heading_deg": list(hdg),
                "heading_sigma_deg": list(np.full(n, 200.0)), "azimuth_deg": [np.nan] * n,
                "azimuth_sigma_deg": [np.nan] * n, "ref_roll_deg": list(np.zeros(n)),
                "ref_pitch_deg": list(np.zeros(n)), "ref_heading_deg": list(hdg)}
    res.heading_source = ["fc"] * 100 + ["synthetic_ahrs"] * 200 + ["coast"] * 100
    res.roll_sigma_deg = list(np.full(n, 500.0))
    res.pitch_sigma_deg = list(np.full(n, 1.0))
    out = tmp_path / "p.png"
    plot(res, out, "test")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    ax_roll, ax_roll_err = saved[0].axes[0], saved[0].axes[1]
    # a roll sigma of 500 deg is drawn as 30: the axes stay within the cap (plus matplotlib's margin)
    for ax in (ax_roll, ax_roll_err):
        lo, hi = ax.get_ylim()
        assert -1.1 * PLOT_SIGMA_CAP_DEG <= lo and hi <= 1.1 * PLOT_SIGMA_CAP_DEG
    # the heading's fc stretch is shaded on both heading panels (an axvspan patch each)
    assert len(saved[0].axes[4].patches) == 1 and len(saved[0].axes[5].patches) == 1
