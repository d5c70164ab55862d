"""The IMU's noise, time offset and lever arm from a recording (EuRoC layout), against its ground truth.

A sensor yaml holds guesses; a recording with motion capture says what the IMU does:

- **Time offset** (`time_offset`): the gyroscope against the ground truth's angular rate, cross-correlated
  per axis as angular accelerations (smoothed, differentiated: no bias, a sharp peak), the peak refined to a fraction of the grid by a parabola. Its
  sign is the tracker's (t_imu = t_camera + offset: the IMU's stamp of the moment the ground truth,
  and so the camera, stamps t_camera).
- **White noise** (`allan`): the Allan deviation at the shortest cluster time on still stretches
  (|rate| and the accelerometer's spread small for at least `min_still_s`), sigma(tau0) sqrt(tau0) =
  the density; without a still stretch, the same statistic on the residuals against the ground truth
  (an upper bound: the truth's own noise is in them).
- **Bias walk**: the slope of the Allan deviation of the gyro residual at long cluster times (rate random
  walk: sigma(tau) = K sqrt(tau / 3)).
- **Lever arm** (`lever_arm`): the accelerometer against the truth's specific force carried to the IMU
  by r, f = R^T (a - g) + alpha x r + w x (w x r), fitted by least squares with a constant bias; the
  residual RMS before and after says how much the unmodelled lever arm costs the filter.

No filter runs here: plain numpy over the whole recording.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from flextrack.formats import euroc
from flextrack.geometry import so3

STANDARD_GRAVITY = 9.80665
GRID_S = 0.001  # the cross-correlation's grid
GLITCH = 8.0  # a gyro-truth disagreement this many times its median: the truth jumped (motion capture swaps
# markers or loses them), the gyro did not; a tracker scored on that truth is scored wrong there
MAX_OFFSET_S = 0.2  # searched either way
SMOOTH_S = 0.03  # the cross-correlation's smoothing before it differentiates


@dataclass
class ImuCalibration:
    """What `calibrate` finds (SI units; densities in Kalibr's continuous-time units)."""

    rate_hz: float  # the median sample rate
    gaps: int  # intervals longer than 5 nominal ones
    longest_gap_s: float
    time_offset_ms: float  # t_imu = t_camera + offset, gyro vs the truth's rate
    time_offset_peak: float  # the normalised cross-correlation at the peak (1: identical shapes)
    still_s: float  # seconds of still stretches found
    gyroscope_noise_density: float  # rad/s/sqrt(Hz)
    accelerometer_noise_density: float  # m/s^2/sqrt(Hz)
    noise_from: str  # "still" or "residual"
    gyroscope_random_walk: float  # rad/s^2/sqrt(Hz), from the residual's long-tau Allan deviation
    gyro_residual_rms: float  # rad/s, gyro minus the truth's rate (offset and slow bias removed)
    accel_residual_rms: float  # m/s^2 without a lever arm
    accel_residual_rms_lever: float  # m/s^2 with the fitted one
    lever_arm_m: tuple[float, float, float]  # truth's origin to the IMU, body frame
    truth_jumps: list[float]  # seconds from the IMU's start where |gyro - the truth's rate| passed GLITCH x its median

    def as_dict(self) -> dict:
        return asdict(self)


def body_rates(gt: euroc.GroundTruth) -> tuple[np.ndarray, np.ndarray]:
    """(t s, (N, 3) body angular rate) from the truth's orientations by central differences."""
    R = np.stack([so3.matrix_from_quat(q) for q in gt.q_WB])
    t = gt.t_ns * 1e-9
    rel = np.einsum("nji,njk->nik", R[:-2], R[2:])  # R_k-1^T R_k+1
    w = np.stack([so3.log(r) for r in rel]) / (t[2:] - t[:-2])[:, None]
    return t[1:-1], w


def _highpass(x: np.ndarray, dt: float, tau_s: float) -> np.ndarray:
    """x minus its moving average over tau_s (removes a bias that walks; over all of x when shorter)."""
    n = max(1, min(round(tau_s / dt), len(x)))
    kernel = np.ones(n) / n
    return x - np.stack([np.convolve(x[:, k], kernel, mode="same") for k in range(x.shape[1])], axis=1)


def _on_grid(t: np.ndarray, x: np.ndarray, grid: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(grid, t, x[:, k]) for k in range(x.shape[1])], axis=1)


