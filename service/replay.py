"""``azimuthd replay LOG``: a recorded flight log through the daemon's own Pipeline, offline.

    azimuthd replay LOG [--config FILE | --site LAT,LON[,ALT]] [--output OUT.csv] [--plot OUT.png]

The log's samples (service.logreaders: .tlog, .bin, .ulg) go, in the log's order, to the same
``service.pipeline.Pipeline`` the daemon runs, as fast as the CPU allows; every NavSolution becomes
a CSV row next to the log's own FC attitude (the reference, held from the last FC attitude at most
``--ref-max-age`` seconds old in FC time). At the end: the streams found and missing, the phases
reached, the RMS differences against the reference, the speed.

Exit codes: 0 done; 2 bad input (unknown extension, not a log, truncated to nothing, no IMU,
no site, bad config), with a one-line message and no traceback.

CSV columns (degrees; empty where a value does not exist): see ``CSV_COLUMNS`` and docs/REPLAY.md.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from service import aiding

SOLUTION_COLUMNS = ["time_s", "phase", "roll_deg", "pitch_deg", "heading_deg", "heading_sigma_deg",
                    "heading_source", "azimuth_deg", "azimuth_sigma_deg", "ref_roll_deg", "ref_pitch_deg",
                    "ref_heading_deg"]
CSV_COLUMNS = SOLUTION_COLUMNS + aiding.csv_columns()
"""The solution, the log's reference, then each heading source's aiding record (service/aiding.py:
``aid_<source>_<field>``, degrees; fused 1/0; why_not a code) of the arbitration step that row's
solution came from."""
REF_MAX_AGE_S = 1.0
LOW_IMU_RATE_HZ = 50.0
"""Below this IMU rate the summary warns that the estimators cannot work as designed."""
"""Default: an FC attitude further than this from a sample (FC time) is no reference for it."""

# pygeomag coefficient sets by validity start year (the daemon's config accepts 2025..2030 only)
_WMM_BY_EPOCH = ((2010.0, "wmm_2010", "WMM_2010"), (2015.0, "wmm_2015v2", "WMM_2015v2"),
                 (2020.0, "wmm_2020", "WMM_2020"))


class ReplayError(ValueError):
    """Input the replay cannot use: reported in one line, exit code 2."""


# --- config ------------------------------------------------------------------------------------

def _parse_site(text: str) -> tuple[float, float, float | None]:
    parts = [p.strip() for p in text.split(",")]
    if len(parts) not in (2, 3):
        raise ReplayError(f"--site: expected LAT,LON or LAT,LON,ALT_M (degrees, metres), got {text!r}")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise ReplayError(f"--site: not numbers: {text!r}") from None
    if not all(math.isfinite(v) for v in vals) or not -90 <= vals[0] <= 90 or not -180 <= vals[1] <= 180:
        raise ReplayError(f"--site: latitude must be in [-90, 90] and longitude in [-180, 180], got {text!r}")
    return vals[0], vals[1], (vals[2] if len(vals) == 3 else None)


def _field_for_year(lat: float, lon: float, alt_m: float, year: float) -> tuple[list, str] | None:
    """The WMM field [N, E, D] gauss for a log dated before the daemon's model (2025..2030)."""
    import importlib
    from pygeomag import GeoMag
    for start, mod, attr in _WMM_BY_EPOCH:
        if start <= year < start + 5.0:
            coeff = getattr(importlib.import_module(f"pygeomag.wmm.{mod}"), attr)
            r = GeoMag(coefficients_data=coeff).calculate(glat=lat, glon=lon, alt=alt_m / 1000.0, time=year)
            return [r.x * 1e-5, r.y * 1e-5, r.z * 1e-5], attr.replace("_", "-")
    return None


def _read_config(path: str) -> dict:
    """The config file's tables as written (validated once, after the site is merged in: a config
    without [site] is valid here when --site or the log gives it). ConfigError as the daemon's."""
    import tomllib
    from service.config import ConfigError
    p = Path(path)
    try:
        raw = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{p}: config file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{p}: is a directory, not a config file") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    for section, keys in raw.items():
        if not isinstance(keys, dict):
            raise ConfigError(f"{section}: must be a table [{section}]")
    return raw


def _from_log(reader, fn):
    """``fn()`` of a reader; a damaged log's parser exception becomes one LogError line."""
    from service.logreaders import LogError, one_line
    try:
        return fn()
    except LogError:
        raise
    except (ValueError, KeyError, IndexError, TypeError, AttributeError, OverflowError) as exc:
        raise LogError(f"{reader.path}: unreadable ({one_line(exc)})") from None


