"""Levelling and gyro bias at rest (METHODS.md A step 2, "block 305").

Averages of the specific force f (m/s^2, sensor axes) and the rate (rad/s) over a still period:

    roll  phi   = atan2(-f_y, -f_z)
    pitch theta = atan2( f_x, sqrt(f_y^2 + f_z^2))

with f the specific force (at rest and level, f = [0, 0, -g] in FRD). The gyro mean is the
pre-launch gyro bias.

Stillness is judged by what the levelling needs: how well the MEANS are known, not how quiet each
sample is. A stationary vehicle with its motors spinning has a vibrating accelerometer (std ~1
m/s^2 at the blade-pass frequency) whose mean is still gravity. So the tests are on the standard
error of the mean (SEM):

    SEM_f   = max(std_f / sqrt(n), std(batch means of f) / sqrt(n_batches))      per axis
    tilt noise = |SEM_f[x,y]| / |f|  must stay below ``max_tilt_noise_rad``
    SEM_w   (same for the rate) must stay below ``max_gyro_sem_rad_s`` (the gyro bias accuracy)

The batch-means term (batches of ``batch_s`` seconds, when the samples carry their time) is the
standard estimator of the SEM of correlated data: a vibration aliased to a low frequency, or a
slow motion (a handled vehicle, a tilt that drifts), makes the batch means spread and fails the
test, where white noise would not. The per-sample std is only bounded by a vibration ceiling
(``max_accel_std_m_s2``, ``max_gyro_std_rad_s``): beyond it the vehicle is moving, not vibrating.
Enough data is a count (``min_samples``, the statistics' floor) and, for timed samples, a
duration (``min_duration_s``), so a 25 Hz stream levels on the same seconds as a 200 Hz one.

Pure and incremental: ``levelling_step(state, gyro, accel, time_s=None) -> state`` (Welford sums,
batch means when timed), and ``levelling_result(state, params)`` that says whether there is enough
still data and why not, with the figures.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from estimators.rotations import dcm_from_euler, quat_from_euler

STANDARD_GRAVITY_M_S2 = 9.80665


@dataclass(frozen=True)
class LevellingParams:
    min_samples: int = 200
    """Samples needed before a result is given (the statistics' floor; the service sets 20: 1 s
    at 20 Hz, the block duration is its still_seconds)."""
    min_duration_s: float = 0.5
    """Timed samples must span at least this (s)."""
    max_accel_std_m_s2: float = 3.0
    """Vibration ceiling: a per-axis std of f above this is motion, not a vibrating vehicle at rest."""
    max_gyro_std_rad_s: float = math.radians(10.0)
    """Vibration ceiling of the rate (per-axis std)."""
    max_tilt_noise_rad: float = math.radians(0.5)
    """Largest tilt error the noise of the mean may give: SEM_f(x, y) / |f| (below the 0.6 deg of
    the default accelerometer-bias allowance)."""
    max_gyro_sem_rad_s: float = math.radians(0.1)
    """Largest standard error of the gyro mean (the gyro bias accuracy the levelling gives)."""
    batch_s: float = 0.25
    """Batch length of the batch-means SEM (timed samples, s)."""
    min_batches: int = 4
    """Batches needed before the batch-means SEM is used."""
    gravity_tolerance_m_s2: float = 0.8
    """| |f| - g | above this means the vehicle is not at rest (or the accel is mis-scaled)."""
    accel_bias_sigma_m_s2: float = 0.1
    """1-sigma accelerometer bias left after the FC's calibration; it tilts the levelling by
    about bias/g and no averaging removes it (0.1 m/s^2 -> 0.6 deg: consumer MEMS)."""


@dataclass(frozen=True)
class LevellingState:
    n: int = 0
    accel_mean_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_m2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_mean_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_m2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    t_first_s: float | None = None
    """Time of the first timed sample (None: untimed)."""
    t_last_s: float | None = None
    batch: tuple = ()
    """Open batch: (t0_s, n, accel sum (3), gyro sum (3)) as Python floats; () = none."""
    nb: int = 0
    """Closed batches."""
    batch_stats: tuple = ()
    """Welford over the closed batches' means: (accel mean, accel m2, gyro mean, gyro m2), lists."""


