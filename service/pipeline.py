"""The estimator wiring: typed samples in, NavSolution out. No sockets, no clocks, no files.

The daemon (service/daemon.py) and the offline replay feed the same Pipeline, so what a user
replays is what flies. Each ``on_*`` method takes one decoded sample; ``on_imu`` returns the
NavSolution for that sample (None while there is nothing to say).

Per IMU sample (sensor axes are rotated to body axes with the configured mount):
- phases (service/phases.py): levelling and gyro bias at rest, launch detection;
- roll/pitch: the polar-capable attitude filter (METHODS.md C, estimators/polar_attitude) once
  it has levelled; before that the levelled attitude, then the coning-correct strapdown of the
  bias-corrected gyros from the levelled start (estimators/strapdown);
- heading sources, each with its sigma:
    ``azimuth``        method A, the in-flight azimuth (estimators/azimuth), after launch;
    ``synthetic_ahrs`` method B (estimators/synthetic_ahrs), variant b1 or b2 from the config;
    ``heading_filter`` method C's heading filter (estimators/polar_heading), magnetometer;
    ``fc``             the flight controller's own yaw while method B's reference health
                       says the FC is trusted;
- one heading from them by gated inverse-variance fusion with blended source changes
  (service/heading_arbitration: the rule is in its docstring); it never jumps silently: every
  source change is an event with the jump it absorbed.
Magnetometer-based sources (B and C) form one correlation group: only the better one is fused,
and neither while method A has a solution (A solves the magnetometer distortions, they do not).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from dataclasses import replace as dc_replace

from estimators.azimuth import azimuth_output
from estimators.azimuth import (AzimuthOutput, AzimuthParams, AzimuthState, azimuth_apply_solve, azimuth_init,
                                azimuth_launch, azimuth_prelaunch_step, azimuth_step)
from estimators.declination import (DeclinationParams, RestState, estimate_declination,
                                    rest_accumulate)
from estimators.geomag import EarthField, earth_field, field_from_vector
from estimators.levelling import LevellingParams, LevellingState
from estimators.mag_deviation import (DeviationParams, DeviationState, deviation_coverage, deviation_init,
                                      residual_sigma_gauss)
from estimators.mag_error_kf import Kf1State
from estimators.mag_disturbance import MagDisturbanceState, mag_disturbance_params_for_field
from estimators.mag_usability import MagUsabilityState, mag_usability_params_for_field
from estimators.polar_attitude import PolarAttitudeParams
from estimators.polar_heading import HeadingInputs, PolarHeadingParams, vertical_rate_sigma_for_site
from estimators.rotations import (dcm_from_quat, euler_from_quat, quat_conj, quat_from_euler,
                                  quat_mul, wrap_2pi, wrap_pi)
from estimators.output_propagation import OutputState, output_reset
from estimators.zero_rate import ZeroRateParams, ZeroRateState, rest_step
from estimators.strapdown import StrapdownParams, StrapdownState, strapdown_init
from estimators import core as core_facade
from estimators.synthetic_ahrs import (AirEvent, FcAttitudeEvent, FcStatusEvent, HeadingEvent, ImuEvent,
                                       SyntheticAhrsOutput, SyntheticAhrsParams, synthetic_ahrs_forget_fc_yaw,
                                       synthetic_ahrs_init, synthetic_ahrs_output, synthetic_ahrs_step,
                                       synthetic_ahrs_unseen)
from mavlink_io.samples import FcAttitude, FcEkfStatus, FcFlightState, FcHeartbeat, ImuSample, PressureSample
from service.core_backend import select as select_core
from service.hot_path import GroundState as GroundStateReference
from service.hot_path import (SamplePack, azimuth_for_solver, azimuth_held_step, azimuth_output_held,
                              azimuth_take_back, batch_steps, ground_field, ground_step, ground_take_back,
                              sample_field, sample_step)
from service.input_checks import InputCheckParams
from service.heading_arbitration import ArbitrationParams, ArbitrationState, SourceReading
from service.heading_sources import (AzimuthCheck, SyntheticAhrsHealth, azimuth_source, deviation_record, fc_source,
                                     heading_filter_reading, heading_filter_source, superseded,
                                     synthetic_ahrs_source)
from service.phases import (IN_FLIGHT, LAUNCH, PRE_LAUNCH, FlightEvidence, InFlightParams, PhaseParams,
                            PhaseState)
from mavlink_io.navsolution import NavSolution
from mavlink_io.imu_batch import ImuBatch
from service.vehicle_type import AUTO as AUTO_VEHICLE, VehicleResolver

log = logging.getLogger("azimuthd.pipeline")

DEVIATION_PERIOD_S = 0.1
"""Interval of method D's RLS updates during a calibration manoeuvre (s)."""
DEVIATION_MAX_REF_SIGMA_RAD = math.radians(2.0)
"""The heading a calibration manoeuvre is referred to must be at least this good."""

B1_HEADING_PERIOD_S = 0.1
"""How often variant B1 is handed the heading of the other sources (s)."""

FC_TILT_MAX_AGE_S = 0.2
"""The FC's roll/pitch older than this (FC time, s) does not level C's magnetometer."""
# the backend's steps that Pipeline._filter_chain_core takes in one core call, and the core's own
_FILTER_CHAIN_CALLS = (("polar_attitude_step", "polar_attitude_step"),
                       ("polar_attitude_estimate", "polar_attitude_estimate"),
                       ("attitude_zero_rate_update", "attitude_zero_rate_update"),
                       ("mag_disturbance_step", "mag_disturbance_step"),
                       ("mag_usability_step", "mag_usability_step"), ("mag_usability_stale", "mag_usability_stale"),
                       ("deviation_coverage", "deviation_coverage"), ("deviation_corrected_mag", "corrected_mag"),
                       ("polar_heading_step", "polar_heading_step"),
                       ("polar_heading_estimate", "polar_heading_estimate"),
                       ("heading_zero_rate_update", "heading_zero_rate_update"))

AIR_EVIDENCE_MAX_AGE_S = 1.0
"""Air data older than this (FC time, s) is no evidence for the started-in-flight rule."""
MULTICOPTER_MANOEUVRE_SPEED_M_S = PolarAttitudeParams.manoeuvre_speed_m_s
"""A multicopter's bound on its turn acceleration (m/s): C's built-in 25 m/s, not its cruise speed:
a multicopter also accelerates sideways, which w x [V, 0, 0] does not see. Measured on
arducopter-flight.tlog (the only real multicopter flight with the FC's attitude): 10 m/s (ArduCopter's
WPNAV_SPEED) gave roll / pitch 36.3 / 14.2 deg RMS, 25 m/s 6.0 / 6.0."""
MANOEUVRE_SPEED_STEP_M_S = 1.0
"""C's attitude filter takes a new manoeuvre speed when it moved by this much (m/s)."""
FIXED_WING = 1
"""MAV_TYPE_FIXED_WING."""
MAV_STATE_STANDBY, MAV_STATE_ACTIVE = 3, 4


_NAV_FIELDS = tuple(NavSolution.__dataclass_fields__)


def _nav_replace(sol: NavSolution, **changes) -> NavSolution:
    """dataclasses.replace for a NavSolution without re-running its __init__ (it has no
    __post_init__: the same fields, the unchanged ones the very same objects), ~3x faster."""
    new = object.__new__(NavSolution)
    for f in _NAV_FIELDS:
        object.__setattr__(new, f, changes[f] if f in changes else getattr(sol, f))
    return new


def decimal_year_now() -> float:
    """Today (00:00 UTC) as a decimal year: the date for the geomagnetic model when neither the
    config nor the log gives one. A day, not the second: the field's secular change in a day is
    ~0.1 nT (1e-6 of it), and two Pipelines built on one day (a replay run twice, the parity
    tests' reference and core runs) then see the same Earth; with the second they differed by
    1e-9..1e-8 relative and a replay of a log without a date did not reproduce itself."""
    import datetime as dt
    now = dt.datetime.now(dt.timezone.utc)
    start = dt.datetime(now.year, 1, 1, tzinfo=dt.timezone.utc)
    end = dt.datetime(now.year + 1, 1, 1, tzinfo=dt.timezone.utc)
    today = dt.datetime(now.year, now.month, now.day, tzinfo=dt.timezone.utc)
    return now.year + (today - start) / (end - start)


def site_field(cfg: dict) -> EarthField:
    """The Earth field for the flight area: configured vector, else the WMM at the site and date."""
    site = cfg["site"]
    if site["earth_field_ned_gauss"] is not None:
        return field_from_vector(np.array(site["earth_field_ned_gauss"], float))
    year = site["decimal_year"] if site["decimal_year"] is not None else decimal_year_now()
    return earth_field(site["lat_deg"], site["lon_deg"], site["alt_m"], year)


@dataclass
class PipelineCounters:
    imu_samples: int = 0
    imu_rejected: int = 0
    pressure_samples: int = 0
    fc_attitude_samples: int = 0
    strapdown_gaps: int = 0
    reasons: dict = field(default_factory=dict)

    def reject(self, reason: str) -> None:
        self.imu_rejected += 1
        self.reasons[reason] = self.reasons.get(reason, 0) + 1