def build_config(args, reader) -> tuple[dict, list[str]]:
    """The Pipeline config: --config if given, else the defaults; the site from --site, else the
    config, else the log's GNSS. Returns (validated config, notes for the user)."""
    from service.config import SPEC, ConfigError, validate
    notes: list[str] = []
    try:
        raw = _read_config(args.config) if args.config else {}
    except ConfigError as exc:
        raise ReplayError(f"config error: {exc}") from None
    if args.config:
        notes.append(f"config: {args.config}")
    site_cfg = raw.setdefault("site", {})
    have_site = site_cfg.get("lat_deg") is not None or site_cfg.get("earth_field_ned_gauss") is not None
    year = _from_log(reader, reader.decimal_year)
    if args.site:
        lat, lon, alt = _parse_site(args.site)
        site_cfg.update({"lat_deg": lat, "lon_deg": lon, "earth_field_ned_gauss": None})
        if alt is not None:
            site_cfg["alt_m"] = alt
        notes.append(f"site from --site: {lat:.6f}, {lon:.6f}")
        have_site, site_from_log = True, False
    elif not have_site:
        site = _from_log(reader, reader.site)
        if site is None:
            raise ReplayError(f"{reader.path}: the log has no GNSS position it says is valid (no 3D fix, no "
                              "valid home) to take the launch site from: "
                              "give --site LAT,LON or --config FILE with [site] lat_deg/lon_deg")
        site_cfg.update({"lat_deg": round(site.lat_deg, 7), "lon_deg": round(site.lon_deg, 7),
                         "alt_m": float(min(max(site.alt_m, -500.0), 10000.0))})
        notes.append(f"site from the log's {site.source}: {site.lat_deg:.6f}, {site.lon_deg:.6f}, "
                     f"{site.alt_m:.0f} m")
        site_from_log = True
    else:
        site_from_log = False
    if (args.site or site_from_log) and site_cfg.get("decimal_year") is None:
        if year is not None and 2025.0 <= year <= 2030.0:
            site_cfg["decimal_year"] = round(year, 4)
            notes.append(f"field model date from the log: {year:.2f}")
        elif year is not None:
            got = _field_for_year(site_cfg["lat_deg"], site_cfg["lon_deg"], site_cfg.get("alt_m", 0.0), year)
            if got is not None:
                site_cfg["earth_field_ned_gauss"] = [round(v, 6) for v in got[0]]
                notes.append(f"the log is dated {year:.2f}, before the daemon's field model (2025..2030): "
                             f"Earth field from {got[1]} at the site: [{', '.join(f'{v:.4f}' for v in got[0])}] G")
            else:
                notes.append(f"the log is dated {year:.2f}: no field model for that date; the field "
                             "model's date is today")
        else:
            notes.append("the log carries no date: the field model's date is today")
    try:
        cfg = validate({s: {k: v for k, v in keys.items() if v is not None} if s in SPEC else keys
                        for s, keys in raw.items()})
    except ConfigError as exc:
        raise ReplayError(f"config error: {exc}") from None
    if getattr(args, "exclude_fc_yaw", False):
        # set after validation: the key may be newer than this config's schema
        cfg["heading"]["use_fc_yaw"] = False
        notes.append("the FC's yaw excluded (--exclude-fc-yaw): heading.use_fc_yaw = false")
    elif cfg["heading"].get("use_fc_yaw", True):
        from_us = fc_yaw_from_our_odometry(reader.summary)
        if from_us is not None:
            cfg["heading"]["use_fc_yaw"] = False
            notes.append(f"the FC's yaw excluded: the log's parameters say it came from our ODOMETRY ({from_us}); "
                         "it is neither a heading source nor a reference here, as the daemon would have done")
    return cfg, notes


def fc_yaw_from_our_odometry(summary) -> str | None:
    """Why the log's FC yaw is ours (its EKF fused azimuthd's ODOMETRY yaw: VISO_TYPE with an
    EK3_SRCn_YAW 6, PX4's EKF2_EV_CTRL or, before 1.14, EKF2_AID_MASK yaw bit), as the daemon decides it live from the same
    parameters (mavlink_io/fc_yaw_feed.py); None when the parameters do not say so or are absent."""
    from mavlink_io.fc_yaw_feed import check_fc_yaw_feed, params_for
    params = getattr(summary, "params", None) or {}
    autopilot = getattr(summary, "autopilot", None)
    wanted = params_for(autopilot)
    if not params or not wanted:
        return None
    check = check_fc_yaw_feed(autopilot, params, set(wanted) - set(params))
    return check.reason if check.fc_yaw_from_us else None


# --- the replay --------------------------------------------------------------------------------

@dataclass
class ReplayResult:
    """Arrays, one entry per output row (degrees; NaN where empty), and the run's figures."""
    time_s: list = field(default_factory=list)
    phase: list = field(default_factory=list)
    cols: dict = field(default_factory=lambda: {c: [] for c in SOLUTION_COLUMNS[2:] if c != "heading_source"})
    heading_source: list = field(default_factory=list)
    roll_sigma_deg: list = field(default_factory=list)
    pitch_sigma_deg: list = field(default_factory=list)
    counts: dict = field(default_factory=dict)
    missing: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    events: list = field(default_factory=list)
    phases: list = field(default_factory=list)
    """(phase, first FC time s) in the order reached."""
    wall_s: float = 0.0
    pipeline_s: float = 0.0
    imu_samples: int = 0
    counters: object = None


def _deg(rad) -> float:
    return math.degrees(rad) if rad is not None and math.isfinite(rad) else math.nan


def _fmt(v: float, spec: str = ".12g") -> str:
    return "" if v is None or not math.isfinite(v) else format(v, spec)


class _Progress:
    """A progress bar with the ETA on stderr: on a terminal by default, or when asked (lines then)."""

    WIDTH = 24

    def __init__(self, enabled: bool | None, stream=None):
        self.stream = stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(stream, "isatty", lambda: False)())
        self.enabled = self.tty if enabled is None else enabled
        self.t0 = time.monotonic()
        self.next_s = self.t0 + 1.0
        self.shown = False

    def update(self, frac: float, t_fc: float | None, n_imu: int) -> None:
        now = time.monotonic()
        if not self.enabled or now < self.next_s:
            return
        self.next_s = now + (0.5 if self.tty else 5.0)
        frac = min(max(frac, 0.0), 1.0)
        elapsed = now - self.t0
        eta = f"ETA {_clock(elapsed * (1.0 - frac) / frac)}" if frac > 0.01 else "ETA --:--"
        bar = "#" * int(round(self.WIDTH * frac))
        msg = (f"replay [{bar:<{self.WIDTH}}] {100 * frac:5.1f}%  {eta}  elapsed {_clock(elapsed)}  "
               f"log t={t_fc if t_fc is not None else float('nan'):.1f} s  {n_imu / max(elapsed, 1e-9):,.0f} IMU/s")
        self.stream.write(("\r" + msg + " " * 4) if self.tty else (msg + "\n"))
        self.stream.flush()
        self.shown = True

    def done(self) -> None:
        if self.shown and self.tty:
            self.stream.write("\n")
            self.stream.flush()