@dataclass(frozen=True)
class LevellingResult:
    ok: bool
    reason: str
    roll_rad: float = math.nan
    pitch_rad: float = math.nan
    gyro_bias_rad_s: np.ndarray | None = None
    accel_mean_m_s2: np.ndarray | None = None
    roll_sigma_rad: float = math.nan
    pitch_sigma_rad: float = math.nan
    samples: int = 0
    duration_s: float = math.nan
    """Span of the timed samples (nan: untimed)."""
    accel_std_m_s2: float = math.nan
    """Largest per-axis std of f (the vibration level)."""
    tilt_noise_rad: float = math.nan
    """Tilt error from the noise of the mean (SEM), without the accelerometer-bias allowance."""
    gyro_bias_sigma_rad_s: float = math.nan
    """Largest per-axis SEM of the rate: the accuracy of gyro_bias_rad_s."""
    noisy: bool = False
    """Failed only because the means are not known well enough yet (vibration): more of the same
    data would level (``levelling_merge``)."""

    def figures(self) -> str:
        """The figures behind the verdict, for an event."""
        rate = (f" ({self.samples / self.duration_s:.0f} Hz over {self.duration_s:.1f} s)"
                if math.isfinite(self.duration_s) and self.duration_s > 0 else "")
        out = f"{self.samples} samples{rate}"
        if math.isfinite(self.accel_std_m_s2):
            out += f", accel std {self.accel_std_m_s2:.2f} m/s^2"
        if math.isfinite(self.tilt_noise_rad):
            out += f", tilt noise {math.degrees(self.tilt_noise_rad):.2f} deg"
        if math.isfinite(self.gyro_bias_sigma_rad_s):
            out += f", gyro bias sigma {math.degrees(self.gyro_bias_sigma_rad_s):.3f} deg/s"
        return out


def levelling_step(state: LevellingState, gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray,
                   time_s: float | None = None, batch_s: float = LevellingParams.batch_s) -> LevellingState:
    """Add one sample (Welford's running mean and sum of squared deviations).

    Per component: d = x - mean; mean' = mean + d/n; m2' = m2 + d (x - mean'). Done on Python
    floats (the same IEEE operations as the numpy form, several times cheaper on 3-vectors).
    With ``time_s`` the samples are also cut into batches of ``batch_s`` whose means feed a
    second Welford sum (the batch-means SEM, module docstring)."""
    g = np.asarray(gyro_rad_s, float).tolist()
    a = np.asarray(accel_m_s2, float).tolist()
    if not all(map(math.isfinite, g + a)):
        return state
    n = state.n + 1
    am, am2 = _welford(a, state.accel_mean_m_s2.tolist(), state.accel_m2.tolist(), n)
    gm, gm2 = _welford(g, state.gyro_mean_rad_s.tolist(), state.gyro_m2.tolist(), n)
    if time_s is None or not math.isfinite(time_s):
        return LevellingState(n, np.array(am), np.array(am2), np.array(gm), np.array(gm2),
                              state.t_first_s, state.t_last_s, state.batch, state.nb, state.batch_stats)
    batch, nb, stats = state.batch, state.nb, state.batch_stats
    if batch and time_s - batch[0] >= batch_s:  # close the open batch, start a new one here
        k = batch[1]
        nb += 1
        bam, bgm = [x / k for x in batch[2]], [x / k for x in batch[3]]
        if stats:
            sam, sam2 = _welford(bam, stats[0], stats[1], nb)
            sgm, sgm2 = _welford(bgm, stats[2], stats[3], nb)
        else:
            sam, sam2, sgm, sgm2 = bam, [0.0] * 3, bgm, [0.0] * 3
        stats, batch = (sam, sam2, sgm, sgm2), ()
    if not batch:
        batch = (time_s, 1, a, g)
    else:
        batch = (batch[0], batch[1] + 1, [x + y for x, y in zip(batch[2], a)],
                 [x + y for x, y in zip(batch[3], g)])
    t_first = state.t_first_s if state.t_first_s is not None else time_s
    return LevellingState(n, np.array(am), np.array(am2), np.array(gm), np.array(gm2),
                          t_first, time_s, batch, nb, stats)