def _valid_grid(t_imu: np.ndarray, grid: np.ndarray, max_gap_s: float) -> np.ndarray:
    """Grid points that lie between two IMU samples at most max_gap_s apart (not inside a gap)."""
    i = np.clip(np.searchsorted(t_imu, grid), 1, len(t_imu) - 1)
    return (t_imu[i] - t_imu[i - 1] <= max_gap_s) & (grid >= t_imu[0]) & (grid <= t_imu[-1])


def _rate_change(t: np.ndarray, w: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """The angular acceleration on `grid`: w interpolated, smoothed over SMOOTH_S, differentiated. Hand
    motion's rates are slow (their own cross-correlation peaks broadly: 16 and 21 ms scored within 0.2 %
    of each other); the derivative whitens them and removes the gyro's bias."""
    n = max(1, round(SMOOTH_S / GRID_S))
    k = np.ones(n) / n
    w = _on_grid(t, w, grid)
    return np.gradient(np.stack([np.convolve(w[:, j], k, "same") for j in range(3)], axis=1), axis=0)


def time_offset(imu: euroc.ImuData, gt: euroc.GroundTruth) -> tuple[float, float]:
    """(offset s, normalised peak correlation): gyro(t) best matches the truth's rate at t - offset (nan when
    the best is at the edge of the +-MAX_OFFSET_S searched)."""
    t0 = int(imu.t_ns[0])
    t_gt, w_gt = body_rates(gt)
    t_gt = t_gt - t0 * 1e-9  # seconds from the first sample: 1 ms steps lose no precision
    t_imu = (imu.t_ns - t0) * 1e-9
    edge = MAX_OFFSET_S + 2 * SMOOTH_S
    grid = np.arange(max(t_imu[0], t_gt[0]) + edge, min(t_imu[-1], t_gt[-1]) - edge, GRID_S)
    ok = _valid_grid(t_imu, grid, 5 * float(np.median(np.diff(t_imu))))
    a = _rate_change(t_imu, imu.gyro, grid)[ok]
    m = round(MAX_OFFSET_S / GRID_S)
    lags = np.arange(-m, m + 1)
    wide = grid[0] + (np.arange(len(grid) + 2 * m) - m) * GRID_S  # the truth's grid, lags either side
    ref = _rate_change(t_gt, w_gt, wide)
    score = np.empty(len(lags))
    for n, lag in enumerate(lags):  # the truth at grid - lag: wide's index k + m - lag
        b = ref[m - lag:m - lag + len(grid)][ok]
        score[n] = float(np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b)))
    k = int(np.argmax(score))
    if not 0 < k < len(lags) - 1:  # the best at the search's edge: no peak (a recording too short or too still)
        return float("nan"), float(score[k])
    y0, y1, y2 = score[k - 1:k + 2]
    den = y0 - 2 * y1 + y2
    frac = 0.5 * (y0 - y2) / den if den < 0 else 0.0
    return float((lags[k] + frac) * GRID_S), float(score[k])


def allan_deviation(x: np.ndarray, dt: float, m: int) -> np.ndarray:
    """Overlapping Allan deviation per column of x (samples dt apart) at cluster size m."""
    c = np.cumsum(np.vstack([np.zeros((1, x.shape[1])), x]), axis=0)
    if len(x) < 2 * m + 1:
        return np.full(x.shape[1], np.nan)
    means = (c[m:] - c[:-m]) / m
    d = means[m:] - means[:-m]
    return np.sqrt(0.5 * np.mean(d * d, axis=0))