def _clock(seconds: float) -> str:
    m, sec = divmod(int(round(seconds)), 60)
    return f"{m // 60:d}:{m % 60:02d}:{sec:02d}" if m >= 60 else f"{m:d}:{sec:02d}"


def _guarded(reader):
    """The reader's items, its runs of IMU samples as ImuBatch where it gives them so; a parser's
    exception on a damaged log becomes LogError (one line, exit 2)."""
    from service.logreaders import LogError, one_line
    it = iter(reader.items(imu_batches=True))
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except LogError:
            raise
        except (ValueError, KeyError, IndexError, TypeError, AttributeError, OverflowError, EOFError,
                UnicodeDecodeError, MemoryError, RecursionError, OSError) as exc:
            raise LogError(f"{reader.path}: unreadable at {100 * reader.progress():.0f}% of the log "
                           f"({one_line(exc)})") from None
        yield item


IMU_BATCH_MAX = 512
"""The most IMU samples a replay hands the Pipeline at once (a log's run of IMU records between two
other items is usually far shorter)."""


def run_replay(reader, cfg: dict, csv_path: Path | None, ref_max_age_s: float = REF_MAX_AGE_S,
               out_period_s: float = 0.0, progress: bool | None = False) -> ReplayResult:
    """Feed every item of ``reader`` to a fresh Pipeline; write the CSV; return the rows."""
    from mavlink_io.imu_batch import IMU_RECORD, ImuBatch
    from mavlink_io.samples import (FcAttitude, FcEkfStatus, FcFlightState, FcHeartbeat, ImuSample,
                                    PressureSample)
    from service.pipeline import Pipeline

    pipe = Pipeline(cfg)
    link_event = None   # only a telemetry log's link gives LinkEvents: a .bin or .ulg replay never imports it
    if getattr(reader.summary, "kind", None) == "tlog":
        from mavlink_io.link_config import LinkEvent as link_event
    if hasattr(reader, "estimator_status") and reader.estimator_status is None:
        pipe.fc_sends_no_status("the log records no FC estimator status")
    # what the daemon's dispatch hands the Pipeline (service/daemon.py Daemon.dispatch)
    handlers = {ImuSample: pipe.on_imu, PressureSample: pipe.on_pressure, FcAttitude: pipe.on_fc_attitude,
                FcHeartbeat: pipe.on_fc_heartbeat, FcEkfStatus: pipe.on_fc_ekf_status,
                FcFlightState: pipe.on_fc_flight_state}
    res = ReplayResult()
    cnt = {"imu": 0, "imu_with_mag": 0, "pressure": 0, "pressure_with_diff": 0, "pressure_diff_nonzero": 0,
           "attitude": 0, "flight_state": 0, "imu_time_span_s": [math.inf, -math.inf]}
    imu_sources: dict[str, int] = {}
    ref: FcAttitude | None = None
    prog = _Progress(progress)
    tmp = None
    writer = None
    fh = None
    if csv_path is not None:
        tmp = csv_path.with_name(csv_path.name + ".part")
        fh = open(tmp, "w", newline="")
        writer = csv.writer(fh)
        writer.writerow(CSV_COLUMNS)
    next_out_s = -math.inf
    t_wall0 = time.perf_counter()
    t_pipe = 0.0
    perf = time.perf_counter
    last_phase = None
    cols = res.cols
    ident = getattr(reader.summary, "fc_identity", None)
    identity_due = ident is not None and pipe.vehicle.pending   # a log without HEARTBEAT: its own word
    from service.hot_path import batch_of

    def row(sol) -> None:
        """One filter-rate solution into the rows (and the CSV)."""
        nonlocal last_phase, next_out_s
        if sol.phase != last_phase:
            res.phases.append((sol.phase, sol.time_fc_s))
            last_phase = sol.phase
        if sol.time_fc_s < next_out_s:
            return
        next_out_s = sol.time_fc_s + out_period_s if out_period_s > 0 else -math.inf
        row_ref = ref if (ref is not None and abs(sol.time_fc_s - ref.time_fc_s) <= ref_max_age_s) else None
        hdg = sol.heading_rad if (sol.heading_valid and sol.heading_rad is not None) else None
        vals = {
            "roll_deg": _deg(sol.roll_rad), "pitch_deg": _deg(sol.pitch_rad),
            "heading_deg": _deg(hdg) % 360.0 if hdg is not None else math.nan,
            "heading_sigma_deg": _deg(sol.heading_sigma_rad) if hdg is not None else math.nan,
            "azimuth_deg": _deg(sol.azimuth_rad) % 360.0 if sol.azimuth_rad is not None else math.nan,
            "azimuth_sigma_deg": _deg(sol.azimuth_sigma_rad),
            "ref_roll_deg": _deg(row_ref.roll_rad) if row_ref else math.nan,
            "ref_pitch_deg": _deg(row_ref.pitch_rad) if row_ref else math.nan,
            "ref_heading_deg": (_deg(row_ref.yaw_rad) % 360.0) if row_ref else math.nan,
        }
        res.time_s.append(sol.time_fc_s)
        res.phase.append(sol.phase)
        src = sol.heading_source if hdg is not None else "none"
        res.heading_source.append(src)
        res.roll_sigma_deg.append(_deg(sol.roll_sigma_rad))
        res.pitch_sigma_deg.append(_deg(sol.pitch_sigma_rad))
        for k, v in vals.items():
            cols[k].append(v)
        if writer is not None:
            writer.writerow([f"{sol.time_fc_s:.6f}", sol.phase, _fmt(vals["roll_deg"]),
                             _fmt(vals["pitch_deg"]), _fmt(vals["heading_deg"]),
                             _fmt(vals["heading_sigma_deg"]), src, _fmt(vals["azimuth_deg"]),
                             _fmt(vals["azimuth_sigma_deg"]), _fmt(vals["ref_roll_deg"]),
                             _fmt(vals["ref_pitch_deg"]), _fmt(vals["ref_heading_deg"]),
                             *aiding.csv_row(pipe.aiding)])

    pending: list = []
    """The run of IMU samples not fed yet, consecutive and of one source: ImuSample objects (a reader
    that yields them) or IMU_RECORD arrays (the ImuBatch rows of a reader that yields batches). One
    Pipeline.imu_batch_steps per run (the daemon's batch path; the compiled core takes the quiet
    samples in C++), cut at every other item, at a change of source and at IMU_BATCH_MAX samples."""
    run_n = 0
    run_src = None

    def feed_imu() -> None:
        nonlocal t_pipe, run_n
        n_run = run_n
        if type(pending[0]) is ImuSample:
            samples = pending[:]
            batch = batch_of(samples)
            t_fc = [s.time_fc_s for s in samples]
        else:   # rows: on_imu gets an ImuSample built from a row only for the samples it handles
            samples = None
            # rows joined as bytes (np.concatenate of structured arrays costs ~15 us a row)
            rec = pending[0] if len(pending) == 1 else np.frombuffer(
                bytearray().join([r.tobytes() for r in pending]), IMU_RECORD)
            batch = ImuBatch(rec, run_src)
            t_fc = rec["time_fc_s"].tolist()
            span = cnt["imu_time_span_s"]
            lo, hi = span
            for t in t_fc:   # as sample by sample: a NaN time changes neither
                lo, hi = min(lo, t), max(hi, t)
            span[0], span[1] = lo, hi
            cnt["imu_with_mag"] += sum(m == m for m in rec["mag_gauss"][:, 0].tolist())   # NaN: none
        pending.clear()
        run_n = 0
        # events the other items raised since the last sample: on_imu's drain gave them the next
        # sample's time, this batch's first
        before = pipe.drain_events()
        t0 = perf()
        for i, sol in pipe.imu_batch_steps(batch, samples):
            t_pipe += perf() - t0
            if before:
                res.events += [(t_fc[0], *ev) for ev in before]
                before = []
            for ev in pipe.drain_events():
                res.events.append((t_fc[i], *ev))
            if sol is not None:
                row(sol)
            t0 = perf()
        t_pipe += perf() - t0
        res.events += [(t_fc[0], *ev) for ev in before]
        n = cnt["imu"]
        if n // 256 != (n - n_run) // 256:
            prog.update(reader.progress(), t_fc[-1], n)

    def take_rows(b) -> None:
        """An ImuBatch's rows into the run (cut at IMU_BATCH_MAX as sample by sample; feed_imu counts
        their magnetometers and times)."""
        nonlocal run_n, run_src
        rec = b.records
        n = len(rec)
        if not n:
            return
        if pending and (b.source != run_src or type(pending[0]) is ImuSample):
            feed_imu()
        run_src = b.source
        cnt["imu"] += n
        imu_sources[b.source] = imu_sources.get(b.source, 0) + n
        i = 0
        while i < n:
            if run_n >= IMU_BATCH_MAX:
                feed_imu()
            k = min(n - i, IMU_BATCH_MAX - run_n)
            pending.append(rec if k == n else rec[i:i + k])
            run_n += k
            i += k

    try:
        for item in _guarded(reader):
            cls = type(item)
            if cls is ImuBatch and not len(item):
                continue
            if identity_due:
                identity_due = False
                t_rx = float(item.records["time_rx_s"][0]) if cls is ImuBatch else item.time_rx_s
                pipe.on_fc_identity(ident.mav_type, ident.autopilot, ident.params, t_rx, ident.source)
            if cls is ImuBatch:
                take_rows(item)
                continue
            if cls is ImuSample:
                if pending and (item.source != run_src or run_n >= IMU_BATCH_MAX
                                or type(pending[0]) is not ImuSample):
                    feed_imu()
                run_src = item.source
                run_n += 1
                cnt["imu"] += 1
                cnt["imu_with_mag"] += item.mag_gauss is not None
                imu_sources[item.source] = imu_sources.get(item.source, 0) + 1
                span = cnt["imu_time_span_s"]
                span[0] = min(span[0], item.time_fc_s)
                span[1] = max(span[1], item.time_fc_s)
                pending.append(item)
                continue
            if pending:
                feed_imu()
            t0 = perf()   # the Pipeline's time includes its other inputs (FC attitude, pressure, ...)
            if cls is FcAttitude:
                cnt["attitude"] += 1
                ref = item
                pipe.on_fc_attitude(item)
            elif cls is PressureSample:
                cnt["pressure"] += 1
                if item.press_diff_pa is not None:
                    cnt["pressure_with_diff"] += 1
                    cnt["pressure_diff_nonzero"] += item.press_diff_pa != 0.0
                pipe.on_pressure(item)
            elif cls is link_event:
                res.events.append((None, f"link.{item.kind}", item.detail))
                if item.kind == "fc_reboot":
                    pipe.on_fc_reboot()
                    ref = None
            else:
                cnt["flight_state"] += cls is FcFlightState
                fn = handlers.get(cls)
                if fn is not None:
                    fn(item)
            t_pipe += perf() - t0
        if pending:
            feed_imu()
    except BaseException:
        if fh is not None:
            fh.close()
            tmp.unlink(missing_ok=True)
        raise
    finally:
        prog.done()
    if fh is not None:
        fh.close()
        if cnt["imu"] == 0:
            tmp.unlink(missing_ok=True)
        else:
            os.replace(tmp, csv_path)
    res.wall_s = time.perf_counter() - t_wall0
    res.pipeline_s = t_pipe
    res.imu_samples = cnt["imu"]
    res.counts = dict(cnt, imu_sources=imu_sources)
    res.notes = list(reader.summary.notes)
    res.missing = missing_streams(cnt)
    res.counters = pipe.counters
    return res


