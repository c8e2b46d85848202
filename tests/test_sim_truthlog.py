"""The truth log beside the live stream: CSV (appended live) and npz give the same columns."""
from __future__ import annotations

import types

import numpy as np

from sim.engine import Engine
from sim.truthlog import COLUMNS, TruthLog, load_truth_log


def _write(path, n_chunks=30):
    eng = Engine("vertical_launch", seed=1, rate_hz=200.0, overrides={"launcher": {"rest_s": 1.0}})
    ap = types.SimpleNamespace(mode="AUTO", gnss_lost_at=2.0, boot_t0=0.0)
    log = TruthLog(str(path), eng, rate_hz=50.0)
    chunks = []
    for _ in range(n_chunks):
        c = eng.chunk(20)
        chunks.append(c)
        log.add(c, ap)
    log.add_ext_yaw(1.5, 0.25, 0.01)
    log.close()
    return {k: np.concatenate([c[k] for c in chunks]) for k in ("time_s", "q_nav_from_body", "f_body_m_s2")}


def test_csv_and_npz_truth_logs_agree_and_decimate(tmp_path):
    ref = _write(tmp_path / "t.npz")
    _write(tmp_path / "t.csv")
    a = load_truth_log(str(tmp_path / "t.npz"))
    b = load_truth_log(str(tmp_path / "t.csv"))
    for name in COLUMNS:
        np.testing.assert_allclose(a[name], b[name], rtol=1e-9, atol=1e-9, err_msg=name)
    np.testing.assert_allclose(a["time_s"], ref["time_s"][::4])  # 200 Hz -> 50 Hz rows
    np.testing.assert_allclose(a["f_x_m_s2"], ref["f_body_m_s2"][::4, 0])
    assert set(np.unique(a["gnss_ok"])) == {0.0, 1.0}
    assert a["gnss_ok"][a["time_s"] < 2.0].all() and not a["gnss_ok"][a["time_s"] >= 2.0].any()
    assert a["ext_yaw_rad"][0] == 0.25
    assert (tmp_path / "t.csv.ext_yaw.csv").read_text().splitlines()[1].startswith("1.5")


def test_csv_truth_log_survives_a_cut_last_line(tmp_path):
    _write(tmp_path / "t.csv", n_chunks=5)
    with open(tmp_path / "t.csv", "a") as f:
        f.write("12.0,1,2")  # a hard kill in the middle of a row
    d = load_truth_log(str(tmp_path / "t.csv"))
    assert len(d["time_s"]) == 25 and d["time_s"][-1] < 12.0