def still_mask(imu: euroc.ImuData, w_gt_at_imu: np.ndarray, min_still_s: float = 1.0,
               max_rate: float = 0.05, max_accel_std: float = 0.1) -> np.ndarray:
    """Samples in runs of at least min_still_s where the truth turns slower than max_rate and the
    accelerometer's 0.25 s spread stays below max_accel_std."""
    t = imu.t_ns * 1e-9
    dt = float(np.median(np.diff(t)))
    n = max(2, round(0.25 / dt))
    a = imu.accel
    k = np.ones(n) / n
    var = sum(np.convolve(a[:, j] ** 2, k, "same") - np.convolve(a[:, j], k, "same") ** 2 for j in range(3))
    calm = (np.linalg.norm(w_gt_at_imu, axis=1) < max_rate) & (np.sqrt(np.maximum(var, 0)) < max_accel_std)
    calm[1:] &= np.diff(t) < 5 * dt
    out = np.zeros_like(calm)
    start = None
    for i, c in enumerate(np.r_[calm, False]):
        if c and start is None:
            start = i
        elif not c and start is not None:
            if t[i - 1] - t[start] >= min_still_s:
                out[start:i] = True
            start = None
    return out


def _specific_force(gt: euroc.GroundTruth, t: np.ndarray, R: np.ndarray, smooth_s: float = 0.05) -> np.ndarray:
    """R^T (a - g) at the truth's samples, a by twice-smoothed differences of the positions."""
    dt = float(np.median(np.diff(t)))
    n = max(1, round(smooth_s / dt))
    k = np.ones(n) / n
    p = np.stack([np.convolve(gt.p_WB[:, j], k, "same") for j in range(3)], axis=1)
    v = np.gradient(p, t, axis=0)
    v = np.stack([np.convolve(v[:, j], k, "same") for j in range(3)], axis=1)
    a = np.gradient(v, t, axis=0)
    return np.einsum("nji,nj->ni", R, a + np.array([0.0, 0.0, STANDARD_GRAVITY]))


def lever_arm(imu: euroc.ImuData, gt: euroc.GroundTruth, offset_s: float) -> tuple[np.ndarray, float, float]:
    """(r m, residual RMS without, with r): the accelerometer against the truth's specific force."""
    t_gt = gt.t_ns * 1e-9
    R = np.stack([so3.matrix_from_quat(q) for q in gt.q_WB])
    f = _specific_force(gt, t_gt, R)
    tw, w = body_rates(gt)
    w = _on_grid(tw, w, t_gt)
    alpha = np.gradient(w, t_gt, axis=0)
    t_imu = imu.t_ns * 1e-9 - offset_s  # on the truth's clock
    edge = 0.5
    ok = (t_gt > max(t_gt[0], t_imu[0]) + edge) & (t_gt < min(t_gt[-1], t_imu[-1]) - edge)
    ok &= _valid_grid(t_imu, t_gt, 5 * float(np.median(np.diff(t_imu))))
    meas = _on_grid(t_imu, imu.accel, t_gt)[ok]
    f, w, alpha = f[ok], w[ok], alpha[ok]
    # f_meas - f = A r + b, A = [alpha]x + [w]x^2 per sample
    A = so3.skew_batch(alpha) + np.einsum("nij,njk->nik", so3.skew_batch(w), so3.skew_batch(w))
    y = (meas - f).reshape(-1)
    X = np.hstack([A.reshape(-1, 3), np.tile(np.eye(3), (len(f), 1))])
    sol, *_ = np.linalg.lstsq(X, y, rcond=None)
    before = y - np.tile(np.eye(3), (len(f), 1)) @ np.mean((meas - f), axis=0)
    after = y - X @ sol
    return sol[:3], float(np.sqrt(np.mean(before ** 2) * 3)), float(np.sqrt(np.mean(after ** 2) * 3))


def recording(data: Path) -> tuple[euroc.ImuData, euroc.GroundTruth]:
    """The IMU and the ground truth of a EuRoC-layout folder (flat, as `shared/data`'s, or mav0/)."""
    return (euroc.read_imu(_file(data, "imu0.csv", "imu0/data.csv")),
            euroc.read_groundtruth(_file(data, "groundtruth.csv", "state_groundtruth_estimate0/data.csv")))