def missing_streams(cnt: dict) -> list[str]:
    """What the log does not give the estimators, in words."""
    out = []
    if cnt["imu"] == 0:
        out.append("IMU (gyro + accelerometer): none")
    elif cnt["imu_with_mag"] == 0:
        out.append("magnetometer: none (no heading from the magnetic methods)")
    if cnt["pressure"] == 0:
        out.append("barometer: none (no air data)")
    elif cnt["pressure_with_diff"] == 0 or cnt["pressure_diff_nonzero"] == 0:
        out.append("airspeed (differential pressure): none" +
                   (" (logged as exactly 0: no sensor)" if cnt["pressure_with_diff"] else ""))
    if cnt["attitude"] == 0:
        out.append("reference attitude (the FC's ATTITUDE): none (ref_ columns empty)")
    return out


def _rms(a: np.ndarray) -> float:
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a * a))) if a.size else math.nan


def summary(res: ReplayResult) -> dict:
    """The figures of a replay (JSON-ready: units in the keys)."""
    c = res.cols
    roll, pitch, hdg = (np.asarray(c[k], float) for k in ("roll_deg", "pitch_deg", "heading_deg"))
    rr, rp, rh = (np.asarray(c[k], float) for k in ("ref_roll_deg", "ref_pitch_deg", "ref_heading_deg"))
    d_roll = roll - rr
    d_pitch = pitch - rp
    d_hdg = (hdg - rh + 180.0) % 360.0 - 180.0
    t = np.asarray(res.time_s, float)
    span = res.counts.get("imu_time_span_s", [math.nan, math.nan])
    dur = span[1] - span[0] if res.imu_samples > 1 else math.nan
    out = {
        "rows": len(res.time_s),
        "imu_samples": res.imu_samples,
        "imu_rate_hz": (res.imu_samples - 1) / dur if dur and dur > 0 else math.nan,
        "imu_sources": res.counts.get("imu_sources", {}),
        "pressure_samples": res.counts.get("pressure", 0),
        "fc_attitude_samples": res.counts.get("attitude", 0),
        "fc_flight_state_records": res.counts.get("flight_state", 0),
        "log_duration_s": dur,
        "phases": [{"phase": p, "from_time_s": tt} for p, tt in res.phases],
        "roll_rms_diff_deg": _rms(d_roll), "pitch_rms_diff_deg": _rms(d_pitch),
        "heading_rms_diff_deg": _rms(d_hdg),
        # the FC's own yaw as a heading source compared with the FC's yaw says nothing: apart
        "heading_rms_diff_own_deg": _rms(d_hdg[np.array(["fc" not in src.split("+") for src in res.heading_source],
                                                        dtype=bool)]) if t.size else math.nan,
        "heading_sources": {k: int(v) for k, v in zip(*np.unique(np.asarray(res.heading_source, dtype=str),
                                                                return_counts=True))} if t.size else {},
        "roll_compared_rows": int(np.sum(np.isfinite(d_roll))),
        "heading_compared_rows": int(np.sum(np.isfinite(d_hdg))),
        "missing_streams": res.missing,
        "notes": res.notes,
        "events": len(res.events),
        "event_reasons": event_reasons(res.events),
        "magnetometer": magnetometer_timeline(res.events, span[1] if res.imu_samples > 1 else math.nan),
        "imu_rejected": getattr(res.counters, "imu_rejected", 0),
        "imu_rejected_reasons": dict(getattr(res.counters, "reasons", {})),
        "wall_time_s": res.wall_s,
        "samples_per_s": res.imu_samples / res.wall_s if res.wall_s > 0 else math.nan,
        "pipeline_us_per_imu_sample": 1e6 * res.pipeline_s / res.imu_samples if res.imu_samples else math.nan,
        "total_us_per_imu_sample": 1e6 * res.wall_s / res.imu_samples if res.imu_samples else math.nan,
    }
    warnings = []
    rate = out["imu_rate_hz"]
    if rate == rate and rate < LOW_IMU_RATE_HZ:
        warnings.append(f"the IMU is logged at {rate:.1f} Hz (< {LOW_IMU_RATE_HZ:.0f} Hz): too slow for these "
                        "estimators (levelling wants hundreds of still samples per block, strapdown and the "
                        "filters integrate rate samples taken >= 50 Hz apart); the figures below check the "
                        "decoding and the plumbing, they are not an accuracy figure")
    out["warnings"] = warnings
    if t.size:
        inflight = np.isin(np.asarray(res.phase), ["launch", "in-flight"])
        out["roll_rms_diff_in_flight_deg"] = _rms(d_roll[inflight])
        out["pitch_rms_diff_in_flight_deg"] = _rms(d_pitch[inflight])
    return out


