"""The paper's ablation (Figure 6) and the 2D-error sawtooth (Figure 5).

Variants: the full system; BSCM and PIA both off (a backend pose still resets the pose, but the
biases are never corrected); IMU only (the backend answers the first request and is never asked
again). Each with the GT and the Noisy backend, on every motion program, or on a real recording
(`data`: a hand-held one in the EuRoC layout, converted as `experiment euroc` does). The paper's
tracker starts only from 0.5 s of still IMU, which a hand-held recording need not have: on one,
its variants run with `init_require_still=False` (its still-start rule lifted, docs/own-data.md).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from client_sdk import FilterOptions, TrackerOptions
from client_sdk.network_model import NetworkOptions
from flextrack.experiments import common, paper, plots
from flextrack.runners.replay import ReplayOptions

HEADER = ["variant", "backend", "motion", "level", "fps", "proj_px", "jitter_px", "nees_mean", "worst_fine_px"]
VARIANTS = {
    "full": TrackerOptions(fusion="paper"),
    "bscm_pia_off": TrackerOptions(fusion="paper", bscm=False, pia=False),
    "imu_only": TrackerOptions(fusion="paper", backend_after_init=False),
    "filter": TrackerOptions(),
    "filter_default_covariance": TrackerOptions(filter=FilterOptions(use_backend_covariance=False)),
    "filter_no_gravity_state": TrackerOptions(filter=FilterOptions(gravity_state=False)),
}


def run(out: Path, seed: int = 0, duration_s: float = 30.0, fps: int = 120, in_process: bool = False,
        motions=paper.MOTIONS, levels=paper.LEVELS, data: Path | None = None) -> list[list]:
    """The ablation on the simulated programs, or on the recording in `data` (at the euroc experiment's rate)."""
    cache = out / "sequences"
    rows = []
    variants = VARIANTS if data is None else {
        v: (replace(o, init_require_still=False) if o.fusion == "paper" else o) for v, o in VARIANTS.items()}
    if data is not None:
        from flextrack.experiments import euroc
        from flextrack.formats import sequence as sequence_io
        from flextrack.runners.scoring import account, in_view_only

        fps = euroc.FPS
        recording = in_view_only(sequence_io.load(euroc.converted(out, data, fps, euroc.OBJECT_SCALE, None, None)))
        xcorr_ms, jumps_s = euroc.truth_timing(data)
        doubtful = euroc.doubtful_truth(recording, jumps_s, xcorr_ms)
        programs = [(euroc.labels(recording)[0], "-")]
    else:
        programs = [(m, lv) for m in motions for lv in levels]
    shown = ("circular", "medium") if data is None else programs[0]
    closeup = {}
    with common.OracleBackend(noise_seed=seed, in_process=in_process) as oracle, \
            common.progress(len(programs) * len(variants) * len(paper.BACKENDS), "ablation") as bar:
        for motion, level in programs:
            seq = recording if data is not None else common.simulated(cache, common.SimSpec(motion, level, fps, seed,
                                                                                           duration_s))
            for variant, tracker_options in variants.items():
                for backend in paper.BACKENDS:
                    options = ReplayOptions(network=NetworkOptions(seed=seed), estimator=backend)
                    record = oracle.run(seq, tracker_options, options)
                    s = record.summarize()
                    if data is None:
                        rows.append([variant, backend, motion, level, fps, s.proj_px, s.jitter_px, s.nees_mean,
                                     s.worst_fine_px])
                    else:  # on a recording: the frames in view called FINE, as experiment euroc scores them
                        _, _, px, jitter, nees = euroc.on_fine(record, euroc.fine_frames(record, doubtful))
                        worst = account(record, fine_only=True, set_aside=doubtful).worst_fine_px
                        rows.append([variant, backend, motion, level, fps, px, jitter, nees, worst])
                    if (motion, level) == shown and variant in ("full", "bscm_pia_off"):
                        closeup[f"{variant}, {backend}"] = _series(record)
                    bar.set_postfix_str(f"{motion}/{level} {variant} {backend}: {s.proj_px:.2f} px")
                    bar.update()
    common.write_csv(out / "ablation.csv", HEADER, rows)
    plots.ablation(rows, out / "ablation.png")
    window = _one_second(closeup)
    where = " ".join(p for p in shown if p != "-")
    plots.sawtooth({k: v for k, v in window.items() if k.startswith("full")}, out / "sawtooth.png",
                   f"2D error over one second, {where} at {fps:g} FPS (paper Figure 5)")
    plots.error_over_time(closeup, out / "ablation_over_time.png", f"2D error, {where} (paper Figure 6)")
    (out / "ablation.md").write_text(report(rows, seed, duration_s, fps, data))
    return rows


def _series(record) -> tuple[np.ndarray, np.ndarray]:
    rows = record.scored()
    t0 = record.rows[0].t_ns
    return np.array([(r.t_ns - t0) * 1e-9 for r in rows]), np.array([r.proj_px for r in rows])


def _one_second(series: dict, start_s: float = 10.0) -> dict:
    """The second from `start_s` (or the run's last second, when it is shorter) of each series."""
    out = {}
    for name, (t, px) in series.items():
        start = min(start_s, max(0.0, float(t.max(initial=0.0)) - 1.0))
        keep = (t >= start) & (t < start + 1.0)
        out[name] = (t[keep], px[keep])
    return out


def report(rows: list[list], seed: int, duration_s: float, fps: float, data: Path | None = None) -> str:
    means = {(v, b): float(np.mean([r[5] for r in rows if r[0] == v and r[1] == b]))
             for v in VARIANTS for b in paper.BACKENDS}
    # the paper's variants against its full system, the filter's against the filter
    table = [[v, *(means[(v, b)] for b in paper.BACKENDS),
              *(means[(v, b)] / means[("filter" if v.startswith("filter") else "full", b)] for b in paper.BACKENDS)]
             for v in VARIANTS]
    per_program = [[r[2], r[3], r[1], r[0], r[5]] for r in rows]
    ratio_gt = means[("bscm_pia_off", "gt")] / means[("full", "gt")]
    ratio_noisy = means[("bscm_pia_off", "noisy")] / means[("full", "noisy")]
    return "\n".join([
        "# Ablation: BSCM and PIA off, IMU only (paper Figures 5 and 6); the filter's covariance and gravity", "",
        ((f"Seed {seed}; {duration_s:g} s sequences at {fps} FPS; replay through a gRPC server with the paper's network "
          "model and the Pixel 2 slowdown. Mean 2D projection error in px over all six motion programs.") if data is None
         else (f"Seed {seed}; the real recording {rows[0][2]} ({data}) at {fps:g} FPS, a virtual object, as `experiment "
               "euroc`; the paper's variants start while moving (`init_require_still=False`). Mean 2D projection "
               "error in px over the frames in view that each variant called FINE.")), "",
        common.markdown_table(["variant", "GT px", "Noisy px", "GT x full", "Noisy x full"], table), "",
        (f"The paper's method: BSCM+PIA off is {ratio_gt:.1f}x (GT) and {ratio_noisy:.1f}x (Noisy) the full system's "
        "error (the paper: more than 2x); IMU only drifts without bound. The filter's own ablations are against "
        "the filter: `filter_default_covariance` (every answer given the default 1 deg / 1 cm instead of its own "
        "covariance) and `filter_no_gravity_state` (g_O frozen at initialisation)."), "",
        "![ablation](ablation.png)", "", "![one second of 2D error](sawtooth.png)", "",
        "![2D error over time](ablation_over_time.png)", "",
        "## Per program", "", common.markdown_table(["motion", "level", "backend", "variant", "proj px"], per_program),
    ]) + "\n"
