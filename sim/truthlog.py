"""The live simulator's truth log, written beside the MAVLink stream for test/benchmark harnesses.

``.csv``: one header line of column names (units in the names), rows appended and flushed per
chunk (survives a hard kill up to the last chunk). Any other suffix: ``.npz`` written at close.
Rows are the engine's truth decimated to ``rate_hz``; ``time_s`` is simulated time since sim
start, ``time_boot_s`` the FC clock that the MAVLink messages carry (differs after a reboot).
External yaw received over ODOMETRY is logged too (npz: ext_yaw_*; csv: a second file
``<name>.ext_yaw.csv``).
"""
from __future__ import annotations

import numpy as np

from sim.frames import euler_from_q
from sim.trajectory import PHASES

MODES = ("AUTO", "RTL", "LOITER", "GUIDED", "CIRCLE")
COLUMNS = (["time_s", "time_boot_s", "lat_rad", "lon_rad", "alt_m", "vn_m_s", "ve_m_s", "vd_m_s",
            "qw", "qx", "qy", "qz", "roll_rad", "pitch_rad", "yaw_rad",
            "omega_x_rad_s", "omega_y_rad_s", "omega_z_rad_s", "f_x_m_s2", "f_y_m_s2", "f_z_m_s2",
            "airspeed_m_s", "field_n_gauss", "field_e_gauss", "field_d_gauss",
            "fc_roll_rad", "fc_pitch_rad", "fc_yaw_rad", "phase", "mode", "gnss_ok"])


class TruthLog:
    def __init__(self, path: str, engine, rate_hz: float = 100.0):
        if not (0 < rate_hz <= engine.rate_hz):
            raise ValueError(f"truth log rate must be in (0, {engine.rate_hz}] Hz, got {rate_hz}")
        self.path = str(path)
        self.csv = self.path.lower().endswith(".csv")
        self.decim = max(1, int(round(engine.rate_hz / rate_hz)))
        self.k = 0
        self.rows: list[np.ndarray] = []
        self.ext: list[tuple[float, float, float]] = []
        self.site = engine.site()
        self._f = None
        self._fe = None
        if self.csv:
            self._f = open(self.path, "w", buffering=1 << 16)
            s = self.site
            self._f.write(f"# azimuthd sim truth; phases={','.join(PHASES)}; modes={','.join(MODES)}; "
                          f"site lat_deg={s['lat_deg']} lon_deg={s['lon_deg']} alt_m={s['alt_m']} "
                          f"launcher={s['launcher_type']} azimuth_deg={s['launcher_azimuth_deg']}\n")
            self._f.write(",".join(COLUMNS) + "\n")

    def add(self, c: dict, ap) -> None:
        n = len(c["time_s"])
        idx = np.nonzero((self.k + np.arange(n)) % self.decim == 0)[0]
        self.k += n
        if idx.size == 0:
            return
        t = c["time_s"][idx]
        eul = euler_from_q(c["q_nav_from_body"][idx])
        mode = MODES.index(ap.mode) if ap.mode in MODES else -1
        gnss_ok = (np.ones_like(t) if ap.gnss_lost_at is None else (t < ap.gnss_lost_at)).astype(float)
        block = np.column_stack([t, t - ap.boot_t0, c["lat_rad"][idx], c["lon_rad"][idx], c["alt_m"][idx],
                                 c["vel_ned_m_s"][idx], c["q_nav_from_body"][idx], eul,
                                 c["omega_body_rad_s"][idx], c["f_body_m_s2"][idx], c["airspeed_m_s"][idx],
                                 c["field_ned_gauss"][idx], c["fc_euler_rad"][idx], c["phase"][idx].astype(float),
                                 np.full(len(t), float(mode)), gnss_ok])
        if self.csv:
            np.savetxt(self._f, block, delimiter=",", fmt="%.10g")
            self._f.flush()
        else:
            self.rows.append(block)

    def add_ext_yaw(self, t: float, yaw_rad: float, var: float) -> None:
        if self.csv:
            if self._fe is None:
                self._fe = open(self.path + ".ext_yaw.csv", "w")
                self._fe.write("time_s,yaw_rad,yaw_var_rad2\n")
            self._fe.write(f"{t:.6f},{yaw_rad:.8f},{var:.6g}\n")
        else:
            self.ext.append((t, yaw_rad, var))

    def close(self) -> None:
        if self.csv:
            if self._f:
                self._f.close()
            if self._fe:
                self._fe.close()
            return
        data = np.vstack(self.rows) if self.rows else np.zeros((0, len(COLUMNS)))
        out = {name: data[:, i] for i, name in enumerate(COLUMNS)}
        ext = np.array(self.ext) if self.ext else np.zeros((0, 3))
        out.update(ext_yaw_time_s=ext[:, 0], ext_yaw_rad=ext[:, 1], ext_yaw_var_rad2=ext[:, 2],
                   phase_names=np.array(PHASES), mode_names=np.array(MODES),
                   site_C_body_from_sensor=self.site["C_body_from_sensor"],
                   site_lat_deg=self.site["lat_deg"], site_lon_deg=self.site["lon_deg"],
                   site_alt_m=self.site["alt_m"], site_launcher_azimuth_deg=self.site["launcher_azimuth_deg"],
                   site_decimal_year=self.site["decimal_year"])
        path = self.path if self.path.endswith(".npz") else self.path + ".npz"
        np.savez_compressed(path, **out)


def load_truth_log(path: str) -> dict[str, np.ndarray]:
    """Read a truth log (csv or npz) into a dict of column arrays."""
    if path.lower().endswith(".csv"):
        with open(path) as f:
            lines = [ln for ln in f if not ln.startswith("#")]
        # skip the header; drop a last row cut short by a hard kill
        rows = [ln for ln in lines[1:] if ln.endswith("\n") and ln.count(",") == len(COLUMNS) - 1]
        data = np.loadtxt(rows, delimiter=",", ndmin=2) if rows else np.zeros((0, len(COLUMNS)))
        return {name: data[:, i] for i, name in enumerate(COLUMNS)}
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


__all__ = ["TruthLog", "load_truth_log", "COLUMNS", "MODES"]