def calibrate(data: Path) -> ImuCalibration:
    """Everything above, for the recording in `data` (imu0.csv and groundtruth.csv, EuRoC columns)."""
    imu, gt = recording(data)
    t = imu.t_ns * 1e-9
    steps = np.diff(t)
    nominal = float(np.median(steps))
    found_offset, peak = time_offset(imu, gt)
    offset = found_offset if np.isfinite(found_offset) else 0.0  # the residuals below need some alignment
    tw, w_gt = body_rates(gt)
    w_at = _on_grid(tw + offset, w_gt, t)
    still = still_mask(imu, w_at)
    inside = (t > tw[0] + offset + 0.5) & (t < tw[-1] + offset - 0.5)
    resid = imu.gyro - w_at
    bias = resid - _highpass(resid, nominal, 10.0)
    gyro_res = _highpass(resid, nominal, 10.0)[inside]
    if still.sum() * nominal >= 1.0:
        runs = np.split(np.where(still)[0], np.where(np.diff(np.where(still)[0]) > 1)[0] + 1)
        g_ad = np.mean([allan_deviation(imu.gyro[r], nominal, 1) for r in runs], axis=0)
        a_ad = np.mean([allan_deviation(imu.accel[r], nominal, 1) for r in runs], axis=0)
        source = "still"
    else:
        g_ad = allan_deviation(gyro_res, nominal, 1)
        a_ad = allan_deviation(_highpass(imu.accel, nominal, 0.05)[inside], nominal, 1)
        source = "residual"
    # rate random walk from the slow bias: its Allan deviation at ~10 s = K sqrt(tau / 3)
    m = max(1, round(10.0 / nominal))
    k_rw = float(np.mean(allan_deviation(bias[inside], nominal, m)) / np.sqrt(m * nominal / 3.0))
    r, before, after = lever_arm(imu, gt, offset)
    jumps = _jump_starts(t, resid, inside)
    return ImuCalibration(
        rate_hz=1.0 / nominal, gaps=int(np.sum(steps > 5 * nominal)), longest_gap_s=float(steps.max()),
        time_offset_ms=found_offset * 1e3, time_offset_peak=peak, still_s=float(still.sum() * nominal),
        gyroscope_noise_density=float(np.mean(g_ad) * np.sqrt(nominal)),
        accelerometer_noise_density=float(np.mean(a_ad) * np.sqrt(nominal)), noise_from=source,
        gyroscope_random_walk=k_rw, gyro_residual_rms=float(np.sqrt(np.mean(gyro_res ** 2) * 3)),
        accel_residual_rms=before, accel_residual_rms_lever=after, lever_arm_m=tuple(float(x) for x in r),
        truth_jumps=[round(float(x - t[0]), 2) for x in jumps])


def truth_jumps(imu: euroc.ImuData, gt: euroc.GroundTruth, offset_s: float) -> np.ndarray:
    """The moments (the IMU's clock, s) the truth jumped where the gyro did not, with the camera-IMU offset
    `offset_s` (`time_offset`): a tracker scored on the truth there is scored against a pose that was never the
    device's (`flextrack experiment euroc` sets those frames aside)."""
    t = imu.t_ns * 1e-9
    if len(gt.t_ns) < 3:
        return np.zeros(0)
    tw, w_gt = body_rates(gt)
    inside = (t > tw[0] + offset_s + 0.5) & (t < tw[-1] + offset_s - 0.5)
    return _jump_starts(t, imu.gyro - _on_grid(tw + offset_s, w_gt, t), inside) if inside.any() else np.zeros(0)


def _jump_starts(t: np.ndarray, resid: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Times where |gyro - the truth's rate| passed GLITCH x its median inside the truth's span, the first of
    each run (runs 0.5 s apart)."""
    disagree = np.linalg.norm(resid, axis=1) * inside
    jumps = np.flatnonzero(disagree > GLITCH * np.median(disagree[inside]))
    return t[jumps[np.r_[True, np.diff(t[jumps]) > 0.5]]] if len(jumps) else np.zeros(0)


def _file(data: Path, *names: str) -> Path:
    for name in names:
        for base in (data, data / "mav0"):
            if (base / name).is_file():
                return base / name
    raise FileNotFoundError(f"{data}: no {' or '.join(names)} (a EuRoC-layout recording, see docs/own-data.md)")