def _welford(x: list, mean: list, m2: list, n: int) -> tuple[list, list]:
    new_mean = []
    new_m2 = []
    for xi, mi, si in zip(x, mean, m2):
        d = xi - mi
        mn = mi + d / n
        new_mean.append(mn)
        new_m2.append(si + d * (xi - mn))
    return new_mean, new_m2


def _chan(n_a: int, mean_a, m2_a, n_b: int, mean_b, m2_b):
    """Two Welford sums combined (Chan et al.): n = n_a + n_b, d = mean_b - mean_a,
    mean = mean_a + d n_b / n, m2 = m2_a + m2_b + d^2 n_a n_b / n."""
    n = n_a + n_b
    d = np.asarray(mean_b, float) - np.asarray(mean_a, float)
    return (np.asarray(mean_a, float) + d * (n_b / n),
            np.asarray(m2_a, float) + np.asarray(m2_b, float) + d * d * (n_a * n_b / n))


def levelling_merge(a: LevellingState, b: LevellingState) -> LevellingState:
    """Two consecutive blocks as one (a before b): a vibrating vehicle whose 2 s blocks each fail
    only for the noise of their means levels on the longer window. The batch-means sums are
    combined too (an open batch of ``a`` is dropped), so motion between the blocks still shows."""
    if a.n == 0:
        return b
    if b.n == 0:
        return a
    am, am2 = _chan(a.n, a.accel_mean_m_s2, a.accel_m2, b.n, b.accel_mean_m_s2, b.accel_m2)
    gm, gm2 = _chan(a.n, a.gyro_mean_rad_s, a.gyro_m2, b.n, b.gyro_mean_rad_s, b.gyro_m2)
    nb, stats = b.nb, b.batch_stats
    if a.nb and b.nb:
        sam, sam2 = _chan(a.nb, a.batch_stats[0], a.batch_stats[1], b.nb, b.batch_stats[0], b.batch_stats[1])
        sgm, sgm2 = _chan(a.nb, a.batch_stats[2], a.batch_stats[3], b.nb, b.batch_stats[2], b.batch_stats[3])
        nb, stats = a.nb + b.nb, (sam.tolist(), sam2.tolist(), sgm.tolist(), sgm2.tolist())
    elif a.nb:
        nb, stats = a.nb, a.batch_stats
    return LevellingState(a.n + b.n, am, am2, gm, gm2, a.t_first_s if a.t_first_s is not None else b.t_first_s,
                          b.t_last_s if b.t_last_s is not None else a.t_last_s, b.batch, nb, stats)


def roll_pitch_from_specific_force(f_m_s2: np.ndarray) -> tuple[float, float]:
    """Roll and pitch (rad) of the sensor frame from a specific force at rest."""
    fx, fy, fz = (float(v) for v in f_m_s2)
    return math.atan2(-fy, -fz), math.atan2(fx, math.hypot(fy, fz))