def magnetometer_timeline(events: list, end_time_s: float) -> dict | None:
    """The magnetometer's verdicts over the log (the Pipeline's ``magnetometer`` events: usable /
    rejected (reason)): the seconds spent usable and rejected after the first verdict, the log's
    verdict (usable for at least half of that time), its state at the end and the first rejection's
    reason. None when the log gave no verdict (no magnetometer,
    or too short to judge it): a reader then says so from ``missing_streams``."""
    verdicts = [(t, str(d)) for t, kind, d in events if kind == "magnetometer" and t is not None]
    if not verdicts:
        return None
    usable_s = rejected_s = 0.0
    for (t0, d0), (t1, _) in zip(verdicts, verdicts[1:] + [(end_time_s, "")]):
        dt = max(0.0, t1 - t0) if t1 == t1 else 0.0
        if d0 == "usable":
            usable_s += dt
        else:
            rejected_s += dt
    rejections = [(t, d) for t, d in verdicts if d != "usable"]
    last_t, last_d = verdicts[-1]
    judged_s = usable_s + rejected_s
    share = usable_s / judged_s if judged_s > 0 else (1.0 if last_d == "usable" else 0.0)
    # the log's verdict: usable for most of the time it was judged (a rejection that ended early
    # does not make a log's magnetometer unusable, nor a late recovery a rejected one usable)
    return {"usable": share >= 0.5, "usable_share": share, "usable_at_end": last_d == "usable",
            "since_s": last_t, "usable_s": usable_s, "rejected_s": rejected_s,
            "rejections": len(rejections),
            "reason": " ".join(rejections[0][1].split()) if rejections else "",
            "first_rejected_s": rejections[0][0] if rejections else None}


