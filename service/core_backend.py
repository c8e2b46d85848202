"""Which implementation runs the ported estimator parts: the compiled core or the Python reference.

``AZIMUTHD_CORE`` (environment): ``core`` (the default) runs the compiled core (estimators._core via
estimators/core.py) where it is ported and proven equal; ``python`` runs the Python reference
everywhere. When the core cannot be imported (a failed build, a foreign platform) the service says
so in one log line and runs the reference: it never stops for it. Both give the same results
(tests/test_core_*.py), so the choice is speed, not behaviour.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Callable

from estimators import core
from estimators import azimuth as _a_reference
from estimators import azimuth_fit as _af_reference
from estimators import mag_deviation as _dv_reference
from estimators import mag_disturbance as _md_reference
from estimators import mag_usability as _mu_reference
from estimators import polar_attitude as _c_reference
from estimators import polar_heading as _ch_reference
from estimators import synthetic_ahrs as _b_reference
from estimators import zero_rate as _zr_reference
from estimators.strapdown import strapdown_step as _strapdown_step_reference
from service.input_checks import CoreImuInputChecks, ImuInputChecks
from service import arbitration_core
from service import phases_core
from service.heading_arbitration import arbitrate as _arbitrate_reference
from service.phases import phase_step as _phase_step_reference
from service.hot_path import GroundState as _GroundStateReference
from service.hot_path import SampleState as _SampleStateReference

log = logging.getLogger("azimuthd.core")

ENV = "AZIMUTHD_CORE"
CHOICES = ("core", "python")
_said: set[str] = set()


@dataclass(frozen=True)
class Backend:
    name: str
    """"core" or "python": what runs."""
    why: str
    """One line: why this one (the request, or why the core is not there)."""
    strapdown_step: Callable
    """The Pipeline's one gyro propagation (estimators.strapdown.strapdown_step's signature)."""
    synthetic_ahrs_step: Callable = _b_reference.synthetic_ahrs_step
    """Method B's step (estimators.synthetic_ahrs.synthetic_ahrs_step's signature)."""
    synthetic_ahrs_unseen: Callable = _b_reference.synthetic_ahrs_unseen
    """Method B after an FC clock restart (estimators.synthetic_ahrs.synthetic_ahrs_unseen's signature)."""
    input_checks: Callable = ImuInputChecks
    """The IMU input checks' class (service/input_checks.py: ``cls(InputCheckParams)``)."""
    mag_usability_step: Callable = _mu_reference.mag_usability_step
    """The magnetometer usability (estimators.mag_usability.mag_usability_step's signature)."""
    mag_usability_stale: Callable = _mu_reference.mag_usability_stale
    """... when no magnetometer sample came (estimators.mag_usability.mag_usability_stale's signature)."""
    azimuth_propagate: Callable = _a_reference.azimuth_propagate
    """Method A's per-sample propagation (estimators.azimuth.azimuth_propagate's signature)."""
    mag_disturbance_step: Callable = _md_reference.mag_disturbance_step
    """Magnetic disturbances in motion (estimators.mag_disturbance.mag_disturbance_step's signature)."""
    polar_attitude_init: Callable = _c_reference.polar_attitude_init
    """Method C's attitude filter, a new one (estimators.polar_attitude.polar_attitude_init's signature) ..."""
    polar_attitude_init_at: Callable = _c_reference.polar_attitude_init_at
    """... started at a given roll/pitch (polar_attitude_init_at's signature) ..."""
    polar_attitude_step: Callable = _c_reference.polar_attitude_step
    """... one filter-rate sample (polar_attitude_step's signature) ..."""
    polar_attitude_estimate: Callable = _c_reference.polar_attitude_estimate
    """... its roll, pitch and covariance (polar_attitude_estimate's signature) ..."""
    polar_attitude_unseen: Callable = _c_reference.polar_attitude_unseen
    """... after an interval not seen (polar_attitude_unseen's signature) ..."""
    attitude_zero_rate_update: Callable = _zr_reference.attitude_zero_rate_update
    """... and its zero-rate update at rest (estimators.zero_rate.attitude_zero_rate_update's signature).
    The six take and give the same state: the reference's record, or the core's held one."""
    polar_heading_init: Callable = _ch_reference.polar_heading_init
    """Method C's heading filter, a new one (estimators.polar_heading.polar_heading_init's signature) ..."""
    polar_heading_step: Callable = _ch_reference.polar_heading_step
    """... one filter-rate step (polar_heading_step's signature) ..."""
    polar_heading_estimate: Callable = _ch_reference.polar_heading_estimate
    """... its heading and published variance (polar_heading_estimate's signature) ..."""
    polar_heading_attitude: Callable = _ch_reference.polar_heading_attitude
    """... the platform formulation's attitude (polar_heading_attitude's signature) ..."""
    polar_heading_unseen: Callable = _ch_reference.polar_heading_unseen
    """... after an interval not seen (polar_heading_unseen's signature) ..."""
    heading_zero_rate_update: Callable = _zr_reference.heading_zero_rate_update
    """... and its zero-rate update at rest (estimators.zero_rate.heading_zero_rate_update's signature).
    The six take and give the same state: the reference's record, or the core's held one."""
    phase_step: Callable = _phase_step_reference
    """The flight phases, one IMU sample (service.phases.phase_step's signature; takes and gives the
    reference's PhaseState or the core's held one)."""
    arbitrate: Callable = _arbitrate_reference
    """The heading arbitration (service.heading_arbitration.arbitrate's signature; the state is the
    reference's ArbitrationState in both, a pure value: service/arbitration_core.py)."""
    sample_state: Callable = _SampleStateReference
    """The Pipeline's per-sample fields (service/hot_path.py SampleState, or the core's twin)."""
    ground_state: Callable = _GroundStateReference
    """The Pipeline's ground state (service/hot_path.py GroundState, or the core's twin that also holds
    method A's delay line: the ground path then runs in the core)."""
    hot_run: Callable | None = None
    """The per-sample hot path behind Pipeline.on_imu_batch (estimators._core.hot_run; None: on_imu
    takes every sample)."""
    azimuth_fit_psi: Callable = _af_reference.fit_psi
    """Method A's re-solve (estimators.azimuth_fit.fit_psi's signature; the solver runs it) ..."""
    azimuth_orientation_diversity: Callable = _af_reference.orientation_diversity_rad
    """... and its orientation diversity (estimators.azimuth_fit.orientation_diversity_rad's signature)."""
    azimuth_output_numbers: Callable = _a_reference.azimuth_output_numbers
    """Method A's output numbers (estimators.azimuth.azimuth_output_numbers' signature)."""
    deviation_step: Callable = _dv_reference.deviation_step
    """Method D's RLS step (estimators.mag_deviation.deviation_step's signature) ..."""
    deviation_corrected_mag: Callable = _dv_reference.corrected_mag
    """... its corrected field (corrected_mag's signature) ..."""
    deviation_residual_sigma_gauss: Callable = _dv_reference.residual_sigma_gauss
    """... its residual sigma (residual_sigma_gauss's signature) ..."""
    deviation_coverage: Callable = _dv_reference.deviation_coverage
    """... and its coverage (deviation_coverage's signature). The four take the reference's
    DeviationState or the core's held one (estimators/core.py HeldDeviation, which reads like it)."""
    synthetic_ahrs_takeoff: Callable = core.synthetic_ahrs_takeoff
    """Method B at the take-off (estimators.synthetic_ahrs.synthetic_ahrs_takeoff's signature):
    estimators.core's, which takes either state (the reference's record: the reference itself)."""


def _say(level: int, text: str) -> None:
    """Each distinct line once per process (a replay builds many Pipelines)."""
    if text not in _said:
        _said.add(text)
        log.log(level, text)


def _phases_ported() -> bool:
    """The flight phases are in the core; one log line when the build predates them."""
    if not phases_core.PHASES_AVAILABLE:
        _say(logging.WARNING, "compiled core without the flight phases (an older build): they run the Python "
                              "reference")
    return phases_core.PHASES_AVAILABLE


def _arbitration_ported() -> dict:
    """The heading arbitration in the core (the Backend's field); one log line when the build predates it."""
    if not arbitration_core.ARBITRATION_AVAILABLE:
        _say(logging.WARNING, "compiled core without the heading arbitration (an older build): it runs the Python "
                              "reference")
        return {}
    return dict(arbitrate=arbitration_core.arbitrate)


def select(environ=os.environ) -> Backend:
    """The backend for ``AZIMUTHD_CORE`` in ``environ``; one log line when it is not the core."""
    want = environ.get(ENV, "").strip().lower() or "core"
    if want not in CHOICES:
        _say(logging.WARNING, f"{ENV}={environ.get(ENV)!r} is not one of {', '.join(CHOICES)}: using core")
        want = "core"
    if want == "python":
        why = f"{ENV}=python: the Python reference runs the estimators"
        _say(logging.INFO, why)
        return Backend("python", why, _strapdown_step_reference)
    if not core.AVAILABLE:
        why = f"compiled core not available ({core.IMPORT_ERROR}): the Python reference runs the estimators"
        _say(logging.WARNING, why)
        return Backend("python", why, _strapdown_step_reference)
    if not core.B_AVAILABLE:  # an extension built before method B was ported: B runs the reference
        _say(logging.WARNING, "compiled core without method B (an older build): B runs the Python reference")
        return Backend("core", "compiled core (estimators._core), method B in Python", core.strapdown_step_held)
    if not (core.CHECKS_AVAILABLE and core.MAG_USABILITY_AVAILABLE):  # built before the checks were ported
        _say(logging.WARNING, "compiled core without the input checks and the magnetometer usability (an older "
                              "build): they run the Python reference")
        return Backend("core", "compiled core (estimators._core), the checks in Python", core.strapdown_step_held,
                       core.synthetic_ahrs_step, core.synthetic_ahrs_unseen)
    if not core.AZIMUTH_AVAILABLE:  # built before method A's propagation was ported
        _say(logging.WARNING, "compiled core without method A's propagation (an older build): it runs the Python "
                              "reference")
        return Backend("core", "compiled core (estimators._core), method A's propagation in Python",
                       core.strapdown_step_held, core.synthetic_ahrs_step, core.synthetic_ahrs_unseen, CoreImuInputChecks,
                       core.mag_usability_step, core.mag_usability_stale)
    if not core.MAG_DISTURBANCE_AVAILABLE:  # built before mag_disturbance was ported
        _say(logging.WARNING, "compiled core without the magnetic-disturbance check (an older build): it runs the "
                              "Python reference")
        return Backend("core", "compiled core (estimators._core), mag_disturbance in Python", core.strapdown_step_held,
                       core.synthetic_ahrs_step, core.synthetic_ahrs_unseen, CoreImuInputChecks,
                       core.mag_usability_step, core.mag_usability_stale, core.azimuth_propagate)
    ported = (core.strapdown_step_held, core.synthetic_ahrs_step, core.synthetic_ahrs_unseen, CoreImuInputChecks,
              core.mag_usability_step, core.mag_usability_stale, core.azimuth_propagate, core.mag_disturbance_step)
    if not core.POLAR_AVAILABLE:  # built before method C's attitude filter was ported
        _say(logging.WARNING, "compiled core without method C's attitude filter (an older build): it runs the "
                              "Python reference")
        return Backend("core", "compiled core (estimators._core), C's attitude filter in Python", *ported)
    c_attitude = dict(polar_attitude_init=core.polar_attitude_init, polar_attitude_init_at=core.polar_attitude_init_at,
                      polar_attitude_step=core.polar_attitude_step, polar_attitude_estimate=core.polar_attitude_estimate,
                      polar_attitude_unseen=core.polar_attitude_unseen,
                      attitude_zero_rate_update=core.attitude_zero_rate_update)
    if not core.POLAR_HEADING_AVAILABLE:  # built before method C's heading filter was ported
        _say(logging.WARNING, "compiled core without method C's heading filter (an older build): it runs the "
                              "Python reference")
        return Backend("core", "compiled core (estimators._core), C's heading filter in Python", *ported,
                       **c_attitude)
    return Backend("core", "compiled core (estimators._core)", *ported, **c_attitude, **_arbitration_ported(),
                   polar_heading_init=core.polar_heading_init, polar_heading_step=core.polar_heading_step,
                   polar_heading_estimate=core.polar_heading_estimate,
                   polar_heading_attitude=core.polar_heading_attitude,
                   polar_heading_unseen=core.polar_heading_unseen,
                   heading_zero_rate_update=core.heading_zero_rate_update,
                   **(dict(phase_step=phases_core.phase_step) if _phases_ported() else {}),
                   **(dict(sample_state=core.SampleState, hot_run=core.hot_run) if core.HOT_PATH_AVAILABLE else {}),
                   **(dict(ground_state=core.GroundState) if core.GROUND_AVAILABLE and _phases_ported() else {}),
                   **(dict(azimuth_fit_psi=core.fit_psi) if core.FIT_AVAILABLE else {}),
                   **(dict(azimuth_orientation_diversity=core.orientation_diversity_rad)
                      if core.DIVERSITY_AVAILABLE else {}),
                   **(dict(azimuth_output_numbers=core.azimuth_output_numbers) if core.AZIMUTH_OUTPUT_AVAILABLE else {}),
                   **(dict(deviation_step=core.deviation_step, deviation_corrected_mag=core.corrected_mag,
                           deviation_residual_sigma_gauss=core.residual_sigma_gauss,
                           deviation_coverage=core.deviation_coverage) if core.DEVIATION_AVAILABLE else {}))