def levelling_sem(state: LevellingState, params: LevellingParams = LevellingParams()
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis standard errors of the accel and gyro means: the larger of the white-noise form
    std/sqrt(n) and the batch-means form std(batch means)/sqrt(n_batches) (module docstring)."""
    n = state.n
    sem_a = np.sqrt(state.accel_m2 / (n - 1) / n)
    sem_g = np.sqrt(state.gyro_m2 / (n - 1) / n)
    if state.nb >= params.min_batches:
        nb = state.nb
        sem_a = np.maximum(sem_a, np.sqrt(np.asarray(state.batch_stats[1]) / (nb - 1) / nb))
        sem_g = np.maximum(sem_g, np.sqrt(np.asarray(state.batch_stats[3]) / (nb - 1) / nb))
    return sem_a, sem_g


def levelling_result(state: LevellingState, params: LevellingParams = LevellingParams()) -> LevellingResult:
    n = state.n
    dur = (state.t_last_s - state.t_first_s) if state.t_first_s is not None else math.nan
    if n < max(params.min_samples, 2):
        rate = f" in {dur:.1f} s ({n / dur:.0f} Hz)" if math.isfinite(dur) and dur > 0 else ""
        return LevellingResult(False, f"{n} of {params.min_samples} still samples{rate}", samples=n,
                               duration_s=dur)
    if math.isfinite(dur) and dur < params.min_duration_s:
        return LevellingResult(False, f"{dur:.2f} s of {params.min_duration_s:g} s of still samples",
                               samples=n, duration_s=dur)
    accel_std = np.sqrt(state.accel_m2 / (n - 1))
    gyro_std = np.sqrt(state.gyro_m2 / (n - 1))
    sem_a, sem_g = levelling_sem(state, params)
    f = state.accel_mean_m_s2
    norm = float(np.linalg.norm(f))
    tilt_noise = float(np.linalg.norm(sem_a[:2])) / max(norm, 1e-9)
    figs = dict(samples=n, duration_s=dur, accel_std_m_s2=float(np.max(accel_std)), tilt_noise_rad=tilt_noise,
                gyro_bias_sigma_rad_s=float(np.max(sem_g)))
    if np.max(accel_std) > params.max_accel_std_m_s2:
        return LevellingResult(False, f"accelerometer not still: moving (std {np.max(accel_std):.3f} m/s^2 > "
                               f"{params.max_accel_std_m_s2:g})", **figs)
    if np.max(gyro_std) > params.max_gyro_std_rad_s:
        return LevellingResult(False, f"gyro not still: moving (std {math.degrees(np.max(gyro_std)):.3f} deg/s > "
                               f"{math.degrees(params.max_gyro_std_rad_s):g})", **figs)
    if tilt_noise > params.max_tilt_noise_rad:
        return LevellingResult(False, f"accelerometer not still: its mean gives a tilt noise of "
                               f"{math.degrees(tilt_noise):.2f} deg > {math.degrees(params.max_tilt_noise_rad):g} deg "
                               f"(std {np.max(accel_std):.2f} m/s^2)", noisy=True, **figs)
    if np.max(sem_g) > params.max_gyro_sem_rad_s:
        return LevellingResult(False, f"gyro not still: its mean is uncertain by {math.degrees(np.max(sem_g)):.3f} "
                               f"deg/s > {math.degrees(params.max_gyro_sem_rad_s):g} deg/s", noisy=True, **figs)
    if abs(norm - STANDARD_GRAVITY_M_S2) > params.gravity_tolerance_m_s2:
        return LevellingResult(False, f"|f| = {norm:.2f} m/s^2 is not gravity", **figs)
    roll, pitch = roll_pitch_from_specific_force(f)
    # sigma of the tilt: noise of the mean (SEM) and the accelerometer bias, over |g|
    tilt_sigma = math.hypot(tilt_noise, params.accel_bias_sigma_m_s2 / norm)
    return LevellingResult(True, "", roll, pitch, state.gyro_mean_rad_s.copy(), f.copy(),
                           tilt_sigma, tilt_sigma, **figs)


def q_level_from_sensor(roll_rad: float, pitch_rad: float, yaw_rad: float = 0.0) -> np.ndarray:
    """q_nav_from_sensor for a levelled sensor with an assumed yaw (0 when heading unknown)."""
    return quat_from_euler(roll_rad, pitch_rad, yaw_rad)


def C_level_from_sensor(roll_rad: float, pitch_rad: float) -> np.ndarray:
    return dcm_from_euler(roll_rad, pitch_rad, 0.0)