class Pipeline:
    """Holds the estimator states; every update is a pure step on them."""

    # the per-sample fields: ONE object (``_hs``) that on_imu and the core's hot path
    # (service/hot_path.py, on_imu_batch) both read and write
    last_time_fc_s = sample_field("last_time_fc_s", "The last used IMU sample's FC time (None before one).")
    _last_rx_s = sample_field("last_rx_s")
    _filter_due_s = sample_field("filter_due_s")
    _acc_gyro = sample_field("acc_gyro")
    _acc_accel = sample_field("acc_accel")
    _acc_n = sample_field("acc_n")
    _acc_mag = sample_field("acc_mag")
    _out = sample_field("out")
    _out_bias_body_rad_s = sample_field("out_bias_body_rad_s")
    _out_rx_s = sample_field("out_rx_s")
    _out_gyro_s = sample_field("out_gyro_s")
    # the ground state: method E's rest data (service/hot_path.py GroundState, or the core's, which also
    # holds method A's delay line on the ground)
    rest = ground_field("rest", "Rest data of consecutive still blocks (what method E uses at launch).")
    _rest_candidate = ground_field("rest_candidate")
    _hot_bound = None
    """The bound hot path's holder (service/hot_path.py _bound), made at the first quiet sample."""

    def __init__(self, cfg: dict, kf1_learn: Kf1State | None = None, kf1_applied: Kf1State | None = None,
                 solver=None, deviation: DeviationState | None = None):
        """``solver``: where method A's re-solves run (service/solver.py); None = inline, inside
        ``on_imu`` (deterministic: replay and tests)."""
        self.cfg = cfg
        imu, launch, heading = cfg["imu"], cfg["launch"], cfg["heading"]
        self.gyro_bias_sigma_rad_s = math.radians(imu["gyro_bias_sigma_deg_s"])
        self.in_flight_start_detect = launch["in_flight_start_detect"]
        # levelling: 20 samples is the statistics' floor (1 s at 20 Hz); the block length is still_seconds
        mount = quat_from_euler(*(math.radians(imu[k]) for k in ("mount_roll_deg", "mount_pitch_deg", "mount_yaw_deg")))
        self.phase_params = PhaseParams(still_seconds=imu["still_seconds"],
                                        levelling=LevellingParams(min_samples=20,
                                                                  accel_bias_sigma_m_s2=imu["accel_bias_sigma_m_s2"]),
                                        detect_accel_m_s2=launch["detect_accel_m_s2"],
                                        detect_hold_s=launch["detect_hold_s"],
                                        boost_window_s=launch["boost_window_s"],
                                        vehicle=None if launch["vehicle"] == AUTO_VEHICLE else launch["vehicle"],
                                        forward_sensor=tuple(dcm_from_quat(mount)[0, :]),  # body x in sensor axes
                                        detect_started_in_flight=self.in_flight_start_detect,
                                        in_flight=InFlightParams(airspeed_m_s=launch["in_flight_airspeed_m_s"],
                                                                 alt_rate_m_s=launch["in_flight_alt_rate_m_s"]))
        self.vehicle = VehicleResolver(launch["vehicle"])
        """The take-off model: configured, or "auto" from the FC's HEARTBEAT (service/vehicle_type.py)."""
        self.strapdown_params = StrapdownParams(max_dt_s=cfg["mavlink"]["imu_gap_s"])
        self.core = select_core()
        """The compiled core or the Python reference for the ported parts (service/core_backend.py)."""
        self.filter_chain_core = core_facade.FILTER_CHAIN_AVAILABLE and all(
            getattr(self.core, k) is getattr(core_facade, f) for k, f in _FILTER_CHAIN_CALLS)
        """Method C's filter step runs as one core call (``_filter_chain``): every step it takes is the
        core's in this backend (one replaced, e.g. a test's recorder, or the reference: the Python chain)."""
        self.solution_core = core_facade.SOLUTION_AVAILABLE and all(
            getattr(self.core, k) is getattr(core_facade, k) for k in ("polar_attitude_estimate",
                                                                      "polar_heading_estimate"))
        """The filter step's solution numbers (roll/pitch, sigmas, heading rate, C's heading) come from
        one core call on the held filters (``_solution_attitude``); else the reference's reads."""
        self._hs = self.core.sample_state()
        """The per-sample fields (service/hot_path.py): the core's object, or the reference's."""
        self._ground = self.core.ground_state()
        """The ground state (service/hot_path.py): the core's object, or the reference's."""
        self._ground_core = not isinstance(self._ground, GroundStateReference)
        """The ground path runs in the core (_step_azimuth's pre-launch branch: service/hot_path.ground_step)."""
        self._ground_a = False
        """Method A's delay line and levelling live in the core's ground state (``azimuth`` takes them back)."""
        # q_body_from_sensor: the sensor axes' attitude in the body frame (configured mount)
        self.q_body_from_sensor = quat_from_euler(math.radians(imu["mount_roll_deg"]),
                                                  math.radians(imu["mount_pitch_deg"]),
                                                  math.radians(imu["mount_yaw_deg"]))
        self.q_sensor_from_body = quat_conj(self.q_body_from_sensor)
        self.C_body_from_sensor = dcm_from_quat(self.q_body_from_sensor)

        # the Earth field and its declination for every magnetic method
        self.field = site_field(cfg)
        dec_sigma = self.field.declination_sigma_rad
        self.declination_sigma_rad = dec_sigma if math.isfinite(dec_sigma) else 0.0

        # method E: declination from Earth rate at rest, when the gyros can see it (else the WMM's)
        self.declination_rad = self.field.declination_rad
        self.rest = RestState()
        self._rest_candidate = RestState()
        self.declination_result = None

        # method D: deviation coefficients, fitted while [deviation] calibrate is on (a calibration
        # manoeuvre under a trusted heading), applied to C's magnetometer once they cover enough
        dev = cfg["deviation"]
        self.deviation_params = DeviationParams()
        self.deviation = deviation
        self.deviation_calibrate = dev["calibrate"]
        if self.deviation_calibrate and self.deviation is None:
            self.deviation = deviation_init(self.deviation_params)
        self.deviation_min_coverage = dev["min_coverage"]
        self.deviation_apply = dev["apply"]
        self._deviation_in_use: bool | None = None
        self._deviation_hard_iron_changed = False
        """The magnetometer's hard iron was re-learnt (estimators/mag_disturbance: a magnet attached)
        since D's coefficients were learnt: their constant terms A_i are the old hard iron."""
        self._deviation_last_s = -math.inf
        self._deviation_coverage_reported = 0.0

        # method A
        self.azimuth_params = AzimuthParams(
            e_ned_gauss=self.field.e_ned_gauss, launch_case=launch["case"],
            distortion_model=cfg["azimuth"]["distortion_model"], C_body_from_sensor=self.C_body_from_sensor,
            levelling=self.phase_params.levelling, strapdown=self.strapdown_params,
            # the delay line must outlast the take-off detector's latency (the runway roll's hold)
            prelaunch_buffer_s=max(0.5, self.phase_params.runway_hold_s, self.phase_params.liftoff_hold_s)
            + 2.0 * self.phase_params.filter_tau_s,
            gyro_bias_sigma_rad_s=self.gyro_bias_sigma_rad_s, field_model_sigma_rad=self.declination_sigma_rad)
        # the step never solves by itself: on_imu hands snapshots to the solver on this schedule
        self.solve_period_s = (self.azimuth_params.resolve_period_s, self.azimuth_params.resolve_period_unsolved_s)
        self.azimuth_params = dc_replace(self.azimuth_params, resolve_period_s=math.inf,
                                         resolve_period_unsolved_s=math.inf)
        from service.solver import InlineSolver
        self.solver = solver if solver is not None else InlineSolver()
        self._next_solve_s = -math.inf
        self._azimuth_held = None
        """Method A's core AzimuthRun while its state lives in the core (service/hot_path.py):
        ``azimuth`` takes it back when read or set."""
        self._a_pack = SamplePack()
        """Method A's stored samples as rows (service/hot_path.py SamplePack): what the solver gets."""
        self.azimuth = azimuth_init(self.azimuth_params)
        self._azimuth_out: AzimuthOutput | None = None
        self._azimuth_out_due: tuple | None = None
        """(AzimuthState, time) of A's last step by the hot path: its output, built when read (None for
        the state: the one held in the core, ``_azimuth_held``)."""
        self._azimuth_status = ""

        # method B
        self.ahrs_params = SyntheticAhrsParams(variant=cfg["ahrs"]["variant"],
                                               C_body_from_sensor=self.C_body_from_sensor,
                                               field_nav_gauss=self.field.e_ned_gauss,
                                               fc_sigma_yaw_rad=math.radians(heading["fc_yaw_sigma_deg"]),
                                               field_model_sigma_rad=self.declination_sigma_rad,
                                               use_fc_yaw=heading.get("use_fc_yaw", True))
        self.ahrs = synthetic_ahrs_init(self.ahrs_params, kf1_learn=kf1_learn, kf1_applied=kf1_applied)
        self._kf1_learn_start = kf1_learn
        """Where this flight's KF1 learning began: what it goes back to when the FC's yaw is excluded."""
        self.ahrs_out: SyntheticAhrsOutput | None = None
        self._ahrs_trusted: bool | None = None

        # method C
        # holes up to imu_gap_s are bridged on the rates around them (as the strapdown does); a
        # longer gap is an interval not seen (the link reports it as a time_gap); a filter-rate
        # sample is the mean over its filter period, a longer interval (a slow IMU stream) is bridged
        # the accelerometer bias prior is the configured one; the speed that bounds the centripetal
        # acceleration in turns is the measured airspeed, else the vehicle's (``_manoeuvre_speed_m_s``)
        self.manoeuvre_speed_cfg_m_s = heading["manoeuvre_speed_m_s"]
        self.cruise_speed_m_s = heading["cruise_speed_m_s"]
        self.polar_att_params = PolarAttitudeParams(
            max_dt_s=cfg["mavlink"]["imu_gap_s"],
            sample_span_max_s=max(PolarAttitudeParams.sample_span_max_s, 1.0 / cfg["heading"]["filter_rate_hz"]),
            accel_bias_sigma_m_s2=imu["accel_bias_sigma_m_s2"], manoeuvre_speed_m_s=self._manoeuvre_speed_m_s(None))
        self.polar_att = self.core.polar_attitude_init(self.polar_att_params)
        lat = cfg["site"]["lat_deg"]
        vr_sigma = (vertical_rate_sigma_for_site(math.radians(lat), heading["cruise_speed_m_s"])
                    if lat is not None else PolarHeadingParams().vertical_rate_sigma_rad_s)
        self.polar_hdg_params = PolarHeadingParams(min_horizontal_field_gauss=heading["min_horizontal_field_gauss"],
                                                   vertical_rate_sigma_rad_s=vr_sigma,
                                                   uncalibrated_hard_iron_gauss=heading["uncalibrated_hard_iron_gauss"],
                                                   uncalibrated_soft_iron=heading["uncalibrated_soft_iron"],
                                                   mag_heading_floor_rad=math.radians(heading["mag_heading_floor_deg"]))
        self.polar_hdg = self.core.polar_heading_init(params=self.polar_hdg_params)
        self._hdg_available: bool | None = None
        # at rest, the mean gyro rate measures C's gyro biases (estimators/zero_rate)
        self.zero_rate_params = ZeroRateParams()
        self.zero_rate = ZeroRateState()

        # is the magnetometer fit for a heading at all (estimators/mag_usability): B and C get no
        # magnetometer while it is not, and coast on the gyros with a growing sigma
        self.mag_usability_params = mag_usability_params_for_field(self.field.e_ned_gauss)
        self.mag_usability = MagUsabilityState()
        # magnetic disturbances in motion (estimators/mag_disturbance): the hard iron learnt (and
        # re-learnt when a magnet is attached), the field checked against the recent undisturbed one
        self.mag_dist_params = mag_disturbance_params_for_field(
            self.field.e_ned_gauss, hard_iron_prior_sigma_gauss=max(heading["uncalibrated_hard_iron_gauss"], 1e-4))
        self.mag_dist = MagDisturbanceState()
        self.mag_status = "no magnetometer sample yet"
        """'usable', or why not ('rejected: field norm 0.870 G vs ...'): published on health."""

        # arbitration
        self.arb_params = ArbitrationParams()
        self.arb = ArbitrationState()
        self.arb_out = None
        """The last ArbitrationOutput (its aiding records, method D's added, are ``aiding``)."""
        self.use_fc_heading = heading["use_fc_when_trusted"]
        self.use_fc_yaw = heading.get("use_fc_yaw", True)
        """False: the FC's yaw is used nowhere ([heading] use_fc_yaw, or ``exclude_fc_yaw``)."""
        self._b1_heading_s = -math.inf
        self._yaw_P_prev = None
        """(time, yaw of the attitude filter's platform attitude) at the last solution: the heading rate."""
        self.b_health = SyntheticAhrsHealth()
        """Method B's reference and consistency as a heading source (service/heading_sources.py)."""
        self.a_check = AzimuthCheck()
        """Method A against the sources it supersedes (service/heading_sources.py)."""
        self._hdg_measurement = None
        """(time, HeadingDiag) of C's last magnetometer heading measurement: its aiding record."""
        self.aiding: dict = {}
        """name -> AidingRecord (service/aiding.py) of the last arbitration, method D's included."""

        self.filter_period_s = 1.0 / cfg["heading"]["filter_rate_hz"]
        self._filter_due_s = -math.inf
        self._acc_gyro, self._acc_accel, self._acc_n, self._acc_mag = np.zeros(3), np.zeros(3), 0, None
        # between filter steps: the last solution turned by the gyros (``propagated_solution``)
        self._out: OutputState | None = None
        self._out_sol: NavSolution | None = None
        self._out_bias_body_rad_s = np.zeros(3)
        self._out_rx_s, self._out_gyro_s = None, None   # the sample _out was last turned to

        self.phase = PhaseState()
        self.strapdown: StrapdownState | None = None
        self.gyro_bias_rad_s = np.zeros(3)
        self.counters = PipelineCounters()
        self.input_checks = self.core.input_checks(InputCheckParams(gap_s=cfg["mavlink"]["imu_gap_s"]))
        self.events: list[tuple[str, str]] = []
        self.last_time_fc_s: float | None = None
        self.fc_attitude: FcAttitude | None = None
        self.pressure: PressureSample | None = None
        self.fc_armed: bool | None = None
        """The FC's last HEARTBEAT: armed (None before the first)."""
        self.fc_reports_flying: bool | None = None
        """ArduPlane's own is_flying() from its HEARTBEAT (None: unknown, or another autopilot)."""
        self.fc_landed: bool | None = None
        """The FC's own landed state (FcFlightState; None: it does not say)."""
        self._last_rx_s: float | None = None
        self._unseen_pending = False
        self._azimuth_off: str | None = None
        """Why method A is off for the rest of the flight (an interval it did not integrate)."""
        self._fc_status_seen = False
        """An estimator status (FcEkfStatus) reached method B since the start / the FC's reboot."""
        self._fc_status_pending: FcEkfStatus | None = None
        """The last status that came before the first IMU sample (no FC time to date it): B gets it there."""
        self._fc_first_attitude_s: float | None = None
        self._fc_status_missing_said = False

    # --- inputs -------------------------------------------------------------------------------

    @property
    def azimuth(self) -> AzimuthState:
        """Method A's state (estimators.azimuth.AzimuthState)."""
        if self._azimuth_held is not None:
            azimuth_take_back(self)
        if self._ground_a:   # its delay line and levelling held in the core on the ground
            ground_take_back(self)
        return self._azimuth

    @azimuth.setter
    def azimuth(self, st: AzimuthState) -> None:
        self._azimuth_held = None   # a held run's state is replaced with the rest
        self._ground_a = False      # ... and so is a held delay line
        self._azimuth = st

    @property
    def azimuth_out(self) -> AzimuthOutput | None:
        """Method A's output at its last step (None: not run, or disabled)."""
        due = self._azimuth_out_due
        if due is not None:
            st, t = due
            if st is None and self._azimuth_held is not None:   # from the held run, no take-back
                out = azimuth_output_held(self, t)
            else:
                out = azimuth_output(self.azimuth if st is None else st, t, self.core.azimuth_output_numbers)
            self._azimuth_out, self._azimuth_out_due = out, None
        return self._azimuth_out

    @azimuth_out.setter
    def azimuth_out(self, out: AzimuthOutput | None) -> None:
        self._azimuth_out, self._azimuth_out_due = out, None

    def on_imu(self, s: ImuSample, verdict=None) -> NavSolution | None:
        """One IMU sample. ``verdict``: the input checks' verdict on it when they already ran (the
        hot path of ``on_imu_batch``: each sample is checked once)."""
        gyro_s, accel_s, t = s.gyro_rad_s, s.accel_m_s2, s.time_fc_s
        if self.vehicle.pending:  # a fixed wing's take-off parameters never answered: decide without them
            self._vehicle_chosen(self.vehicle.poll(s.time_rx_s))
        if verdict is None:  # service/input_checks.py: bad values never reach the estimators
            verdict = self.input_checks.check(s)
        for ev in verdict.events:
            self._event(*ev)
        if verdict.reset:
            self.on_fc_reboot()
        if verdict.reject is not None:
            self.counters.reject(verdict.reject)
            return None
        # ndarray.all, not np.all: the same test without numpy's Python-level dispatch (3 per sample)
        if not (np.isfinite(gyro_s).all() and np.isfinite(accel_s).all() and math.isfinite(t)):
            self.counters.reject("non-finite IMU sample")
            return None
        if self.last_time_fc_s is not None and t <= self.last_time_fc_s:
            self.counters.reject("IMU time not increasing")
            return None
        mag_s = s.mag_gauss if s.mag_gauss is not None and np.isfinite(s.mag_gauss).all() else None
        self.last_time_fc_s = t
        self.counters.imu_samples += 1

        if self._unseen_pending:
            self._unseen_pending = False
            self._account_unseen(s)
        if self._fc_status_pending is not None:   # a status that came before the first sample's FC time
            st, self._fc_status_pending = self._fc_status_pending, None
            self.on_fc_ekf_status(st)
        self._last_rx_s = s.time_rx_s

        prev_phase = self.phase.phase
        evidence = self._flight_evidence(t) if prev_phase in (PRE_LAUNCH, LAUNCH) else None
        self.phase, events = self.core.phase_step(self.phase, gyro_s, accel_s, t, self.phase_params, evidence)
        for ev in events:
            self._event(*ev)
        self._step_azimuth(prev_phase, gyro_s, accel_s, mag_s, t)
        if prev_phase != self.phase.phase or self.phase.started_in_flight:
            # re-levelling at rest only while the vehicle may be at rest (polar_attitude relevel_allowed)
            on_ground = self.phase.phase not in (LAUNCH, IN_FLIGHT) and not self.phase.started_in_flight
            if self.polar_att_params.relevel_allowed != on_ground:
                self.polar_att_params = dc_replace(self.polar_att_params, relevel_allowed=on_ground)
        if prev_phase == PRE_LAUNCH and self.phase.phase == LAUNCH:
            self._start_flight(s)
        elif prev_phase == PRE_LAUNCH and self.phase.started_in_flight:
            self._start_in_flight(t, accel_s)
        elif self.phase.phase in (LAUNCH, IN_FLIGHT) and self.strapdown is not None:
            self.strapdown, diag = self.core.strapdown_step(self.strapdown, gyro_s - self.gyro_bias_rad_s, t,
                                                            self.strapdown_params)
            if not diag.integrated and diag.reason != "first sample":
                self.counters.strapdown_gaps += 1
                self._event("strapdown", diag.reason)
                self._disable_azimuth(f"IMU gap in flight ({diag.reason})")

        # The filters (B, C, arbitration) run at filter_rate_hz on the mean rate and specific
        # force of the samples since their last step: the mean rate times the interval is the
        # exact angle increment (only the coning within the interval is lost, well below the
        # gyro noise at 50 Hz for an airframe's motion). Method A and the phases above keep the
        # full IMU rate.
        hs = self._hs   # the accumulators and the output attitude (service/hot_path.SampleState, or the core's)
        if hs.accumulate(gyro_s, accel_s, mag_s, t, self.filter_period_s):  # no filter step due (tolerance: jitter)
            hs.turn_output(t, self.C_body_from_sensor @ gyro_s, self.polar_att_params.max_dt_s, s.time_rx_s,
                           s.gyro_rad_s)
            return None
        # slots advance by one period, so the mean rate is exact under timestamp jitter
        self._filter_due_s += self.filter_period_s
        if self._filter_due_s <= t:  # the first sample, or after a gap: restart the slots here
            self._filter_due_s = t + self.filter_period_s
        gyro_s = self._acc_gyro / self._acc_n
        accel_s = self._acc_accel / self._acc_n
        mag_s = self._acc_mag
        self._acc_gyro, self._acc_accel, self._acc_n, self._acc_mag = np.zeros(3), np.zeros(3), 0, None

        C = self.C_body_from_sensor
        gyro_b, accel_b = C @ gyro_s, C @ accel_s
        mag_b = C @ mag_s if mag_s is not None else None
        att, mag_s, mag_b_learn = self._filter_chain(t, gyro_b, accel_b, mag_b)
        self._step_ahrs(ImuEvent(t, gyro_s, mag_s))
        sol = self._solution(s, gyro_s, att)
        if self.deviation_calibrate and mag_b_learn is not None:   # undisturbed, usable
            self._deviation_learn(sol, mag_b_learn, t)
        has_q = att is not None and sol.q_nav_from_body is not None
        self._out = output_reset(sol.q_nav_from_body, t) if has_q else None
        self._out_sol = sol if has_q else None
        self._out_rx_s, self._out_gyro_s = (s.time_rx_s, s.gyro_rad_s) if has_q else (None, None)
        if has_q:
            self._out_bias_body_rad_s = att.gyro_bias_rad_s
        return sol

    def on_imu_batch(self, batch: ImuBatch) -> list[NavSolution]:
        """The IMU samples of one read (mavlink_io.imu_batch: IMU_RECORD rows in FC time order) ->
        the filter-rate solutions they produced, in order; what on_imu does to each sample, events
        included (drain_events after the batch); propagated_solution() then brings the last one to
        the batch's newest sample. With the compiled core, the quiet samples (no filter step, no
        event, nothing decided: service/hot_path.py) are taken in C++ (core/hot_path.hpp) and
        on_imu handles the others; with the reference, on_imu handles every sample."""
        return [sol for _, sol in batch_steps(self, batch) if sol is not None]

    def step_imu(self, s: ImuSample) -> NavSolution | None:
        """``on_imu(s)``, with the compiled core a quiet sample taken by its hot path
        (service/hot_path.sample_step: a batch of one row): what the daemon's message path calls.
        The same solution, events and state as on_imu."""
        return sample_step(self, s)

    def imu_batch_steps(self, batch: ImuBatch, samples: list[ImuSample] | None = None):
        """``on_imu_batch`` one handled sample at a time: yields (row, solution or None) for each row
        on_imu handled (a caller that drains the events per sample, as a replay does: the rows the
        core took give no solution and no event). ``samples``: the rows as ImuSample objects, when
        the caller has them."""
        return batch_steps(self, batch, samples)

    def propagated_solution(self) -> NavSolution | None:
        """The last filter step's solution brought to the newest IMU sample (what the daemon sends
        between filter steps: a real AHRS publishes at its IMU rate): its attitude turned by the gyro
        increments since (estimators/output_propagation), roll, pitch and heading from that attitude,
        the newest body rates; sigmas, sources and flags as of the filter step (they change by far
        less than they state over one filter period). The solution itself right after a filter step;
        None before C's attitude filter has levelled or after a sample interval it cannot integrate."""
        return self.solution_from_snapshot(self.propagated_snapshot())

    def propagated_snapshot(self):
        """What ``propagated_solution`` is made of, taken now without building it (the daemon builds
        it only when an output slot or a reader wants it: most of the IMU samples between filter steps
        reach no slot): None or a NavSolution as propagated_solution gives them, else an opaque
        snapshot that ``solution_from_snapshot`` turns into the same NavSolution later, whatever the
        Pipeline did since."""
        sol = self._out_sol
        if sol is None:
            return None
        o = self._hs.out_snapshot()   # (q, time_s, rx, gyro) of the output attitude
        if o is None:
            return None
        if o[1] == sol.time_fc_s:
            return sol
        return sol, o, self.phase.phase, self.gyro_bias_rad_s

    def solution_from_snapshot(self, snap) -> NavSolution | None:
        """The NavSolution of a ``propagated_snapshot``."""
        if snap is None or type(snap) is NavSolution:
            return snap
        sol, (q, time_s, rx, gyro), phase, bias = snap
        q = np.array(q)
        roll, pitch, yaw = euler_from_quat(q)
        return _nav_replace(sol, time_fc_s=time_s, time_rx_s=rx, phase=phase,
                            q_nav_from_body=q, roll_rad=roll, pitch_rad=pitch,
                            heading_rad=wrap_2pi(yaw) if sol.heading_rad is not None else None,
                            rates_body_rad_s=self.C_body_from_sensor @ (np.asarray(gyro, float) - bias))

    def on_pressure(self, s: PressureSample) -> None:
        self.pressure = s
        self.counters.pressure_samples += 1
        if math.isfinite(s.press_abs_pa):
            self._step_ahrs(AirEvent(s.time_fc_s, s.press_abs_pa, s.press_diff_pa, s.temperature_k))

    def on_fc_attitude(self, a: FcAttitude) -> None:
        self.fc_attitude = a
        self.counters.fc_attitude_samples += 1
        self._step_ahrs(FcAttitudeEvent(a.time_fc_s, np.array([a.roll_rad, a.pitch_rad, a.yaw_rad])))
        if not (self._fc_status_seen or self._fc_status_missing_said):
            if self._fc_first_attitude_s is None:
                self._fc_first_attitude_s = a.time_fc_s
            wait_s = self.ahrs_params.health.status_wait_s
            if a.time_fc_s - self._fc_first_attitude_s >= wait_s:
                # estimators/reference_health's rule for an FC that sends no estimator status
                self._fc_status_missing_said = True
                self._event("reference_status", f"the FC sent no estimator status (EKF_STATUS_REPORT / "
                                                f"ESTIMATOR_STATUS) within {wait_s:g} s of its first ATTITUDE: "
                                                "its attitude is judged on freshness and agreement with our "
                                                "gyros alone")

    def fc_sends_no_status(self, why: str) -> None:
        """The FC's estimator status is known to be absent for the whole input (a log that records none:
        service/replay.py asks the reader): its attitude is judged without one from the first ATTITUDE,
        not after ``status_wait_s`` of waiting (estimators/reference_health). Call before any input."""
        self.ahrs_params = dc_replace(self.ahrs_params,
                                      health=dc_replace(self.ahrs_params.health, status_wait_s=0.0))
        self._fc_status_missing_said = True
        self._event("reference_status", f"{why}: the FC's attitude is judged on freshness and agreement with "
                                        "our gyros alone")

    def on_fc_heartbeat(self, hb: FcHeartbeat) -> None:
        self.fc_armed = bool(hb.armed)
        if self.vehicle.pending:
            self._vehicle_chosen(self.vehicle.on_heartbeat(hb.vehicle_type, hb.autopilot, hb.time_rx_s))
        # ArduPlane's system_status is its is_flying() estimate (ACTIVE / STANDBY); other
        # autopilots' ACTIVE means armed, and CRITICAL/EMERGENCY (failsafes) say nothing
        self.fc_reports_flying = None
        if hb.autopilot == "ardupilot" and hb.vehicle_type == FIXED_WING \
                and hb.system_status in (MAV_STATE_STANDBY, MAV_STATE_ACTIVE):
            self.fc_reports_flying = hb.system_status == MAV_STATE_ACTIVE
        if self.last_time_fc_s is not None:
            self._step_ahrs(FcStatusEvent(self.last_time_fc_s, system_status=hb.system_status))

    def on_fc_params(self, values: dict, done: bool, time_rx_s: float) -> None:
        """The FC parameters read so far (link.fc_params; ``done``: all answered or given up)."""
        if self.vehicle.pending:
            self._vehicle_chosen(self.vehicle.on_params(values, done, time_rx_s))

    def on_fc_identity(self, mav_type: int, autopilot: str, params: dict, time_rx_s: float,
                       source: str = "") -> None:
        """What a log says of its FC where it has no HEARTBEAT (service/logreaders FcIdentity): the
        HEARTBEAT's type and the FC's take-off parameters for ``[launch] vehicle = "auto"``, nothing else."""
        if self.vehicle.pending:
            self.vehicle.on_params(params, True, time_rx_s)
            self._vehicle_chosen(self.vehicle.on_heartbeat(mav_type, autopilot, time_rx_s),
                                 f" (the log's {source}: it has no HEARTBEAT)" if source else "")

    def _vehicle_chosen(self, choice, said_by: str = "") -> None:
        """``[launch] vehicle = "auto"`` decided (once): the take-off detector it selects, and why."""
        if choice is None:
            return
        if choice.vehicle is None:
            self._event("vehicle", f"no take-off model: {choice.reason}{said_by}")
            return
        self.phase_params = dc_replace(self.phase_params, vehicle=choice.vehicle)
        self._event("vehicle", f"{choice.vehicle} take-off (auto): {choice.reason}{said_by}")

    def on_fc_flight_state(self, st: FcFlightState) -> None:
        """The FC's armed/landed state (EXTENDED_SYS_STATE, or a log's own records): phase evidence."""
        if st.armed is not None:
            self.fc_armed = bool(st.armed)
        self.fc_landed = st.landed

    def on_fc_ekf_status(self, st: FcEkfStatus) -> None:
        """The FC's estimator status. Until the first one its ATTITUDE is no reference (method B's
        reference health: an FC publishes a fallback attitude before its EKF runs)."""
        if self.last_time_fc_s is None:   # no FC time yet (before the first IMU sample): held for it
            self._fc_status_pending = st
            return
        self._fc_status_seen = True
        self._step_ahrs(FcStatusEvent(self.last_time_fc_s, attitude_ok=st.attitude_ok,
                                      horiz_pos_ok=st.horiz_pos_ok))

    def on_fc_reboot(self) -> None:
        """The FC clock restarted: keep the attitude, restart the time bookkeeping. The interval
        between the last sample before and the first after was not seen: at that sample the
        attitude and heading filters widen their covariance by it (receive time; the FC clock
        cannot measure it) and restart their increments."""
        self.last_time_fc_s = None
        if self.strapdown is not None:
            self.strapdown = StrapdownState(self.strapdown.q_ref_from_sensor)
        self._unseen_pending = True
        # method B forgets the FC's estimator status (synthetic_ahrs_unseen): wait for it again
        self._fc_status_seen, self._fc_first_attitude_s, self._fc_status_missing_said = False, None, False
        self._event("fc_reboot", "FC time restarted; integration resumes at the next sample")

    def exclude_fc_yaw(self, reason: str) -> None:
        """From now on the FC's yaw is used nowhere (e.g. it is our own heading fed back to us):
        not a heading source, not method B's reference yaw or KF1 reference. One event, once."""
        if not self.use_fc_yaw:
            return
        self.use_fc_yaw = False
        self.ahrs_params = dc_replace(self.ahrs_params, use_fc_yaw=False)
        # ... nor what B took from it before (its heading, magnetometer biases, KF1): a held core
        # state goes through the reference's record (once per run) and is taken in again
        st = self.ahrs.to_state() if hasattr(self.ahrs, "to_state") else self.ahrs
        self.ahrs = synthetic_ahrs_forget_fc_yaw(st, self.ahrs_params, self._kf1_learn_start)
        if self.ahrs_out is not None:
            self.ahrs_out = synthetic_ahrs_output(self.ahrs, self.ahrs_params)
        self._event("fc_yaw_excluded", f"the FC's yaw is no longer used: {reason}")

    def air_data(self):
        """The latest air data (estimators.air_data.AirData) from method B's air-data step, or None."""
        return self.ahrs.air_last

    def kf1_estimate(self) -> Kf1State | None:
        """This flight's magnetometer-error estimate (method B, KF1), for the calibration store."""
        return self.ahrs.kf1_learn

    def drain_events(self) -> list[tuple[str, str]]:
        ev, self.events = self.events, []
        return ev

    # --- internals ----------------------------------------------------------------------------

    def _event(self, kind: str, detail: str) -> None:
        self.events.append((kind, detail))

    def _step_ahrs(self, event) -> None:
        try:
            self.ahrs, out = self.core.synthetic_ahrs_step(self.ahrs, event, self.ahrs_params,
                                                           isinstance(event, ImuEvent))
        except ValueError as exc:  # a sample the estimator refuses is dropped with its reason
            self.counters.reject(f"synthetic AHRS: {exc}")
            return
        if out is not None:
            self.ahrs_out = out
            if out.reference_trusted != self._ahrs_trusted:
                self._ahrs_trusted = out.reference_trusted
                self._event("reference", ("FC attitude trusted: " if out.reference_trusted
                                          else "FC attitude NOT trusted: ") + out.reference_reason)

    def _filter_chain(self, t: float, gyro_b: np.ndarray, accel_b: np.ndarray, mag_b: np.ndarray | None):
        """Method C's filter step with its magnetometer chain (body axes: the filter-rate mean rate and
        specific force, the newest magnetometer): the attitude filter, the zero-rate update at rest, the
        heading filter's tilt, the magnetometer's hard iron, disturbance and usability, D's correction,
        the heading filter. -> (attitude estimate or None, the magnetometer for B (sensor axes) or None,
        the measured field D may learn on or None). With the compiled core one C++ call
        (core/filter_chain.hpp, ``_filter_chain_core``); the Python chain is the reference
        (``_filter_chain_python``; tests/test_core_filter_chain.py proves them equal)."""
        speed = self._manoeuvre_speed_m_s(t)
        if abs(speed - self.polar_att_params.manoeuvre_speed_m_s) >= MANOEUVRE_SPEED_STEP_M_S:
            self.polar_att_params = dc_replace(self.polar_att_params, manoeuvre_speed_m_s=speed)
        if self.filter_chain_core and self._chain_states_held():
            return self._filter_chain_core(t, gyro_b, accel_b, mag_b)
        return self._filter_chain_python(t, gyro_b, accel_b, mag_b)

    def _chain_states_held(self) -> bool:
        """The chain's states are held in the core (those not yet are taken in; a deviation state the
        core does not take leaves the step to the Python chain)."""
        cf = core_facade
        if type(self.polar_att) is not cf.HeldPolarAttitude or type(self.polar_hdg) is not cf.HeldPolarHeading:
            return False
        if type(self.zero_rate) is not cf.HeldZeroRate:
            self.zero_rate = cf.HeldZeroRate(self.zero_rate)
        if type(self.mag_dist) is not cf.HeldMagDisturbance:
            self.mag_dist = cf.HeldMagDisturbance(self.mag_dist)
        if type(self.mag_usability) is not cf.HeldMagUsability:
            self.mag_usability = cf.HeldMagUsability(self.mag_usability)
        if self.deviation is not None and type(self.deviation) is not cf.HeldDeviation:
            try:
                self.deviation = cf.HeldDeviation(self.deviation)
            except ValueError:   # a state without its coverage bins
                return False
        return True

    def _filter_chain_core(self, t: float, gyro_b: np.ndarray, accel_b: np.ndarray, mag_b: np.ndarray | None):
        """``_filter_chain_python`` in one core call on the held states (estimators/core.py filter_chain_step)."""
        fc, b = self.fc_attitude, self.ahrs_out
        r = core_facade.filter_chain_step(
            self.polar_att, self.polar_att_params, self.zero_rate, self.zero_rate_params, self.mag_dist,
            self.mag_dist_params, self.mag_usability, self.mag_usability_params, self.polar_hdg, self.polar_hdg_params,
            self.deviation, t, gyro_b, accel_b, mag_b, self.C_body_from_sensor,
            (fc.time_fc_s, fc.roll_rad, fc.pitch_rad) if fc is not None and b is not None and b.reference_trusted
            else None, self.ahrs_params.fc_sigma_tilt_rad, FC_TILT_MAX_AGE_S, self.declination_rad,
            self.declination_sigma_rad, self.field.e_ned_gauss, self.deviation_apply, self.deviation_min_coverage,
            self.deviation_params.min_samples_per_bin, self._deviation_hard_iron_changed, self._deviation_in_use)
        for ev in r.events:
            self._event(*ev)
        if r.mag_status is not None:
            self.mag_status = r.mag_status
        self._deviation_hard_iron_changed, self._deviation_in_use = r.dev_hard_iron_changed, r.dev_in_use
        if r.hdiag is not None:
            self._heading_measured(t, r.hdiag)
        return r.att, r.mag_s, (mag_b if r.mag_raw else None)

    def _filter_chain_python(self, t: float, gyro_b: np.ndarray, accel_b: np.ndarray, mag_b: np.ndarray | None):
        """``_filter_chain``'s reference: each step a call of its own (the core's or the Python reference's)."""
        self.polar_att, adiag = self.core.polar_attitude_step(self.polar_att, t, gyro_b, accel_b,
                                                              self.polar_att_params)
        if adiag.relevelled:
            self._event("attitude", adiag.reason)
        # zero-rate updates only while the vehicle may be at rest (as the re-levelling): steady
        # flight also has a steady rate and specific force, and a slow turn is no gyro bias
        rest_rate = None
        if self.polar_att_params.relevel_allowed:
            step = core_facade.rest_step if type(self.zero_rate) is core_facade.HeldZeroRate else rest_step
            self.zero_rate, rest_rate = step(self.zero_rate, t, gyro_b, accel_b, self.zero_rate_params)
        elif self.zero_rate.time_s is not None:
            self.zero_rate = ZeroRateState()
        if rest_rate is not None:
            self.polar_att, _ = self.core.attitude_zero_rate_update(self.polar_att, rest_rate, self.zero_rate_params)
        att = self.core.polar_attitude_estimate(self.polar_att)
        tilt = self._heading_tilt(t, att, gyro_b)
        mag_b_meas = mag_b                                # as measured: what D learns on and corrects
        mag_b_hi = self._mag_disturbance(mag_b, t, att)   # m - learnt hard iron, None when disturbed
        if not self._mag_usable(mag_b, t, tilt, gyro_b) or mag_b_hi is None:
            mag_b = mag_s = None
        else:
            mag_b, mag_s = mag_b_hi, self.C_body_from_sensor.T @ mag_b_hi
        mag_b_raw = mag_b
        if mag_b is not None:
            mag_b = self._deviation_corrected(mag_b_meas, mag_b)
        if tilt is not None:
            self.polar_hdg, hdiag = self.core.polar_heading_step(
                self.polar_hdg, HeadingInputs(t, gyro_b, tilt[0], tilt[1], tilt[2],
                                              mag_b, self.declination_rad, self.declination_sigma_rad,
                                              # D applied: its residual; else C's uncalibrated model
                                              float(np.max(residual_sigma_gauss(self.deviation)))
                                              if mag_b is not mag_b_raw else self._mag_hard_iron_residual(mag_b, att),
                                              # heading in every attitude: the platform formulation
                                              *self._heading_platform(att, tilt),
                                              # the model's field: its mismatch widens the sigma
                                              field_model_ned_gauss=self.field.e_ned_gauss),
                self.polar_hdg_params)
            if rest_rate is not None:
                self.polar_hdg, _ = self.core.heading_zero_rate_update(self.polar_hdg, rest_rate,
                                                                       self.zero_rate_params)
            self._heading_measured(t, hdiag)
        return att, mag_s, (mag_b_meas if mag_b_raw is not None else None)

    def _heading_measured(self, t: float, hdiag) -> None:
        """After C's heading step (either chain): its measurement kept for the heading source, one
        'heading_filter' event when the magnetometer heading comes or goes."""
        if not hdiag.measured:
            return
        self._hdg_measurement = (t, hdiag)
        if hdiag.source_available != self._hdg_available:
            self._hdg_available = hdiag.source_available
            self._event("heading_filter", "magnetometer heading available" if hdiag.source_available
                        else f"magnetometer heading unavailable: {hdiag.reason}")

    def _manoeuvre_speed_m_s(self, t: float | None) -> float:
        """The speed V along the body x axis with which C's attitude filter bounds the centripetal
        acceleration w x [V, 0, 0] of a turn (estimators/polar_attitude ``manoeuvre_speed_m_s``):
        the measured true airspeed while the air data is fresh and its pitot sound (a steady wind
        moves the vehicle but does not turn it: the air-relative velocity is what a turn rotates);
        else ``[heading] manoeuvre_speed_m_s`` when set, else the vehicle's: a multicopter
        ``MULTICOPTER_MANOEUVRE_SPEED_M_S``, a fixed wing (or a vehicle not known yet) the
        configured cruise speed."""
        choice = self.vehicle.choice
        multicopter = choice is not None and choice.vehicle == "multicopter"
        air = self.ahrs.air_last
        # not a multicopter's: it has no pitot, and its SCALED_PRESSURE's differential pressure reads
        # ~0 (arducopter-flight.tlog: 0 m/s on 2547 of 2857 steps, roll 6.0 -> 46.6 deg RMS with it)
        if (not multicopter and t is not None and air is not None and self.pressure is not None
                and self.pressure.press_diff_pa is not None
                and abs(t - air.time_s) <= AIR_EVIDENCE_MAX_AGE_S and not (air.pitot_blocked or air.pitot_noisy)
                and math.isfinite(air.tas_m_s)):
            return float(air.tas_m_s)
        if self.manoeuvre_speed_cfg_m_s > 0.0:
            return self.manoeuvre_speed_cfg_m_s
        if multicopter:
            return MULTICOPTER_MANOEUVRE_SPEED_M_S
        return self.cruise_speed_m_s

    def _flight_evidence(self, t: float) -> FlightEvidence:
        """What the started-in-flight rule weighs besides the IMU (service/phases.py)."""
        air = self.ahrs.air_last
        fresh = air is not None and abs(t - air.time_s) <= AIR_EVIDENCE_MAX_AGE_S
        has_pitot = self.pressure is not None and self.pressure.press_diff_pa is not None
        return FlightEvidence(armed=self.fc_armed, fc_reports_flying=self.fc_reports_flying, fc_landed=self.fc_landed,
                              airspeed_m_s=air.tas_m_s if fresh and has_pitot and not air.pitot_noisy else None,
                              alt_rate_m_s=air.alt_rate_m_s if fresh and air.rate_valid else None)

    def _fc_tilt_now(self, t: float) -> tuple[float, float] | None:
        """The FC's roll/pitch if it is trusted and fresh at FC time ``t``, else None."""
        fc, b = self.fc_attitude, self.ahrs_out
        if fc is None or b is None or not b.reference_trusted or abs(t - fc.time_fc_s) > self.arb_params.max_age_s:
            return None
        return fc.roll_rad, fc.pitch_rad

    def _start_in_flight(self, t: float, accel_sensor_m_s2: np.ndarray) -> None:
        """Started in flight (service/phases.py): no levelling and no launch, so method A is off for
        this run. Roll/pitch: the attitude filter C re-initialised from the trusted FC ATTITUDE, else
        from the accelerometer with a wide sigma; heading from what stays valid (FC when trusted,
        C's magnetometer heading re-acquired with the new tilt, B)."""
        p = self.phase_params.in_flight
        old = self.core.polar_attitude_estimate(self.polar_att)
        fc = self._fc_tilt_now(t)
        if fc is not None:
            roll, pitch = fc
            sigma, src = p.fc_tilt_sigma_rad, "the trusted FC attitude"
        else:
            sigma, src = p.accel_tilt_sigma_rad, "the accelerometer (FC attitude not trusted)"
            if old is not None:  # C levelled itself on the accelerometer at start and has run since
                roll, pitch = old.roll_rad, old.pitch_rad
            else:
                f = self.C_body_from_sensor @ accel_sensor_m_s2
                roll, pitch = math.atan2(-f[1], -f[2]), math.atan2(f[0], math.hypot(f[1], f[2]))
        # the gyro bias: the FC's calibrated stream's residual (zero mean, its in-run drift as the
        # sigma), not C's bias so far: a filter that levelled on a take-off roll or in a turn has put
        # that motion into it, and no rest measured it; a stream too slow to resolve the FC's gyro
        # keeps C's own bias and turn-on prior (phases.InFlightParams.gyro_bias_sigma_rad_s)
        t0 = self.phase.start_time_s
        rate_hz = (self.counters.imu_samples - 1) / (t - t0) if t0 is not None and t > t0 else 0.0
        if rate_hz >= p.calibrated_gyro_min_rate_hz:
            bias, bias_sigma = np.zeros(3), p.gyro_bias_sigma_rad_s
            bias_text = (f"gyro bias 0 +- {math.degrees(bias_sigma):.2f} deg/s (the FC's calibrated gyro at "
                         f"{rate_hz:.0f} Hz, no rest to measure it)")
        else:
            bias, bias_sigma = (old.gyro_bias_rad_s if old is not None else None), None
            bias_text = (f"gyro bias prior {math.degrees(self.polar_att_params.gyro_bias_init_sigma_rad_s):.2f} "
                         f"deg/s: a {rate_hz:.0f} Hz stream does not resolve the FC's gyro")
        self.polar_att = self.core.polar_attitude_init_at(t, roll, pitch, sigma, self.polar_att_params, bias,
                                                          bias_sigma)
        self.polar_hdg = self.core.polar_heading_init(params=self.polar_hdg_params)
        self._hdg_available = None
        self.zero_rate = ZeroRateState()
        # the magnetic-disturbance check levels the field with C's attitude: its field references (norm,
        # dip) and its pair anchor were taken in C's old frame and tilt (levelled on a take-off roll: an
        # ArduPlane SITL log's dip reference was 11 deg off, and the field read as disturbed for 145 s
        # once the tilt was right); the hard iron it learnt from relative turns is kept
        md = self.mag_dist
        self.mag_dist = MagDisturbanceState(
            hard_iron_gauss=np.array(md.hard_iron_gauss, float),
            P_hard_iron=None if md.P_hard_iron is None else np.array(md.P_hard_iron, float),
            n_relearns=int(md.n_relearns))
        self._event("attitude", f"started in flight: roll/pitch from {src} (roll {math.degrees(roll):.1f} deg, "
                    f"pitch {math.degrees(pitch):.1f} deg, sigma {math.degrees(sigma):.1f} deg), {bias_text}")
        self._event("azimuth", "disabled: started in flight (method A needs the levelling and the launch)")

    def _account_unseen(self, s: ImuSample) -> None:
        """After an FC clock restart: widen C's attitude and heading covariance by the interval
        not seen (receive time between the last sample before and this one)."""
        if self._last_rx_s is None or not math.isfinite(s.time_rx_s):
            return
        unseen = max(0.0, s.time_rx_s - self._last_rx_s)
        self.polar_att = self.core.polar_attitude_unseen(self.polar_att, unseen, self.polar_att_params)
        self.polar_hdg = self.core.polar_heading_unseen(self.polar_hdg, unseen, self.polar_hdg_params)
        self.ahrs = self.core.synthetic_ahrs_unseen(self.ahrs, unseen, self.ahrs_params)
        self._disable_azimuth(f"FC clock restarted in flight ({unseen:.1f} s not seen)")
        # the filter slots restart here (the samples accumulated before belong to the old clock)
        self._filter_due_s = -math.inf
        self._acc_gyro, self._acc_accel, self._acc_n, self._acc_mag = np.zeros(3), np.zeros(3), 0, None
        self.zero_rate = ZeroRateState()
        if unseen > 0.0:
            self._event("unseen", f"{unseen:.1f} s not seen (FC clock restarted): attitude and heading "
                        "sigma widened")

    def _disable_azimuth(self, why: str) -> None:
        """Method A chains the gyros from the launch: an interval it did not integrate breaks it
        for the rest of the flight (its fit would go on with a wrong attitude and a small sigma)."""
        if self._azimuth_off is None and self.azimuth.phase != "prelaunch":
            self._azimuth_off, self.azimuth_out = f"disabled: {why}", None
            self._event("azimuth", self._azimuth_off)

    def _step_azimuth(self, prev_phase: str, gyro_s, accel_s, mag_s, t: float) -> None:
        if self.phase.started_in_flight or self._azimuth_off is not None:
            return
        if self.phase.phase == PRE_LAUNCH:
            if self._ground_core:   # the same in the core (service/hot_path.py ground_step, core/ground.hpp)
                ground_step(self, gyro_s, accel_s, mag_s, t)
                return
            self.azimuth = azimuth_prelaunch_step(self.azimuth, gyro_s, accel_s, t)
            if mag_s is not None:
                self._rest_candidate = rest_accumulate(self._rest_candidate, gyro_s, accel_s, mag_s)
            if self.phase.block_start_s == t:  # a still block ended on this sample
                if self.phase.block_passed_s == t:  # ... and passed: the rest so far is usable
                    self.rest = self._rest_candidate
                else:  # handled or moved: start over
                    self._rest_candidate = self.rest = RestState()
        elif prev_phase == PRE_LAUNCH:  # launch detected on this sample
            self._declination_at_launch()
            self.azimuth = azimuth_prelaunch_step(self.azimuth, gyro_s, accel_s, t)
            why = self._azimuth_why_not()
            if why:  # one line, and method A stays off for this flight
                self._azimuth_off, self.azimuth_out = f"not run: {why}", None
                self._event("azimuth", self._azimuth_off)
                return
            # method A levels on the phases' kept block (the quietest window), the samples from the
            # launch on replayed from its delay line
            t_launch = self.phase.launch_time_s
            block = self.phase.level_block
            if self.phase.moved_rad > self.phase_params.moved_rad:  # picked up since: C's tilt at the launch
                block, why = self._level_block_from_attitude_filter(block)
                if block is None:
                    self._azimuth_off, self.azimuth_out = f"not run: {why}", None
                    self._event("azimuth", self._azimuth_off)
                    return
                self._event("azimuth", why)
            self.azimuth = dc_replace(self.azimuth, levelling=block,
                                      pending=tuple(x for x in self.azimuth.pending if x[0] >= t_launch))
            self.azimuth, why = azimuth_launch(self.azimuth, t_launch)
            if why:
                self._event("azimuth", why)
        elif self._azimuth_held is not None and azimuth_held_step(self, gyro_s, mag_s, t):
            return   # stepped on A's held run in the core: no solve, no result, no submit, its status kept
        elif self.azimuth.phase != "prelaunch":
            self.azimuth, out = azimuth_step(self.azimuth, gyro_s, accel_s, mag_s, t, self.core.azimuth_propagate,
                                             output_numbers=self.core.azimuth_output_numbers)
            result = self.solver.poll()
            if result is not None:
                self.azimuth = azimuth_apply_solve(self.azimuth, result)
            if t >= self._next_solve_s and self.azimuth.phase == "flight" and self.azimuth.samples \
                    and self.solver.submit(azimuth_for_solver(self, self.azimuth), t, self.core.azimuth_fit_psi,
                                           self.core.azimuth_orientation_diversity):
                # the result (at once from an inline solver) applies from the next sample on
                self._next_solve_s = t + self.solve_period_s[0 if self.azimuth.solution is not None else 1]
            if out.status != self._azimuth_status:  # one event per status change, the reason with it
                self._event("azimuth", f"{out.status}: {out.reason}" if out.reason else out.status)
            self._azimuth_status = out.status
            self.azimuth_out = out

    def _azimuth_why_not(self) -> str:
        """Why method A cannot run from this take-off ("" = its conditions hold: levelled on a
        block that still holds at the launch, and a flight direction for the configured case)."""
        ph, pp = self.phase, self.phase_params
        if ph.level is None or ph.level_block is None:
            return "no levelling before the take-off"
        if ph.moved_rad > pp.moved_rad and self.core.polar_attitude_estimate(self.polar_att) is None:
            return (f"the vehicle turned {math.degrees(ph.moved_rad):.1f} deg since its last still block "
                    f"(> {math.degrees(pp.moved_rad):g} deg) and the attitude filter has not levelled")
        if self.azimuth_params.launch_case == "inclined" and pp.vehicle not in ("launcher", "hand"):
            return (f"launch.case inclined needs a boost along the flight axis; a {pp.vehicle} take-off has "
                    "none (set launch.case aligned)")
        return ""

    def _level_block_from_attitude_filter(self, block: LevellingState) -> tuple[LevellingState | None, str]:
        """The vehicle turned since its last still block (a hand launch: picked up and held): the
        ground levelling no longer holds at the launch. Method A then levels on the attitude
        filter's (method C's, no heading needed) roll/pitch at the launch with its 1-sigma, and
        keeps the block's gyro bias. Written as a levelling state whose mean is gravity at C's tilt
        and whose spread gives the tilt noise |SEM_xy| / g = sigma_C (SEM = sigma_C g / sqrt(2) per
        axis), so levelling_result gives back C's tilt and sigma, and refuses a sigma above its
        max_tilt_noise_rad (None and why)."""
        att = self.core.polar_attitude_estimate(self.polar_att)
        g = float(np.linalg.norm(block.accel_mean_m_s2))
        roll, pitch = att.roll_rad, att.pitch_rad
        sigma = math.sqrt(max(att.cov_roll_pitch_rad2[0, 0], att.cov_roll_pitch_rad2[1, 1], 0.0))
        turned = f"the vehicle turned {math.degrees(self.phase.moved_rad):.1f} deg since its last still block"
        limit = self.phase_params.levelling.max_tilt_noise_rad
        if sigma > limit:
            return None, (f"{turned} and the attitude filter's tilt sigma at the launch, {math.degrees(sigma):.2f} deg, "
                          f"is above the {math.degrees(limit):g} deg a levelling needs")
        f_body = g * np.array([math.sin(pitch), -math.cos(pitch) * math.sin(roll), -math.cos(pitch) * math.cos(roll)])
        n = block.n
        sem = sigma * g / math.sqrt(2.0)
        lev = LevellingState(n, self.C_body_from_sensor.T @ f_body, np.full(3, sem * sem * n * (n - 1)),
                             block.gyro_mean_rad_s.copy(), block.gyro_m2.copy())
        why = (f"{turned}: levelled on the attitude filter at the launch (roll {math.degrees(roll):.2f} deg, pitch "
               f"{math.degrees(pitch):.2f} deg, sigma {math.degrees(sigma):.2f} deg), the gyro bias from the block")
        return lev, why

    def azimuth_status(self) -> str:
        """Method A's state in one line (what the replay summary and the status topic show)."""
        if self.phase.started_in_flight:
            return "disabled: started in flight"
        if self._azimuth_off is not None:
            return self._azimuth_off
        if self.azimuth_out is not None:
            o = self.azimuth_out
            return f"{o.status}: {o.reason}" if o.reason else o.status
        if self.phase.level is None:
            return "waiting: not levelled yet"
        return "waiting for the take-off"

    def _heading_tilt(self, t: float, att, gyro_body_rad_s: np.ndarray):
        """(roll, pitch, 2x2 covariance) that level the magnetometer for C's heading filter: the
        FC's roll/pitch while its attitude is trusted and fresh (its yaw is not used: this holds with
        ``use_fc_yaw`` false too), else C's own attitude filter (None before it has one).
        Why: C's accelerometer-based tilt is biased by sustained accelerations (a multicopter's
        specific force stays along its thrust axis, whatever its tilt), and at a dip of 60-70 deg a
        tilt error e turns the magnetic heading by up to ~tan(dip) e (2-3 e); the GNSS-aided FC
        observes its tilt. Covariance: the FC tilt sigma plus the turn over the sample's age,
        (|omega| age)^2, per axis."""
        fc, b = self.fc_attitude, self.ahrs_out
        if fc is not None and b is not None and b.reference_trusted and 0.0 <= t - fc.time_fc_s <= FC_TILT_MAX_AGE_S:
            age = t - fc.time_fc_s
            var = self.ahrs_params.fc_sigma_tilt_rad ** 2 + (float(np.linalg.norm(gyro_body_rad_s[:2])) * age) ** 2
            return fc.roll_rad, fc.pitch_rad, np.diag([var, var])
        if att is None:
            return None
        return att.roll_rad, att.pitch_rad, att.cov_roll_pitch_rad2

    def _mag_disturbance(self, mag_body_gauss, t: float, att):
        """The magnetometer with its learnt hard iron removed (estimators/mag_disturbance: a magnet
        attached is re-learnt), or None while the field departs from the recent undisturbed one (a
        magnet nearby) or the hard iron is being re-learnt; one 'magnetometer' event per change."""
        if mag_body_gauss is None or att is None:
            return mag_body_gauss if att is None else None
        self.mag_dist, v = self.core.mag_disturbance_step(self.mag_dist, t, mag_body_gauss, att.q_P_from_body,
                                                          self.mag_dist_params)
        if v.relearned:
            self._event("magnetic_disturbance", f"hard iron changed (a magnet attached?): re-learning it, "
                        f"the heading coasts on the gyros meanwhile")
            self._deviation_hard_iron_changed = self.deviation is not None
        if v.changed:
            self._event("magnetic_disturbance", "undisturbed: used again, hard iron [" + ", ".join(
                f"{x:+.3f}" for x in v.hard_iron_gauss) + f"] G +- {v.hard_iron_sigma_gauss:.3f} G"
                if v.usable else f"rejected ({v.reason}): the heading coasts on the gyros, its sigma growing")
        return v.mag_corrected_gauss

    def _mag_hard_iron_residual(self, mag_body_gauss, att) -> float | None:
        """Per-axis sigma (gauss) of what the learnt hard iron leaves in the magnetometer, as the
        heading sees it: the hard iron's covariance P_b turns the heading by g^T C_PB db,
        g = [m_y, -m_x, 0] / H^2 (levelled field m), so its heading variance is
        g^T C_PB P_b C_BP g = s_eq^2 / H^2 with s_eq = H sqrt(g^T C_PB P_b C_BP g); plus the
        uncompensated soft iron (polar_heading's ``uncalibrated_soft_iron`` of |m|)."""
        if mag_body_gauss is None or att is None:
            return None
        md = self.mag_dist
        if type(md) is core_facade.HeldMagDisturbance and core_facade.MAG_HARD_IRON_RESIDUAL_AVAILABLE:
            # the core's twin on the held state (estimators/core.py; parity: tests/test_core_hot_path.py)
            return core_facade.mag_hard_iron_residual(md, mag_body_gauss, att.q_P_from_body,
                                                      self.polar_hdg_params.uncalibrated_soft_iron)
        P = md.P_hard_iron
        if P is None:
            return None
        C = dcm_from_quat(att.q_P_from_body)
        m = C @ mag_body_gauss
        H2 = float(m[0] ** 2 + m[1] ** 2)
        if H2 <= 0.0:
            return None
        g = np.array([m[1], -m[0], 0.0]) / H2
        s_eq = math.sqrt(H2 * float(g @ C @ P @ C.T @ g))
        return math.hypot(s_eq, self.polar_hdg_params.uncalibrated_soft_iron * float(np.linalg.norm(mag_body_gauss)))

    def _heading_platform(self, att, tilt) -> tuple:
        """HeadingInputs' platform fields (estimators/polar_heading): the attitude filter's full
        attitude in its platform frame, its attitude-error covariance and gyro bias, and whether the
        magnetometer is levelled with ``tilt`` (the trusted FC's) rather than that attitude."""
        if att is None:
            return None, None, None, False
        return (att.q_P_from_body, self.polar_att.P[0:3, 0:3], att.gyro_bias_rad_s,
                tilt is not None and tilt[2] is not att.cov_roll_pitch_rad2)

    def _mag_usable(self, mag_body_gauss: np.ndarray | None, t: float, tilt, gyro_body_rad_s: np.ndarray) -> bool:
        """The magnetometer usability verdict for this filter step (estimators/mag_usability, on the
        raw body-axes field levelled with C's roll/pitch); one 'magnetometer' event per change."""
        p = self.mag_usability_params
        if mag_body_gauss is None:
            self.mag_usability, v = self.core.mag_usability_stale(self.mag_usability, t, p, gyro_body_rad_s)
        else:
            self.mag_usability, v = self.core.mag_usability_step(
                self.mag_usability, t, mag_body_gauss, tilt[0] if tilt is not None else None,
                tilt[1] if tilt is not None else None, p, gyro_body_rad_s,
                # a NEW hard iron learnt (a magnet attached) is removed before the model tests; the
                # airframe's own, within its uncalibrated prior, is what those tests allow for
                self.mag_dist.hard_iron_gauss if self.mag_dist.n_relearns > 0 and not self.mag_dist.relearning
                else None)
        if v is not None:
            pending = self.mag_usability.usable is None
            self.mag_status = "usable" if v.usable else (v.reason if pending else f"rejected: {v.reason}")
            if v.usable and self.mag_dist.reason and self.mag_dist.P_hard_iron is not None:
                self.mag_status = f"rejected: {self.mag_dist.reason}"
        if v is not None and v.changed:
            self._event("magnetometer", "usable" if v.usable else
                        f"rejected ({v.reason}): the heading coasts on the gyros, its sigma growing")
        return mag_body_gauss is not None and bool(self.mag_usability.usable)

    def _deviation_corrected(self, mag_measured_body_gauss: np.ndarray, mag_hard_iron_corrected_body_gauss:
                             np.ndarray) -> np.ndarray:
        """The magnetometer (body axes) for C: method D's correction of the MEASURED field once it
        covers enough headings, rolls and pitches (its constant terms A_i are the hard iron: it
        replaces estimators/mag_disturbance's estimate, which moves as it learns); else the field
        less that hard-iron estimate. Not after a re-learnt hard iron (D's A_i are the old one)."""
        if self.deviation is None or not self.deviation_apply:
            return mag_hard_iron_corrected_body_gauss
        cover = self.core.deviation_coverage(self.deviation, self.deviation_params)
        use = cover.overall >= self.deviation_min_coverage and not self._deviation_hard_iron_changed
        if use != self._deviation_in_use:
            self._deviation_in_use = use
            cov = cover
            self._event("deviation", f"compensation {'applied' if use else 'not applied'}: " + (
                        "the hard iron was re-learnt (a magnet attached?) since its calibration"
                        if self._deviation_hard_iron_changed else
                        f"coverage {cov.overall:.2f} (headings {cov.heading_fraction:.2f}, rolls "
                        f"{cov.roll_fraction:.2f}, pitches {cov.pitch_fraction:.2f}), needed "
                        f"{self.deviation_min_coverage:.2f}"))
        if not use:
            return mag_hard_iron_corrected_body_gauss
        h = self.core.polar_heading_estimate(self.polar_hdg)
        if not (h.initialised and math.isfinite(h.heading_rad)):
            return mag_hard_iron_corrected_body_gauss
        att = self.core.polar_attitude_estimate(self.polar_att)
        if att is None:
            return mag_hard_iron_corrected_body_gauss
        return self.core.deviation_corrected_mag(self.deviation, mag_measured_body_gauss, h.heading_rad, att.roll_rad,
                                                 att.pitch_rad)

    def _deviation_learn(self, sol: NavSolution, mag_body_gauss: np.ndarray, t: float) -> None:
        """Calibration manoeuvre (METHODS.md D): one RLS update at DEVIATION_PERIOD_S against a
        heading that does not come from the magnetometer alone (A's solution or the trusted FC), on
        the MEASURED field: D's model holds the hard iron (A_i), so it must not learn on the field
        less mag_disturbance's hard-iron estimate, which moves while it learns (on the deviation
        bench's flights from 0 to ~30 mG mid-manoeuvre: the fit then mixed two offsets). After a
        re-learnt hard iron the calibration starts again (its data hold the old one)."""
        if t - self._deviation_last_s < DEVIATION_PERIOD_S or not sol.heading_valid:
            return
        if self._deviation_hard_iron_changed:
            self.deviation, self._deviation_hard_iron_changed = deviation_init(self.deviation_params), False
            self._deviation_coverage_reported = 0.0
            self._event("deviation", "calibration restarted: the hard iron was re-learnt (a magnet attached?)")
        sources = set(sol.heading_source.split("+"))
        if not sources & {"azimuth", "fc"} or sol.heading_sigma_rad is None \
                or sol.heading_sigma_rad > DEVIATION_MAX_REF_SIGMA_RAD:
            return
        self._deviation_last_s = t
        self.deviation, _ = self.core.deviation_step(self.deviation, mag_body_gauss, self.field.e_ned_gauss,
                                                     sol.heading_rad, sol.roll_rad, sol.pitch_rad,
                                                     self.deviation_params)
        cov = self.core.deviation_coverage(self.deviation, self.deviation_params).overall
        if cov >= self._deviation_coverage_reported + 0.25:
            self._deviation_coverage_reported = cov
            self._event("deviation", f"calibration manoeuvre coverage {cov:.2f}")

    def _declination_at_launch(self) -> None:
        """Method E on the rest before launch: a measured declination only if the gyros resolve
        Earth rate (the check says why not, and the WMM value stays); a local anomaly is flagged."""
        lat = self.cfg["site"]["lat_deg"]
        if lat is None:
            return
        res = estimate_declination(self.rest, math.radians(lat), self.field.declination_rad,
                                   self.declination_sigma_rad,
                                   DeclinationParams(gyro_bias_sigma_rad_s=self.gyro_bias_sigma_rad_s))
        self.declination_result = res
        self._event("declination", res.message)
        if res.anomaly:
            self._event("magnetic_anomaly", f"measured declination {math.degrees(res.measured_declination_rad):.1f} deg "
                        f"vs WMM {math.degrees(res.wmm_declination_rad):.1f} deg")
        if res.source == "measured":
            self.declination_rad = res.declination_rad
            self.declination_sigma_rad = res.sigma_rad

    def _start_flight(self, s: ImuSample) -> None:
        # method B drops the magnetometer bias it learnt at rest: the launcher's or the site's field
        # is gone a few metres up (synthetic_ahrs_takeoff)
        self.ahrs = self.core.synthetic_ahrs_takeoff(self.ahrs, self.ahrs_params)
        if self.ahrs_out is not None:
            self.ahrs_out = core_facade.synthetic_ahrs_output(self.ahrs, self.ahrs_params)  # either state
        level = self.phase.level
        if level is None:  # launched unlevelled: roll/pitch come from the attitude filter alone
            return
        self.gyro_bias_rad_s = level.gyro_bias_rad_s.copy()
        # yaw unknown at launch: 0 until a heading source exists
        self.strapdown = strapdown_init(quat_from_euler(level.roll_rad, level.pitch_rad, 0.0))
        self.strapdown, _ = self.core.strapdown_step(self.strapdown, s.gyro_rad_s - self.gyro_bias_rad_s,
                                                     s.time_fc_s, self.strapdown_params)

    def _tilt_sigma_rad(self, time_s: float) -> float | None:
        """1-sigma roll/pitch of the levelled + strapdown attitude: levelling error, then growing
        linearly with the residual gyro bias ``imu.gyro_bias_sigma_deg_s`` after launch."""
        level = self.phase.level
        if level is None:
            return None
        if self.phase.launch_time_s is None:
            return level.roll_sigma_rad
        return math.hypot(level.roll_sigma_rad, self.gyro_bias_sigma_rad_s * (time_s - self.phase.launch_time_s))

    def _readings(self, t: float, c_heading=False, a_status: str | None = None) -> tuple[list[SourceReading], list]:
        """Every heading source offered to the arbitration (service/heading_sources.py), and the
        ones not offered with why (NotOffered): (readings, not_offered). ``c_heading``: C's heading as
        the core read it (``_solution_attitude``: None before its first, else (heading, variance,
        source_available, rejected_since_s, last_mag_time_s)); False: read here. ``a_status``: method
        A's ``azimuth_status()`` (None: asked here)."""
        b = synthetic_ahrs_source(self.ahrs_out, self.b_health, t, False, self.use_fc_yaw)
        period = self.polar_hdg_params.mag_update_period_s
        if c_heading is False:
            c = heading_filter_source(self.core.polar_heading_estimate(self.polar_hdg), self.polar_hdg,
                                      self._hdg_measurement, t, False, period)
        elif c_heading is None:
            c = heading_filter_reading(False, math.nan, math.inf, None, None, self._hdg_measurement, t, period)
        else:
            c = heading_filter_reading(True, c_heading[0], c_heading[1], c_heading[3], c_heading[4],
                                       self._hdg_measurement, t, period)
        a = azimuth_source(self.azimuth_out, self.azimuth_status() if a_status is None else a_status, t,
                           self.a_check, (b, c), self.arb_params.gate_chi2)
        if isinstance(a, SourceReading) and a.consistent and self.a_check.more_certain:
            # A's solution agrees with B and C and is the more certain: they are not offered
            b, c = superseded(b), superseded(c)
        out = [a, b, c,
               fc_source(self.fc_attitude, self.ahrs_out, t, self.use_fc_heading, self.use_fc_yaw,
                         self.ahrs_params.fc_sigma_yaw_rad, self.arb_params.max_age_s)]
        return [r for r in out if isinstance(r, SourceReading)], [r for r in out if not isinstance(r, SourceReading)]

    def _deviation_record(self, t: float):
        """Method D's aiding record: is its correction applied to C's magnetometer (or why not)."""
        prev = self.aiding.get("deviation")
        cov = (deviation_coverage(self.deviation, self.deviation_params).overall
               if self.deviation is not None and self._deviation_in_use is False else None)
        rec = deviation_record(t, self.deviation, self.deviation_apply, self._deviation_in_use, cov,
                               self.deviation_min_coverage, prev.time_last_fused_s if prev else math.nan)
        if self._deviation_hard_iron_changed and rec.why_not == "not_applied":
            rec = rec._replace(detail="the hard iron was re-learnt (a magnet attached?) since its calibration")
        return rec

    def _feed_b1_heading(self, readings: list[SourceReading], t: float) -> None:
        """Variant B1 takes its heading from another source (METHODS.md B1): the most certain
        reading that is not B itself, at most every ``B1_HEADING_PERIOD_S``."""
        if t - self._b1_heading_s < B1_HEADING_PERIOD_S:
            return
        others = [r for r in readings if r.name != "synthetic_ahrs"]
        if others:
            best = min(others, key=lambda r: r.sigma_rad)
            self._b1_heading_s = t
            self._step_ahrs(HeadingEvent(t, best.heading_rad, best.sigma_rad))

    def _solution_attitude(self, t: float, att, rates_body: np.ndarray):
        """The solution's roll, pitch, their sigmas and the heading rate: (roll, pitch, roll sigma,
        pitch sigma, heading rate or None, C's heading as read by the core or False), None when there is
        no attitude yet. With the compiled core one call on the held filters (core/solution.hpp); the
        reads below are the reference (tests/test_core_solution.py proves them equal)."""
        if att is not None and self.solution_core and type(self.polar_att) is core_facade.HeldPolarAttitude \
                and type(self.polar_hdg) is core_facade.HeldPolarHeading:
            n = core_facade.solution_numbers(self.polar_att, self.polar_hdg, t, self._yaw_P_prev, rates_body)
            if n is not None:
                roll, pitch, roll_sigma, pitch_sigma, yaw_P, heading_rate, c_heading = n
                self._yaw_P_prev = (t, yaw_P)
                return roll, pitch, roll_sigma, pitch_sigma, heading_rate, c_heading
        # roll/pitch: the attitude filter once levelled, else the levelled/strapdown attitude
        if att is not None:
            roll, pitch = att.roll_rad, att.pitch_rad
            roll_sigma = math.sqrt(max(att.cov_roll_pitch_rad2[0, 0], 0.0))
            pitch_sigma = math.sqrt(max(att.cov_roll_pitch_rad2[1, 1], 0.0))
        else:
            q_ns = self.strapdown.q_ref_from_sensor if self.strapdown is not None else (
                quat_from_euler(self.phase.level.roll_rad, self.phase.level.pitch_rad, 0.0)
                if self.phase.level is not None else None)
            if q_ns is None:
                return None
            roll, pitch, _ = euler_from_quat(quat_mul(q_ns, self.q_sensor_from_body))
            roll_sigma = pitch_sigma = self._tilt_sigma_rad(t)
        heading_rate = None
        yaw_P = euler_from_quat(att.q_P_from_body)[2] if att is not None else None
        prev, self._yaw_P_prev = self._yaw_P_prev, (t, yaw_P) if yaw_P is not None else None
        if prev is not None and yaw_P is not None and t > prev[0]:
            # the yaw's change over the step from the full attitude: exact through pitch +-90 deg,
            # where the Euler rate below is singular
            heading_rate = wrap_pi(yaw_P - prev[1]) / (t - prev[0])
        elif abs(math.cos(pitch)) > 1e-3:  # psi_dot = (q sin(phi) + r cos(phi)) / cos(theta)
            heading_rate = (rates_body[1] * math.sin(roll) + rates_body[2] * math.cos(roll)) / math.cos(pitch)
        return roll, pitch, roll_sigma, pitch_sigma, heading_rate, False

    def _solution(self, s: ImuSample, gyro_sensor_rad_s: np.ndarray, att) -> NavSolution:
        t = s.time_fc_s
        rates_body = self.C_body_from_sensor @ (gyro_sensor_rad_s - self.gyro_bias_rad_s)
        a = self._solution_attitude(t, att, rates_body)
        if a is None:
            return NavSolution(t, s.time_rx_s, self.phase.phase, None, None, None, rates_body)
        roll, pitch, roll_sigma, pitch_sigma, heading_rate, c_heading = a
        if self.phase.phase == PRE_LAUNCH and self.phase.level is None and self.fc_armed:
            # armed and not levelled yet: the vehicle may be flying (the started-in-flight rule has
            # not decided), so the accelerometer-levelled attitude is only as good as in a turn
            wide = self.phase_params.in_flight.accel_tilt_sigma_rad
            roll_sigma, pitch_sigma = max(roll_sigma or 0.0, wide), max(pitch_sigma or 0.0, wide)
        a_status = self.azimuth_status()
        readings, not_offered = self._readings(t, c_heading, a_status)
        self.arb, arb_out = self.core.arbitrate(self.arb, readings, t, self.arb_params, heading_rate, not_offered)
        self.arb_out = arb_out
        self.aiding = {**arb_out.records, "deviation": self._deviation_record(t)}
        if self.ahrs_params.variant == "b1":
            self._feed_b1_heading(readings, t)
        for ev in arb_out.events:
            self._event("heading_" + ev.kind, ev.message)

        flags = {"azimuth": a_status}
        az = self.azimuth_out
        if self.phase.started_in_flight:
            flags["started_in_flight"] = self.phase.in_flight_evidence
        if self.ahrs_out is not None:
            flags["fc_reference"] = "trusted" if self.ahrs_out.reference_trusted else self.ahrs_out.reference_reason
        if self._hdg_available is False:
            flags["magnetometer_heading"] = "unavailable (horizontal field too weak)"
        flags["magnetometer"] = self.mag_status
        valid = arb_out.valid and arb_out.heading_rad is not None
        heading = arb_out.heading_rad if valid else None
        q_nb = self.core.polar_heading_attitude(self.polar_hdg, heading) if valid and att is not None else None
        if q_nb is None:   # (the platform attitude avoids the Euler split of roll and yaw at pitch +-90 deg)
            q_nb = quat_from_euler(roll, pitch, heading if valid else 0.0)
        return NavSolution(t, s.time_rx_s, self.phase.phase, q_nb, roll, pitch, rates_body,
                           roll_sigma_rad=roll_sigma, pitch_sigma_rad=pitch_sigma,
                           heading_rad=heading, heading_sigma_rad=arb_out.sigma_rad if valid else None,
                           heading_source=arb_out.source if valid else "none", heading_valid=valid,
                           azimuth_rad=az.azimuth_rad if az is not None and az.valid else None,
                           azimuth_sigma_rad=az.azimuth_sigma_rad if az is not None and az.valid else None,
                           flags=flags)
