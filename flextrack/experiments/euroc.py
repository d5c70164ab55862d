"""Real IMU: a recording in the EuRoC layout (by default EuRoC V1_02_medium: ADIS16448 at 200 Hz, Vicon
ground truth; `--data` for one's own, docs/own-data.md) with a virtual object placed where cam0 sees it, tracked against the Noisy oracle, with and without BSCM (a table like
the paper's Table 4, which used its own RealSense recordings at 52 FPS).

The converter starts the frames inside the MAV's ~0.7 s of stillness, so the tracker initialises
as designed (gravity and gyro bias from 0.5 s of still IMU). The MAV flies about a room, 1-4 m
from anything: the virtual object is the default one scaled by `OBJECT_SCALE` (a 58 cm box), which
the placement puts where cam0 sees it whole and large enough for the PIA in the most frames
(~23 % of them: the MAV looks everywhere). Out of view, the tracker reports TRACKING_LOST and the
oracle answers OBJECT_NOT_FOUND; back in view, the tracker re-acquires from the next backend pose.
Errors are scored on the frames whose ground truth puts the object's centre in the image (the
paper's sequences kept the object in view) and that the tracker calls FINE: the paper accepts a
pose only then ("other statuses are classified as failures"). The report also gives the share of
in-view frames with a FINE pose and the error over all in-view frames, failures included. Frames at the
moments the motion capture jumped where the gyro did not (`calibration.imu.truth_jumps`) are set aside:
counted in view, not scored, the worst FINE one among them reported beside.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np

from client_sdk import TrackerOptions
from client_sdk.network_model import NetworkOptions
from flextrack.experiments import common, paper, plots
from flextrack.formats import sequence as sequence_io
from flextrack.runners.replay import ReplayOptions
from flextrack.runners.scoring import NothingScored, account, in_view_only

HEADER = ["variant", "pos_mm", "ori_deg", "proj_px", "jitter_px", "nees_mean", "worst_fine_px", "fine_share",
          "time_offset_ms", "time_offset_sigma_ms", "offset_xcorr_ms", "set_aside_frames", "worst_set_aside_px"]
DEFAULT_DATA = Path(__file__).resolve().parents[3] / "shared" / "data" / "euroc_v1_02_medium"
# "full": the paper-faithful tracker; "filter": the error-state Kalman filter (flextrack.experiments.common.FILTER)
VARIANTS = {"full": common.PAPER_FAITHFUL, "bscm_off": TrackerOptions(fusion="paper", bscm=False),
            "filter": common.FILTER}
FPS = paper.EUROC_FPS
OBJECT_SCALE = 4.0  # see module doc
# the frames set aside around a jump of the truth (camera clock): from just before the jump's first sample (the
# truth's rate is a central difference) until the filter can have re-synchronised with the answers, which carry
# the jumped truth: max_rejections (3) gated answers at ~16 a second, plus one round trip
DOUBTFUL_BEFORE_S, DOUBTFUL_AFTER_S = 0.05, 0.3


def run(out: Path, data: Path = DEFAULT_DATA, seed: int = 0, in_process: bool = False, fps: float = FPS,
        tracker: tuple[str, TrackerOptions] | None = None, object_scale: float = OBJECT_SCALE,
        object_distance_m: float | None = None, object_position: tuple[float, float, float] | None = None
        ) -> list[list]:
    """Convert `data` (cached under out/sequences, keyed by its files and these options), track it with each
    variant (and `tracker`, a (label, options) pair, when given), write euroc.md/.csv/.png; NothingScored
    (after writing them) when no variant scored a frame."""
    if not data.is_dir():
        raise FileNotFoundError(f"EuRoC data folder {data} not found (see shared/data/SOURCES.md); pass --data")
    seq = in_view_only(sequence_io.load(converted(out, data, fps, object_scale, object_distance_m, object_position)))
    xcorr_ms, jumps_s = truth_timing(data)
    doubtful = doubtful_truth(seq, jumps_s, xcorr_ms)
    variants = dict(VARIANTS) | (dict([tracker]) if tracker else {})
    rows, series, accounts = [], {}, {}
    with common.OracleBackend(noise_seed=seed, in_process=in_process) as oracle, \
            common.progress(len(variants), "euroc") as bar:
        for variant, tracker_options in variants.items():
            options = ReplayOptions(network=NetworkOptions(seed=seed), estimator="noisy")
            record = oracle.run(seq, tracker_options, options)
            accounts[variant] = a = account(record, fine_only=True, set_aside=doubtful)
            fine = fine_frames(record, doubtful)
            rows.append([variant, *on_fine(record, fine), a.worst_fine_px,
                         a.fine / a.in_view if a.in_view else float("nan"), record.time_offset_ms,
                         record.time_offset_sigma_ms, xcorr_ms, a.set_aside, a.worst_set_aside_px])
            record.write(out / "trajectories", f"euroc_{variant}")
            series[variant] = _gapped_series(record, fine)
            bar.set_postfix_str(f"{variant}: {rows[-1][3]:.2f} px")
            bar.update()
    common.write_csv(out / "euroc.csv", HEADER, rows)
    plots.error_over_time(series, out / "euroc.png", f"{labels(seq)[0]}, Noisy backend: 2D error (in view, FINE)")
    (out / "euroc.md").write_text(report(rows, seq, seed, accounts, fps))
    reasons = {v: a.nothing_scored_reason() for v, a in accounts.items()}
    if all(reasons.values()):
        by_reason: dict[str, list[str]] = {}
        for v, r in reasons.items():
            by_reason.setdefault(r, []).append(v)
        raise NothingScored("no variant scored a frame: " + "; ".join(
            f"{', '.join(vs)}: {r}" if len(by_reason) > 1 else r for r, vs in by_reason.items()))
    return rows


def truth_timing(data: Path) -> tuple[float, np.ndarray]:
    """From one read of the recording in `data`: its camera-IMU time offset, ms, by cross-correlating its gyroscope
    with its ground truth's angular rate (what the filter's online estimate is judged against; nan without a
    clear peak), and the moments its truth jumped where the gyro did not (s, the IMU's clock;
    `flextrack.calibration.imu`)."""
    from flextrack.calibration import imu as calibration

    imu, gt = calibration.recording(data)
    if len(gt.t_ns) <= 2:
        return float("nan"), np.zeros(0)
    offset_s = calibration.time_offset(imu, gt)[0]
    return offset_s * 1e3, calibration.truth_jumps(imu, gt, offset_s if np.isfinite(offset_s) else 0.0)


def doubtful_truth(seq, jumps_s: np.ndarray, offset_ms: float) -> frozenset[int]:
    """Ids of the frames in view within [-DOUBTFUL_BEFORE_S, DOUBTFUL_AFTER_S] of a moment the recording's truth
    jumped where its gyro did not (`jumps_s`, the IMU's clock, `truth_timing`; a motion capture swapping or
    losing markers): scored there, a tracker that follows the phone's own IMU is scored against a pose the
    device never had (`nexus5_ar_b` at 92.7 s: the truth turned ~1 deg in 25 ms, the gyro did not; FINE frames
    17 px "off" until the oracle's answers, made from that truth, re-initialised the filter)."""
    offset_s = offset_ms * 1e-3 if np.isfinite(offset_ms) else 0.0
    jumps_ns = (np.asarray(jumps_s) - offset_s) * 1e9  # on the camera's clock
    if not len(jumps_ns):
        return frozenset()
    t = seq.frame_times_ns.astype(float)
    last = np.searchsorted(jumps_ns, t + DOUBTFUL_BEFORE_S * 1e9, side="right") - 1  # the latest jump up to there
    near = (last >= 0) & (t - jumps_ns[np.maximum(last, 0)] <= DOUBTFUL_AFTER_S * 1e9)
    return frozenset(int(f) for f in seq.frame_ids[near] if int(f) in seq.gt_T_CO)


def fine_frames(record, set_aside: frozenset[int] = frozenset()) -> list:
    """The scored FINE frames of `record`, those `set_aside` left out (the paper's rule, on a recording)."""
    return [r for r in record.scored() if r.status == "FINE" and r.frame_id not in set_aside]


def converted(out: Path, data: Path, fps: float, object_scale: float, object_distance_m: float | None,
              object_position: tuple[float, float, float] | None) -> Path:
    """The sequence folder converted from `data` with these options: made once, then reused while neither the
    data's files (names, sizes, modification times), the options nor the converter's code change."""
    from flextrack.simulator import euroc_convert

    stats = sorted((str(p.relative_to(data)), p.stat().st_size, p.stat().st_mtime_ns)
                   for p in data.rglob("*") if p.is_file())
    # the name is the sequence's identity (the Noisy oracle's draws are keyed by it): the data's names and
    # sizes and the options, never the files' times, so that a copy of the same data gets the same draws;
    # times and the converter's code are in a stamp beside it, and a change in either remakes the folder
    key = hashlib.sha256(json.dumps([[f[:2] for f in stats], fps, object_scale, object_distance_m,
                                     object_position]).encode())
    root = out / "sequences" / f"{euroc_convert._source_name(data)}_{fps:g}fps_x{object_scale:g}_{key.hexdigest()[:12]}"
    converter = hashlib.sha256(Path(euroc_convert.__file__).read_bytes()).hexdigest()
    made_from = hashlib.sha256(json.dumps([stats, converter]).encode()).hexdigest()
    stamp = root / "converter.sha256"
    if not (root / "rig.yaml").is_file() or not stamp.is_file() or stamp.read_text() != made_from:
        if root.exists():
            shutil.rmtree(root)
        euroc_convert.convert_euroc(data, root, fps=fps, object_scale=object_scale, object_distance_m=object_distance_m,
                      object_position=object_position)
        stamp.write_text(made_from)
    if not (root / "plots" / "trajectory.png").is_file():  # the camera path and the object's place, drawn
        from flextrack.simulator.plots import plot_sequence

        plot_sequence(root)
    return root


def labels(seq) -> tuple[str, str]:
    """(recording name, IMU name) from the converted sequence's record of its source."""
    converter = seq.meta.get("converter", {})
    name = converter.get("source_name") or Path(converter.get("source", seq.name)).name
    return name, converter.get("imu", "IMU")


def _gapped_series(record, fine) -> tuple[list[float], list[float]]:
    """(t s, px) of the FINE frames, with a NaN between frames that do not follow each other (no line drawn
    across a stretch without data)."""
    t0 = record.rows[0].t_ns if record.rows else 0
    t, px = [], []
    for k, r in enumerate(fine):
        if k and r.index != fine[k - 1].index + 1:
            t.append((r.t_ns - t0) * 1e-9)
            px.append(float("nan"))
        t.append((r.t_ns - t0) * 1e-9)
        px.append(r.proj_px)
    return t, px


def on_fine(record, fine) -> list[float]:
    """Position mm, orientation deg, 2D px, jitter px and NEES over the FINE frames `fine` of `record` (the
    paper's rule; the ablation on a recording scores the same way)."""
    return [*_means(fine), *_fine_jitter_and_nees(record, fine)]


def _means(rows) -> list[float]:
    """Mean position mm, orientation deg, 2D projection px over frame rows (nan when none)."""
    if not rows:
        return [float("nan")] * 3
    return [float(np.mean([getattr(r, k) for r in rows])) for k in ("pos_mm", "ori_deg", "proj_px")]


def _fine_jitter_and_nees(record, fine) -> tuple[float, float]:
    """RMS jitter between consecutive FINE frames and mean NEES over FINE frames: the frames the 2D error
    is scored on (a re-acquisition's jump after the object was out of view is no shake a user sees)."""
    is_fine = {r.index for r in fine}
    jitter = [r.jitter_px for r in fine if r.index - 1 in is_fine and np.isfinite(r.jitter_px)]
    nees = [r.nees for r in fine if np.isfinite(r.nees)]
    return (float(np.sqrt(np.mean(np.square(jitter)))) if jitter else float("nan"),
            float(np.mean(nees)) if nees else float("nan"))


def report(rows: list[list], seq, seed: int, accounts: dict, fps: float) -> str:
    paper_rows = [[name, *vals] for name, vals in paper.TABLE4.items()]
    full, off = rows[0][3], rows[1][3]
    name, imu = labels(seq)
    scale = seq.meta.get("converter", {}).get("object_scale", OBJECT_SCALE)
    coverage = [[v, a.in_view, a.fine, a.scored, a.out_of_view, a.initialising, sum(a.lost.values()),
                 "-" if a.worst_fine_frame is None else f"{a.worst_fine_px:.2f} (frame {a.worst_fine_frame})",
                 a.set_aside, "-" if np.isnan(a.worst_set_aside_px) else f"{a.worst_set_aside_px:.2f}"]
                for v, a in accounts.items()]
    nothing = [f"- `{v}` scored nothing: {a.nothing_scored_reason()}" for v, a in accounts.items()
               if a.nothing_scored_reason()]
    placement = seq.meta.get("placement", {})
    where = "" if not placement else (
        f" ({placement.get('how', 'auto')}: centre at ({', '.join(f'{x:.2f}' for x in placement['centre_W'])}) m in "
        f"the recording's world, seen whole in {100 * placement['visible_fraction']:.0f} % of the frames)")
    bscm = (f"BSCM {'lowers' if full < off else 'does NOT lower'} the 2D error: {full:.2f} px with it, {off:.2f} px "
            "without" if np.isfinite([full, off]).all() else "BSCM's effect is not measured here: `full` or `bscm_off` "
            "scored nothing")
    return "\n".join([
        f"# Real IMU: {name} with a Noisy oracle", "",
        (f"{len(seq.frame_ids)} frames at {fps:g} FPS ({len(seq.gt_T_CO)} with the object in view), the recording's "
         f"IMU ({imu}, {seq.imu_noise.update_rate:g} Hz), the default "
         f"object scaled x{scale:g} where the camera sees it{where}; Noisy backend "
         f"3 mm / 0.3 deg per axis, seed {seed}; paper network model and Pixel 2 slowdown."), "",
        common.markdown_table(["variant", "position mm", "orientation deg", "2D projection px", "jitter px", "NEES",
                               "worst FINE px", "FINE / in view", "time offset ms", "its sigma ms"],
                              [[*r[:7], f"{100 * r[7]:.0f} %", *r[8:10]] for r in rows]), "",
        ("The time offset (t_imu = t_camera + offset) is the filter's online estimate at the end, with its standard "
         "deviation; the gyroscope cross-correlated with the ground truth's angular rate " + (
             f"gives {rows[0][10]:.2f} ms" if np.isfinite(rows[0][10]) else "shows no clear peak (a recording too short "
             "or too still)") + " (`flextrack calibrate imu`)."), "",
        ("Frames scored above: in view and FINE (the paper's rule); the jitter between consecutive such frames. What was and was not scored, and why (out of "
         "view: the object's centre not in the image or behind the camera; initialising: before the tracker's "
         "first pose; lost: in view but TRACKING_LOST / WRONG_POSE; set aside: in view, within "
         f"{DOUBTFUL_BEFORE_S * 1e3:.0f} ms before to {DOUBTFUL_AFTER_S * 1e3:.0f} ms after a moment the ground truth "
         "jumped where the gyro did not, its worst FINE frame beside):"), "",
        common.markdown_table(["variant", "in view", "FINE", "scored", "out of view", "initialising", "lost",
                               "worst FINE px", "set aside", "worst FINE px set aside"], coverage), "",
        *([*nothing, ""] if nothing else []),
        (f"{bscm} (`full` is the paper-faithful tracker; `filter` is the error-state Kalman filter, "
         "`flextrack.experiments.common.FILTER`)."), "",
        "The paper's Table 4 (its own five RealSense sequences, for scale):", "",
        common.markdown_table(["sequence", "position mm", "orientation deg", "2D projection px"], paper_rows), "",
        "![2D error over time](euroc.png)", "",
        f"![where the object was placed](sequences/{seq.root.name}/plots/trajectory.png)",
    ]) + "\n"