MAX_REASON_LINES = 25
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?")


def event_reasons(events: list) -> list[dict]:
    """The events grouped by kind and reason (numbers aside), in order of first appearance: one
    entry per reason with its count, the first occurrence's text and time, and how many differ."""
    groups: dict[tuple, dict] = {}
    for t, kind, detail in events:
        detail = " ".join(str(detail).split())
        key = (kind, _NUMBER.sub("#", detail))
        g = groups.get(key)
        if g is None:
            groups[key] = g = {"kind": kind, "reason": detail, "first_time_s": t, "count": 0, "_texts": set()}
        g["count"] += 1
        if len(g["_texts"]) < 2:
            g["_texts"].add(detail)
    out = []
    for g in groups.values():
        g["variants"] = len(g.pop("_texts"))
        out.append(g)
    return out


def print_summary(s: dict, res: ReplayResult, notes: list[str], log: Path, out=None) -> None:
    out = out if out is not None else sys.stdout
    p = lambda *a: print(*a, file=out)  # noqa: E731
    p(f"replay of {log}")
    for n in notes + s["notes"]:
        p(f"  note: {n}")
    src = ", ".join(f"{k} {v}" for k, v in s["imu_sources"].items()) or "none"
    p(f"  streams: IMU {s['imu_samples']} samples ({src}) at {s['imu_rate_hz']:.1f} Hz over "
      f"{s['log_duration_s']:.1f} s; pressure {s['pressure_samples']}; FC attitude {s['fc_attitude_samples']}; "
      f"FC armed/landed state {s['fc_flight_state_records']}")
    for m in s["missing_streams"]:
        p(f"  missing: {m}")
    ph = ", ".join(f"{x['phase']} at {x['from_time_s']:.2f} s" for x in s["phases"]) or "none"
    p(f"  phases: {ph}")
    ph_log = ", ".join(f"{t:.2f} s" for t in s.get("log_takeoff_times_s", []))
    if ph_log:
        p(f"  the log's own take-off (its landed -> in air, not used by the estimators): {ph_log}")
    groups = event_reasons(res.events)
    if groups:
        p(f"  events ({len(res.events)}), each reason once (first time; count):")
        for g in groups[:MAX_REASON_LINES]:
            t = "" if g["first_time_s"] is None else f" at {g['first_time_s']:.2f} s"
            vary = ", values vary: the first shown" if g["variants"] > 1 else ""
            p(f"    {g['kind']}: {g['reason']}{t} x{g['count']}{vary}")
        if len(groups) > MAX_REASON_LINES:
            p(f"    ... {len(groups) - MAX_REASON_LINES} more reasons (--json lists them all)")
    mag = s.get("magnetometer")
    if mag:
        state = "usable" if mag["usable_at_end"] else "rejected"
        p(f"  magnetometer: usable {mag['usable_s']:.1f} s, rejected {mag['rejected_s']:.1f} s "
          f"({mag['rejections']} rejection(s)); {state} at the end (since {mag['since_s']:.2f} s)")
    if s["imu_rejected"]:
        p(f"  IMU samples rejected by the pipeline: {s['imu_rejected']} {s['imu_rejected_reasons']}")
    for w in s["warnings"]:
        p(f"  warning: {w}")
    p(f"  rows: {s['rows']}; compared with the FC: roll/pitch {s['roll_compared_rows']} rows, heading "
      f"{s['heading_compared_rows']} rows")
    fmt = lambda v: "-" if not v == v else f"{v:.3f} deg"  # noqa: E731
    p(f"  RMS difference vs the log's FC attitude: roll {fmt(s['roll_rms_diff_deg'])}, pitch "
      f"{fmt(s['pitch_rms_diff_deg'])}, heading {fmt(s['heading_rms_diff_deg'])}")
    if s["heading_sources"]:
        p("  heading source by rows: " + ", ".join(f"{k} {v}" for k, v in sorted(s["heading_sources"].items())))
    if any("fc" in k.split("+") for k in s["heading_sources"]):
        p(f"    heading vs the FC without the rows whose heading uses the FC's own yaw: "
          f"{fmt(s['heading_rms_diff_own_deg'])}")
    if s.get("roll_rms_diff_in_flight_deg") == s.get("roll_rms_diff_in_flight_deg"):
        p(f"    after launch only: roll {fmt(s['roll_rms_diff_in_flight_deg'])}, pitch "
          f"{fmt(s['pitch_rms_diff_in_flight_deg'])}")
    p(f"  speed: {s['wall_time_s']:.2f} s wall, {s['samples_per_s']:,.0f} IMU samples/s; "
      f"{s['pipeline_us_per_imu_sample']:.1f} us/sample in the Pipeline, "
      f"{s['total_us_per_imu_sample']:.1f} us/sample with log decoding")


# --- plot --------------------------------------------------------------------------------------

PLOT_SIGMA_CAP_DEG = 30.0
"""1-sigma bands are drawn up to this (a sigma of 200 deg says "unknown": it would flatten the traces)."""
PLOT_GAP_FACTOR = 5.0
"""A line is broken where consecutive rows are further apart than this x the median row interval."""
_SOURCE_COLOURS = {"azimuth": "C2", "synthetic_ahrs": "C0", "heading_filter": "C4", "coast": "C1", "fc": "C3"}


def _breaks(t: np.ndarray, y: np.ndarray, wrap_deg: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(t, y) with NaN inserted at time gaps and, for a wrapped angle, where it crosses 0/360, so
    that a line plot joins neither a gap nor a wrap."""
    if t.size < 2:
        return t, y
    dt = np.diff(t)
    pos = dt[dt > 0]
    gap = PLOT_GAP_FACTOR * (np.median(pos) if pos.size else 1.0)
    cut = dt > gap
    if wrap_deg is not None:
        with np.errstate(invalid="ignore"):
            cut |= np.abs(np.diff(y)) > wrap_deg / 2.0
    idx = np.nonzero(cut)[0] + 1
    return np.insert(t, idx, np.nan), np.insert(y, idx, np.nan)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index runs where ``mask`` holds."""
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    d = np.diff(m)
    return list(zip(np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]))


def plot(res: ReplayResult, path: Path, title: str) -> None:
    """Roll, pitch, heading (ours with the 1-sigma band capped at PLOT_SIGMA_CAP_DEG, the log's
    reference) and the error; heading coloured by its source, the stretches whose heading uses the
    FC's own yaw shaded (their zero error is the FC compared with itself); lines broken at gaps and
    at the 0/360 wrap."""
    try:
        import matplotlib
    except ImportError:
        raise ReplayError("--plot needs matplotlib: pip install matplotlib") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(res.time_s, float)
    c = {k: np.asarray(v, float) for k, v in res.cols.items()}
    src = np.asarray(res.heading_source, dtype=str)
    step = max(1, t.size // 20000)  # a plot needs no more points than pixels
    t, src = t[::step], src[::step]
    c = {k: v[::step] for k, v in c.items()}
    cap = lambda sg: np.minimum(sg, PLOT_SIGMA_CAP_DEG)  # noqa: E731
    sig = {"roll": cap(np.asarray(res.roll_sigma_deg, float)[::step]),
           "pitch": cap(np.asarray(res.pitch_sigma_deg, float)[::step]),
           "heading": cap(c["heading_sigma_deg"])}
    uses_fc = np.array(["fc" in x.split("+") for x in src], dtype=bool)
    fig, axes = plt.subplots(3, 2, figsize=(14, 9), sharex=True, squeeze=False)
    for row, name in enumerate(("roll", "pitch", "heading")):
        ax, ax_e = axes[row]
        y, r = c[f"{name}_deg"], c[f"ref_{name}_deg"]
        wrap = 360.0 if name == "heading" else None
        ax.plot(*_breaks(t, r, wrap), color="0.4", lw=1.0, label="log's FC estimate")
        err = y - r
        if name == "heading":
            err = (err + 180.0) % 360.0 - 180.0
            for s_name in sorted(set(src) - {"none"}):
                parts = s_name.split("+")
                colour = _SOURCE_COLOURS.get(parts[0], "C5") if len(parts) == 1 else "C6"
                ys = np.where(src == s_name, y, np.nan)
                ax.plot(*_breaks(t, ys, wrap), color=colour, lw=1.0, label=f"azimuthd: {s_name}")
            for a, b in _runs(uses_fc):
                for a_x in (ax, ax_e):
                    a_x.axvspan(t[a], t[min(b, t.size - 1)], color="C3", alpha=0.08, lw=0,
                                label="heading uses the FC's own yaw" if (a_x is ax_e and a == _runs(uses_fc)[0][0])
                                else None)
        else:
            ax.plot(*_breaks(t, y), color="C0", lw=1.0, label="azimuthd")
        ok = np.isfinite(y) & np.isfinite(sig[name])
        if ok.any():
            lo, hi = y - sig[name], y + sig[name]
            ax.fill_between(t, lo, hi, where=ok, color="C0", alpha=0.2, lw=0,
                            label=f"azimuthd 1-sigma (capped at {PLOT_SIGMA_CAP_DEG:g} deg)")
            ax_e.fill_between(t, -sig[name], sig[name], where=ok, color="C0", alpha=0.2, lw=0, label="+-1-sigma")
        ax_e.plot(*_breaks(t, err), color="k", lw=0.8, label="azimuthd - FC")
        ax_e.axhline(0.0, color="0.6", lw=0.5)
        ax.set_ylabel(f"{name} (deg)")
        ax_e.set_ylabel(f"{name} error (deg)")
        if name == "heading":
            ax.set_ylim(0.0, 360.0)
            ax.set_yticks([0, 90, 180, 270, 360])
        if not np.isfinite(y).any():
            ax.text(0.5, 0.5, f"no {name} from azimuthd", transform=ax.transAxes, ha="center", color="C0")
        if not np.isfinite(r).any():
            ax.text(0.5, 0.4, "no reference in the log", transform=ax.transAxes, ha="center", color="0.4")
        for a in (ax, ax_e):
            a.grid(True, lw=0.3)
        if row in (0, 2):
            ax.legend(loc="upper right", fontsize=7)
            ax_e.legend(loc="upper right", fontsize=7)
    for p, t0 in res.phases:
        if p in ("launch", "in-flight"):
            for a in axes.ravel():
                a.axvline(t0, color="k", lw=0.6, ls="--")
    axes[2, 0].set_xlabel("FC time (s)")
    axes[2, 1].set_xlabel("FC time (s)")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# --- command line ------------------------------------------------------------------------------

def json_safe(v):
    """A result for json.dumps: NaN/inf (not JSON) become null, tuples lists (benches use it too)."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [json_safe(x) for x in v]
    return v


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="azimuthd replay",
        description="Run a recorded flight log (.tlog MAVLink telemetry, .bin ArduPilot DataFlash, .ulg PX4 "
                    "ULog) through the daemon's estimators, offline, and compare with the log's own attitude.")
    ap.add_argument("log", metavar="LOG", help="the flight log (.tlog, .bin, .ulg)")
    ap.add_argument("--config", metavar="FILE", help="daemon config (TOML); default: built from the log")
    ap.add_argument("--site", metavar="LAT,LON[,ALT]",
                    help="launch site (deg, deg, m); overrides the config's and the log's")
    ap.add_argument("--output", metavar="OUT.csv", help="CSV, one row per output sample")
    ap.add_argument("--plot", metavar="OUT.png", help="plot of roll/pitch/heading vs the log's attitude (PNG)")
    ap.add_argument("--json", metavar="PATH", help="write the summary figures as JSON")
    ap.add_argument("--rate", type=float, metavar="HZ", default=0.0,
                    help="CSV/plot rows at most this often in FC time (the estimators still see every "
                         "sample); default 0: one row per solution the Pipeline outputs")
    ap.add_argument("--ref-max-age", type=float, metavar="S", default=REF_MAX_AGE_S,
                    help=f"oldest FC attitude used as the reference of a row (default {REF_MAX_AGE_S} s)")
    ap.add_argument("--exclude-fc-yaw", action="store_true",
                    help="never use the FC's own yaw as a heading source (heading.use_fc_yaw = false): "
                         "our heading alone, compared with the FC's")
    prog = ap.add_mutually_exclusive_group()
    prog.add_argument("--progress", action="store_true",
                      help="progress with ETA on stderr even when it is not a terminal")
    prog.add_argument("--no-progress", action="store_true", help="no progress on stderr")
    try:
        args = ap.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    from service.logreaders import LogError, one_line, open_log
    try:
        if args.rate < 0 or not math.isfinite(args.rate):
            raise ReplayError(f"--rate: must be >= 0 Hz, got {args.rate}")
        if not args.ref_max_age > 0:
            raise ReplayError(f"--ref-max-age: must be > 0 s, got {args.ref_max_age}")
        if args.plot and Path(args.plot).suffix.lower() != ".png":
            raise ReplayError(f"--plot: the plot is a PNG file (OUT.png), got {args.plot!r}")
        for opt in (args.output, args.plot, args.json):
            if opt and not Path(opt).resolve().parent.is_dir():
                raise ReplayError(f"{opt}: directory does not exist")
        reader = open_log(args.log)
        cfg, notes = build_config(args, reader)
        if hasattr(reader, "imu_gap_s"):
            reader.imu_gap_s = cfg["mavlink"]["imu_gap_s"]
        res = run_replay(reader, cfg, Path(args.output) if args.output else None, args.ref_max_age,
                         1.0 / args.rate if args.rate > 0 else 0.0,
                         progress=True if args.progress else (None if not args.no_progress else False))
        if res.imu_samples == 0:
            raise ReplayError(f"{args.log}: no IMU samples in this log (missing: "
                              f"{'; '.join(res.missing) or 'IMU'})")
        s = summary(res)
        if args.plot:
            plot(res, Path(args.plot), f"azimuthd replay: {Path(args.log).name}")
    except (LogError, ReplayError) as exc:
        print(f"azimuthd replay: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"azimuthd replay: {exc.filename or args.log}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - a bug of ours: one line for the user, not a traceback
        tb = exc.__traceback__
        while tb is not None and tb.tb_next is not None:
            tb = tb.tb_next
        where = f" at {Path(tb.tb_frame.f_code.co_filename).name}:{tb.tb_lineno}" if tb is not None else ""
        print(f"azimuthd replay: internal error{where} ({one_line(exc)}); please report it with the log",
              file=sys.stderr)
        return 1
    s["config_notes"] = notes
    try:
        s["log_takeoff_times_s"] = reader.takeoff_times_s()
    except LogError:
        s["log_takeoff_times_s"] = []
    print_summary(s, res, notes, Path(args.log))
    if args.output:
        print(f"  csv: {args.output}")
    if args.plot:
        print(f"  plot: {args.plot}")
    if args.json:
        Path(args.json).write_text(json.dumps(json_safe(s), indent=2) + "\n")
        print(f"  json: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
