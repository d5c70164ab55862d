"""`flextrack report`: the README's and docs' result sections, generated from the stored results.

A stored result is a folder `docs/results/NAME/` with the run's small files (CSV/JSON) and its
provenance (`NAME.json`: {"provenance": flextrack.provenance.provenance(...), ...}; a folder of several
runs instead holds one JSON per run, each with its own provenance). A Markdown file
shows it between two markers:

    <!-- results:NAME -->
    ...generated, never edited by hand...
    <!-- /results:NAME -->

`flextrack report` rewrites every such section of README.md and docs/*.md from the folders;
`flextrack report --check` only says which sections differ (exit 1), and a test runs the same check,
so a table and the run behind it cannot drift apart.

Adding a result: copy the run's files into `docs/results/NAME/` (with its provenance JSON), add a
function `render(folder: Path) -> str` below, registered with `@section("NAME")`, put the two
markers where the table belongs, run `flextrack report`, commit the files, the code and the page.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

RESULTS_DIR = Path("docs") / "results"
PAGES = ("README.md", "docs/*.md")
_MARKER = re.compile(r"(<!-- results:(?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /results:(?P=name) -->)", re.DOTALL)

RENDERERS: dict[str, Callable[[Path], str]] = {}


def section(name: str) -> Callable:
    """Register `render(folder) -> markdown` for the markers `<!-- results:NAME -->`."""
    def register(fn: Callable[[Path], str]) -> Callable[[Path], str]:
        RENDERERS[name] = fn
        return fn
    return register


# --- helpers a renderer uses -------------------------------------------------------------------


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def read_provenance(path: Path) -> dict:
    """The provenance record of a stored result's JSON (the whole file when it has no "provenance" key)."""
    data = json.loads(path.read_text())
    return data.get("provenance", data)


def provenance_line(prov: dict, command: str | None = None) -> str:
    """One sentence: the command, the date, the commit (dirty or not), the host and, when recorded, the wall
    time and the processes it ran in."""
    commit = (prov.get("commit") or "unknown")[:10]
    dirty = prov.get("dirty")
    state = " (uncommitted changes in the tree)" if dirty else ("" if dirty is False else " (tree state unknown)")
    cmd = command or prov.get("options", {}).get("command")
    parts = [f"`{cmd}`" if cmd else None, f"run {prov.get('date', '?')}", f"commit {commit}{state}",
             f"host {prov.get('host', '?')}"]
    if prov.get("wall_s") is not None:
        jobs = prov.get("options", {}).get("jobs")
        parts.append(f"{prov['wall_s']:.0f} s" + (f" in {jobs} processes" if jobs and jobs > 1 else ""))
    return "Source: " + ", ".join(p for p in parts if p) + "."


def seed_flags(seeds: list[int]) -> str:
    """The --seed and --seeds flags that run these consecutive seeds again (none for seed 0 alone)."""
    first = f" --seed {seeds[0]}" if seeds and seeds[0] else ""
    return first + (f" --seeds {len(seeds)}" if len(seeds) > 1 else "")


def _range(values) -> str:
    lo, hi = float(np.min(values)), float(np.max(values))
    return f"{lo:.2f}" if f"{lo:.2f}" == f"{hi:.2f}" else f"{lo:.2f}-{hi:.2f}"


# --- the sections --------------------------------------------------------------------------------


def _table2_nees(rows: list[dict[str, str]]) -> str:
    """The filter's mean NEES per cell against its 95 % interval (correlated frames allowed for)."""
    parts = []
    for backend, title in (("gt", "GT"), ("noisy", "Noisy")):
        cells = [r for r in rows if r["backend"] == backend and "nees_lo" in r]
        if not cells:
            continue
        nees = [_num(r["nees_mean"]) for r in cells]
        inside = sum(_num(r["nees_lo"]) <= _num(r["nees_mean"]) <= _num(r["nees_hi"]) for r in cells)
        low = sum(_num(r["nees_mean"]) < _num(r["nees_lo"]) for r in cells)
        parts.append(f"{title}: mean NEES {_range(nees)}, inside its interval in {inside} of {len(cells)} cells "
                     f"({low} below it: covariance larger than the errors, {len(cells) - inside - low} above it)")
    return ("The filter's consistency (chi-square, 6 dof; each cell's 95 % interval of the mean allows for "
            "consecutive frames sharing one state, as correlated as the filter's own error dynamics make them: "
            "`flextrack.evaluation.consistency`, columns `nees_lo`, `nees_hi`). " + "; ".join(parts) + ".") if parts else ""


@section("table2")
def render_table2(folder: Path) -> str:
    """Table 2: the paper / the paper-faithful tracker / the filter per cell (2D px), the filter's jitter."""
    from flextrack.experiments import paper

    variants = {"filter": read_csv(folder / "table2.csv"), "paper": read_csv(folder / "table2_paper.csv")}
    prov = read_provenance(folder / "table2.json")
    cells: dict[str, dict[tuple, np.ndarray]] = {}
    for variant, rows in variants.items():
        acc: dict[tuple, list] = {}
        for r in rows:
            key = (r["motion"], r["level"], int(float(r["fps"])), r["backend"])
            acc.setdefault(key, []).append([float(r["proj_px"]), float(r["jitter_px"])])
        cells[variant] = {k: np.array(v) for k, v in acc.items()}
    seeds = sorted({int(r["seed"]) for r in variants["filter"]})
    programs = [(m, lv) for m in paper.MOTIONS for lv in paper.LEVELS]
    fps_list = sorted({k[2] for k in cells["filter"]})
    short = {"translational": "trans.", "circular": "circ."}
    lines = ["| backend | FPS | " + " | ".join(f"{short[m]} {lv}" for m, lv in programs) + " |",
             "|---|---|" + "---|" * len(programs)]
    ranges: dict[tuple[str, str], list[float]] = {}
    for backend in paper.BACKENDS:
        for fps in fps_list:
            row = ["GT" if backend == "gt" else "Noisy", str(fps)]
            for m, lv in programs:
                key = (m, lv, fps, backend)
                if key not in cells["filter"] or key not in cells["paper"]:
                    row.append("")
                    continue
                f, p = cells["filter"][key], cells["paper"][key]
                spread = f" ±{f[:, 0].std():.2f}" if len(f) > 1 else ""
                row.append(f"{paper.TABLE2[key][2]:.2f} / {p[:, 0].mean():.2f} / **{f[:, 0].mean():.2f}**{spread} "
                           f"({f[:, 1].mean():.2f})")
                for name, v in (("paper", paper.TABLE2[key][2]), ("faithful", p[:, 0].mean()),
                                ("filter", f[:, 0].mean()), ("jitter", f[:, 1].mean())):
                    ranges.setdefault((backend, name), []).append(float(v))
            lines.append("| " + " | ".join(row) + " |")
    seed_text = f"seed {seeds[0]}" if len(seeds) == 1 else f"seeds {seeds[0]}-{seeds[-1]}, ± the filter's std over seeds"
    summary = "; ".join(
        f"{'GT' if b == 'gt' else 'Noisy'} backend: the paper {_range(ranges[(b, 'paper')])} px, paper-faithful "
        f"{_range(ranges[(b, 'faithful')])} px, the filter {_range(ranges[(b, 'filter')])} px "
        f"(jitter {_range(ranges[(b, 'jitter')])} px)" for b in paper.BACKENDS if (b, "filter") in ranges)
    nees_text = _table2_nees(variants["filter"])
    return "\n".join([
        (f"Mean 2D projection error in px ({seed_text}; every frame with a pose is scored, FINE or not), per cell: "
         "the paper / our paper-faithful tracker / "
         "**the filter** (the error-state Kalman filter, the default tracker), and in parentheses the filter's "
         "jitter (RMS frame-to-frame change of the 2D error, px). Noisy backend: 3 mm and 0.3 deg per axis."),
        "", *lines, "", f"Ranges over the cells: {summary}.", "", nees_text, "",
        provenance_line(prov, f"flextrack experiment table2{seed_flags(seeds)} --out out/table2") + " Files: "
        f"`{RESULTS_DIR.as_posix()}/{folder.name}/` (per-cell position, orientation, NEES and worst-frame columns "
        "too)."])


def _num(value: str) -> float:
    return float(value) if value not in ("", "nan") else float("nan")


def _cells(rows: list[dict[str, str]], columns: list[tuple[str, str, str]]) -> list[str]:
    """Markdown rows: (header, csv column, format) per column."""
    out = ["| " + " | ".join(h for h, _, _ in columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        out.append("| " + " | ".join(format(_num(r[c]), f) if f else r[c] for _, c, f in columns) + " |")
    return out


@section("filter")
def render_filter(folder: Path) -> str:
    """The filter's peer cells, moving start and time offset (flextrack experiment filter)."""
    from flextrack.experiments.filter_checks import BOUND_CHECKS, GOALS, PEER, WINDOW_LABELS, WINDOW_NAMES

    rows = read_csv(folder / "filter.csv")
    prov = read_provenance(folder / "filter.json")
    seeds = prov.get("options", {}).get("seeds", [])

    def mean(sel, col):
        return float(np.mean([_num(r[col]) for r in sel]))

    peer = []
    for cell in sorted({(r["motion"], r["level"]) for r in rows if r["check"] == "peer"}, reverse=True):
        for fusion in ("filter", "paper"):
            sel = [r for r in rows if r["check"] == "peer" and (r["motion"], r["level"]) == cell and r["fusion"] == fusion]
            peer.append(f"| {cell[0]} {cell[1]} | {fusion} | {mean(sel, 'proj_px'):.2f} | {mean(sel, 'pos_mm'):.2f} | "
                        f"{mean(sel, 'ori_deg'):.3f} | {mean(sel, 'jitter_px'):.2f} | {mean(sel, 'nees_mean'):.2f} | "
                        f"{mean(sel, 'worst_fine_px'):.2f} |")
    starts, windows, bounds = [], [], []
    for check in ("still_start", "moving_start", "time_offset_20ms"):
        sel = [r for r in rows if r["check"] == check]
        if sel:
            starts.append(f"| {check.replace('_', ' ')} | {mean(sel, 'proj_px'):.2f} | {mean(sel, 'proj_px_after_1s'):.2f} | "
                          f"{mean(sel, 'fine_after_s'):.2f} | {mean(sel, 'time_offset_ms'):.2f} |")
            windows.append(f"| {check.replace('_', ' ')} | "
                           + " | ".join(f"{mean(sel, f'proj_px_{w}'):.2f}" for w in WINDOW_NAMES) + " | "
                           + " | ".join(f"{mean(sel, f'nees_{w}'):.1f}" for w in WINDOW_NAMES) + " |")
            if check in BOUND_CHECKS:
                bounds.append(f"| {check.replace('_', ' ')} | "
                              + " | ".join(f"{mean(sel, f'proj_px_{w}'):.2f} / {mean(sel, f'bound_px_{w}'):.2f}"
                                           for w in WINDOW_NAMES) + " |")
    return "\n".join([
        (f"Circular medium and translational hard at 60 FPS, the noisy oracle with its covariance behind a real gRPC "
         f"server, seeds {seeds}, every frame scored; means over seeds. The peer, a public C++ error-state EKF (MaRS), on "
         f"the same inputs: {PEER['proj_px']} px, {PEER['pos_mm']} mm, {PEER['ori_deg']} deg, jitter "
         f"{PEER['jitter_px']} px (goals: below {GOALS['proj_px']} px, {GOALS['ori_deg']} deg, {GOALS['jitter_px']} px)."),
        "", "| cell | tracker | 2D px | pos mm | rot deg | jitter px | NEES | worst FINE px |", "|---|---|---|---|---|---|---|---|",
        *peer, "", ("Circular medium with the filter: a still start, a start on a moving device (`simulate "
                    "--moving-start`) and an IMU stamping 20 ms late (`simulate --imu-time-offset 0.02`):"), "",
        "| start | 2D px | 2D px from 1 s after the first pose | first pose to FINE, s | estimated offset, ms |",
        "|---|---|---|---|---|", *starts, "",
        "The same by time after the first pose, 2D px and the filter's NEES (6 for a consistent filter):", "",
        "| start | " + " | ".join(f"px {w}" for w in WINDOW_LABELS) + " | " + " | ".join(f"NEES {w}" for w in WINDOW_LABELS) + " |",
        "|---|" + "---|" * (2 * len(WINDOW_NAMES)), *windows, "",
        ("Measured / the Riccati bound, px, by the same windows: the expected error of the filter's own covariance on a "
         "noise-free IMU with exact answers at the same times, from the same initial uncertainty (the noise-free IMU run "
         "of each start; `flextrack/experiments/bound.py`). Once the start is forgotten it is the least mean error of "
         "any estimator that takes the motion from the IMU and the pose from these answers; in the first seconds it "
         "also carries the filter's deliberately generous initial uncertainty, which a run can beat:"),
        "", "| start | " + " | ".join(WINDOW_LABELS) + " |", "|---|" + "---|" * len(WINDOW_NAMES), *bounds, "",
        provenance_line(prov, f"flextrack experiment filter{seed_flags(seeds)} --out out/filter") + f" Files: "
        f"`{RESULTS_DIR.as_posix()}/{folder.name}/`."])


def _means_by_motion(rows: list[dict[str, str]], column: str) -> str:
    """"translational 5.46, circular 6.14": a column's mean per motion program."""
    motions = dict.fromkeys(r["motion"] for r in rows)
    return ", ".join(f"{m} {np.mean([_num(r[column]) for r in rows if r['motion'] == m]):.2f}" for m in motions)


def _runs_inside(rows: list[dict[str, str]]) -> str:
    """How many runs' mean NEES lie inside their own 95 % interval (`nees_lo`, `nees_hi`)."""
    if not rows or "nees_lo" not in rows[0]:
        return ""
    nees = [(_num(r["nees_mean"]), _num(r["nees_lo"]), _num(r["nees_hi"])) for r in rows]
    inside = sum(lo <= m <= hi for m, lo, hi in nees)
    low = sum(m < lo for m, lo, _ in nees)
    return (f"Each run's mean NEES is inside its 95 % interval (from the filter's error dynamics, "
            f"`flextrack.evaluation.consistency`) in {inside} of {len(nees)} runs ({low} below, "
            f"{len(nees) - inside - low} above; a consistent filter: about 95 % inside).")


@section("bound")
def render_bound(folder: Path) -> str:
    """The Noisy Table 2 cells beside their Riccati bound (flextrack experiment bound)."""
    from flextrack.experiments.bound import LIMIT_PX, SETTLE_S

    rows = read_csv(folder / "bound.csv")
    prov = read_provenance(folder / "bound.json")
    seeds = prov.get("options", {}).get("seed_list", [])
    columns = ("proj_px_all", "proj_px", "predicted_px", "bound_px")
    lines = ["| cell | FPS | measured, all frames | measured | predicted | bound | measured / bound |",
             "|---|---|---|---|---|---|---|"]
    means = []
    for key in dict.fromkeys((r["motion"], r["level"], r["fps"]) for r in rows):
        sel = [r for r in rows if (r["motion"], r["level"], r["fps"]) == key]
        m = [float(np.mean([_num(r[c]) for r in sel])) for c in columns]
        means.append(m)
        lines.append(f"| {key[0]} {key[1]} | {_num(key[2]):g} | {m[0]:.2f} | {m[1]:.2f} | {m[2]:.2f} | **{m[3]:.2f}** | "
                     f"{m[1] / m[3]:.2f} |")
    a = np.array(means)
    runs = np.array([[_num(r[c]) for c in columns] for r in rows])
    return "\n".join([
        (f"The Noisy cells of Table 2 (seeds {', '.join(map(str, seeds))}, means over seeds), mean 2D error in px over the frames from "
         f"{SETTLE_S:g} s after the first (the first column: all frames, Table 2's figure). *measured*: the filter; "
         "*predicted*: the error its own covariances predict; *bound*: the Riccati bound, the expected error of the "
         "Kalman filter linearised at the truth on the same answer times (the least any estimator that takes the "
         "motion from the IMU can reach on average, up to the ~0.01 px the shown pose's easing adds; "
         "`flextrack/experiments/bound.py`). A run scatters about its expectation: single runs fall on either side."),
        "", *lines, "",
        (f"The bound is above {LIMIT_PX:g} px in {int((a[:, 3] > LIMIT_PX).sum())} of {len(a)} cells. Over all runs "
         f"measured / bound is {runs[:, 1].mean() / runs[:, 3].mean():.3f} (per run "
         f"{_range(runs[:, 1] / runs[:, 3])}) and predicted / bound {runs[:, 2].mean() / runs[:, 3].mean():.3f}. "
         f"The filter's mean NEES over all {len(rows)} runs (all frames) is "
         f"{np.mean([_num(r['nees_mean']) for r in rows]):.2f} for 6 ({_means_by_motion(rows, 'nees_mean')}), "
         f"its rotation block's {np.mean([_num(r['nees_rotation']) for r in rows]):.2f} for 3 "
         f"({_means_by_motion(rows, 'nees_rotation')}). {_runs_inside(rows)}"),
        "", provenance_line(prov, f"flextrack experiment bound{seed_flags(seeds)} --out out/bound") + " Files: "
        f"`{RESULTS_DIR.as_posix()}/{folder.name}/`."])


@section("euroc")
def render_euroc(folder: Path) -> str:
    """The real-IMU experiment (EuRoC V1_02, a virtual object, the noisy oracle)."""
    rows = read_csv(folder / "euroc.csv")
    prov = read_provenance(folder / "euroc.json")
    return "\n".join([
        ("EuRoC V1_02_medium (the real ADIS16448 IMU at 200 Hz, motion-capture truth, a virtual object where the "
         "camera looks, the noisy oracle); errors on the frames in view that the tracker called FINE (the paper's "
         "rule); `full` is the paper-faithful tracker, `bscm_off` the same without BSCM, `filter` the default."),
        "", *_cells(rows, [("variant", "variant", ""), ("position mm", "pos_mm", ".2f"), ("orientation deg", "ori_deg", ".2f"),
                           ("2D px", "proj_px", ".2f"), ("jitter px", "jitter_px", ".2f"), ("NEES", "nees_mean", ".1f"),
                           ("worst FINE px", "worst_fine_px", ".2f"), ("FINE share", "fine_share", ".2f"),
                           ("offset ms", "time_offset_ms", ".2f"), ("sigma ms", "time_offset_sigma_ms", ".2f")]),
        "", (f"Offset: the filter's camera-IMU time offset at the end; the gyroscope cross-correlated with the truth's "
             f"angular rate gives {_num(rows[0]['offset_xcorr_ms']):.2f} ms."),
        "", provenance_line(prov, "flextrack experiment euroc --out out/euroc") + f" Files: "
        f"`{RESULTS_DIR.as_posix()}/{folder.name}/`."])


@section("ablation")
def render_ablation(folder: Path) -> str:
    """The ablation (the paper's Figure 6) and the filter's own."""
    rows = read_csv(folder / "ablation.csv")
    prov = read_provenance(folder / "ablation.json")
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    mean = {(v, b): float(np.mean([_num(r["proj_px"]) for r in rows if r["variant"] == v and r["backend"] == b]))
            for v in variants for b in ("gt", "noisy")}
    lines = ["| variant | GT px | Noisy px | GT x its full system | Noisy x its full system |", "|---|---|---|---|---|"]
    for v in variants:
        base = "filter" if v.startswith("filter") else "full"
        lines.append(f"| {v} | {mean[(v, 'gt')]:.2f} | {mean[(v, 'noisy')]:.2f} | {mean[(v, 'gt')] / mean[(base, 'gt')]:.2f} "
                     f"| {mean[(v, 'noisy')] / mean[(base, 'noisy')]:.2f} |")
    return "\n".join([
        ("Mean 2D error over the six programs at 120 FPS. The paper's method (`full`) against BSCM and PIA off and IMU "
         "only; the filter against every answer given the default covariance and against gravity frozen at start-up."),
        "", *lines, "", provenance_line(prov, "flextrack experiment ablation --out out/ablation") + f" Files: "
        f"`{RESULTS_DIR.as_posix()}/{folder.name}/`."])


def _nees(row: dict[str, str]) -> str:
    """", NEES x" where the tracker gave a covariance (the paper's method gives none)."""
    value = _num(row["nees_mean"])
    return f", NEES {value:.1f}" if np.isfinite(value) else ""


def _request_kb(row: dict[str, str]) -> str:
    """", request x kB": the median request's size, where the run recorded it."""
    return f", request {_num(row['median_request_kb']):.0f} kB" if row.get("median_request_kb") else ""


def _render_table2_vision(folder: Path, backend: str) -> str:
    """Table 2's medium cells with an image estimator on rendered frames, both trackers."""
    prov = read_provenance(folder / f"table2_{backend}.json")
    backend_ms = prov.get("options", {}).get("backend_ms", 145.0)
    lines = ["| tracker | backend | FPS | translational medium | circular medium |", "|---|---|---|---|---|"]
    for variant, name in (("filter", f"table2_{backend}.csv"), ("paper", f"table2_{backend}_paper.csv")):
        rows = read_csv(folder / name)
        for estimator in ("gt_oracle", backend):
            for fps in sorted({r["fps"] for r in rows}, key=float):
                cell = {r["motion"]: r for r in rows if r["backend"] == estimator and r["fps"] == fps}
                lines.append(f"| {variant} | {estimator} | {float(fps):g} | " + " | ".join(
                    f"**{_num(cell[m]['proj_px']):.2f}** (jitter {_num(cell[m]['jitter_px']):.2f}, worst FINE "
                    f"{_num(cell[m]['worst_fine_px']):.1f}{_nees(cell[m])}{_request_kb(cell[m])})" if m in cell else ""
                    for m in ("translational", "circular")) + " |")
    command = f"flextrack experiment table2 --backend {backend}" + seed_flags(prov.get("options", {}).get("seed_list", []))
    if backend_ms != 145.0:
        command += f" --backend-ms {backend_ms:g}"
    return "\n".join([
        (f"2D error in px on rendered frames through a real gRPC server, `{backend}`'s compute modelled as "
         f"{backend_ms:g} ms a frame, beside the ground-truth oracle on the same frames; the filter with the options "
         "it uses for every backend, and the paper's method. Where a request size is given (the median), each request "
         "was charged on the link at its real size, the device sending the crop around its prior once it tracks."),
        "", *lines, "",
        provenance_line(prov, f"{command} --out out/table2_{backend}") + f" Files: "
        f"`{RESULTS_DIR.as_posix()}/{folder.name}/`."])


@section("table2_pvnet")
def render_table2_pvnet(folder: Path) -> str:
    """Table 2's medium cells with the PVNet-style backend on rendered frames, both trackers."""
    return _render_table2_vision(folder, "pvnet")


@section("table2_pvnet_region")
def render_table2_pvnet_region(folder: Path) -> str:
    """Table 2's medium cells with the chained backend (pvnet, then region from the device's prior)."""
    return _render_table2_vision(folder, "pvnet_region")


def _prior_itself(r: dict) -> str:
    if r.get("prior_share_proj_5px") is None:
        return "-"
    return f"{100 * r['prior_share_proj_5px']:.0f} % ({r['prior_median_proj_px']:.1f})"


def _prior_label(prov: dict) -> str:
    options = prov.get("options", {})
    label = f"{options.get('estimator', '?')}, seed {options.get('seed', '?')}"
    return label + (", `--fresh` (every frame a new session)" if options.get("fresh") else "")


@section("region_clutter")
@section("region_prior")
def render_region_prior(folder: Path) -> str:
    """`flextrack evaluate prior` runs: an estimator on a BOP folder from priors drawn around the truth."""
    lines = [("| run | prior (per axis) | answers | < 5 px | ADD 10 % | median px | prior itself < 5 px (median px) "
             "| NEES mean / median |"), "|---|---|---:|---:|---:|---:|---:|---:|"]
    sources = []
    for path in sorted(folder.glob("*.json")):
        data = json.loads(path.read_text())
        for level, result in data["levels"].items():
            r = result["summary"]
            if not r.get("ok"):
                continue
            lines.append(f"| {_prior_label(data)} | {level} | {r['answers']} | **{100 * r['share_proj_5px']:.1f} %** | "
                         f"{100 * r['share_add_10']:.0f} % | {r['median_proj_px']:.2f} | "
                         f"{_prior_itself(r)} | "
                         f"{r['nees_mean']:.1f} / {r['nees_median']:.1f} |")
        sources.append(f"- `{path.name}`: " + provenance_line(data, data.get("command")).removeprefix("Source: "))
    return "\n".join([*lines, "", "Sources (chi-square(6): mean 6, median 5.35):", *sources,
                      f"Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


def _halves(answers: list[dict]) -> dict[str, set]:
    """(scene, frame) of every other frame of each scene, by sorted frame id: `--part even` and `--part odd`."""
    by_scene: dict[int, list[int]] = {}
    for a in answers:
        by_scene.setdefault(a["scene"], []).append(a["frame"])
    out: dict[str, set] = {"even": set(), "odd": set()}
    for scene, frames in by_scene.items():
        ordered = sorted(set(frames))
        out["even"] |= {(scene, f) for f in ordered[0::2]}
        out["odd"] |= {(scene, f) for f in ordered[1::2]}
    return out


def _share(rows: list[dict], test, interval: bool = False) -> str:
    """The share of `rows` passing `test`; with `interval`, its Wilson 95 % interval beside it (a share of a few
    hundred instances moves by several points between draws of the priors)."""
    if not rows:
        return "-"
    hits = int(sum(bool(test(r)) for r in rows))
    text = f"{100 * hits / len(rows):.1f} %"
    if interval:
        from scipy.stats import binomtest

        ci = binomtest(hits, len(rows)).proportion_ci(0.95, method="wilson")
        text += f" ({100 * ci.low:.1f}-{100 * ci.high:.1f})"
    return text


def _under_5(r: dict) -> bool:
    return r["proj_px"] is not None and r["proj_px"] < 5.0


def _ok_wrong(r: dict) -> bool:
    return r["proj_px"] is not None and r["proj_px"] > 20.0


REGION_GOALS = {"10mm/5deg": (0.3, "85 %"), "20mm/10deg": (0.3, "70 %"), "30mm/15deg": (0.5, "60 %")}


@section("region_lmo")
def render_region_lmo(folder: Path) -> str:
    """`flextrack evaluate prior --obj-id all` on the real LM-O frames: pooled over the 8 objects, on the frame
    half settings were tuned on and the half they were not, per visibility band and per object."""
    from scipy.stats import chi2

    docs = {p.stem: json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))}  # each file read once
    main = docs["lmo_region"]
    lines = [("| prior (per axis) | instances | visible | < 5 px: all frames | tune half (even) | held-out half (odd) "
             "| goal | OK yet > 20 px off |"), "|---|---:|---|---:|---:|---:|---:|---:|"]
    for level, result in main["levels"].items():
        answers = result["answers"]
        halves = _halves(answers)
        min_v, goal = REGION_GOALS.get(level, (0.3, "-"))
        seen = _seen(answers, level)
        part = {k: [a for a in seen if (a["scene"], a["frame"]) in v] for k, v in halves.items()}
        lines.append(f"| {level} | {len(seen)} | >= {100 * min_v:.0f} % | **{_share(seen, _under_5, True)}** | "
                     f"{_share(part['even'], _under_5)} | **{_share(part['odd'], _under_5, True)}** | {goal} | "
                     f"{_share(seen, _ok_wrong)} |")
        hidden = [a for a in answers if a["visib"] is not None and a["visib"] < 0.3]
        lines.append(f"| {level} | {len(hidden)} | < 30 % | {_share(hidden, _under_5)} | | | OK > 20 px at most 2 % | "
                     f"**{_share(hidden, _ok_wrong, True)}** |")
    for name, label in (("lmo_region_flip", "prior turned 180 deg (`--flip`)"),
                        ("lmo_region_no_flip_check", "flip check off (`no_flip_check.toml`)"),
                        ("lmo_region_no_flip_check_flip", "prior turned 180 deg, flip check off")):
        if name not in docs:
            continue
        for level, result in docs[name]["levels"].items():
            answers = result["answers"]
            min_v = REGION_GOALS.get(level, (0.3, "-"))[0]
            seen = _seen(answers, level)
            halves = _halves(answers)
            odd = [a for a in seen if (a["scene"], a["frame"]) in halves["odd"]]
            even = [a for a in seen if (a["scene"], a["frame"]) in halves["even"]]
            goal = "none OK > 20 px" if name.endswith("_flip") else ""
            lines.append(f"| {level}, {label} | {len(seen)} | >= {100 * min_v:.0f} % | {_share(seen, _under_5)} | "
                         f"{_share(even, _under_5)} | {_share(odd, _under_5)} | {goal} | **{_share(seen, _ok_wrong, True)}** |")
    first = next(iter(main["levels"]))
    objects = [("| object | instances >= 30 % visible | < 5 px | ADD(-S) 10 % | OK yet > 20 px off (of the OK answers) "
                "| NEES mean (95 % interval of the mean) | NEES median |"), "|---|---:|---:|---:|---:|---:|---:|"]
    answers = [a for a in main["levels"][first]["answers"] if (a["visib"] or 0) >= 0.3]
    for obj in sorted({a["obj_id"] for a in answers}):
        rows = [a for a in answers if a["obj_id"] == obj]
        nees = [a["nees"] for a in rows if a["nees"] is not None]
        lo, hi = (chi2.ppf([0.025, 0.975], 6 * len(nees)) / len(nees)) if nees else (np.nan, np.nan)
        objects.append(f"| {obj} | {len(rows)} | {_share(rows, _under_5)} | {_share(rows, lambda r: r['add_ok'])} | "
                       f"{_share(rows, _ok_wrong)} ({_share([r for r in rows if r['proj_px'] is not None], _ok_wrong)}) | "
                       f"{np.mean(nees):.1f} ({lo:.1f}-{hi:.1f}) | {np.median(nees):.1f} |")
    bands = ["| visible | instances | < 5 px | OK yet > 20 px off |", "|---|---:|---:|---:|"]
    for band, summary in main["levels"][first]["by_visib"].items():
        bands.append(f"| {band} | {summary['answers']} | {100 * summary['share_proj_5px']:.1f} % | "
                     f"{100 * summary['share_ok_wrong']:.1f} % |")
    sources = [f"- `{name}.json`: " + provenance_line(doc, doc.get("command")).removeprefix("Source: ")
               for name, doc in docs.items()]
    return "\n".join([*lines, "", *_colour_ceiling(docs), (f"Per object, {first}, instances at least 30 % "
                      "visible (NEES: chi-square(6), "
                      "mean 6, median 5.35; against the nearest symmetric pose):"), "", *objects, "",
                      f"Per visibility band, {first}, every instance:", "", *bands, "", *_centre_lean(answers),
                      "Sources:", *sources, f"Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


COLOUR_CEILING = (("lmo_region", "served", "the prior's outline"),
                  ("lmo_region_colours_at_truth", "served", "**the true outline** (oracle)"),
                  ("lmo_region_m3t_like", "M3T's (`m3t_like.toml`)", "the prior's outline"),
                  ("lmo_region_m3t_like_colours_at_truth", "M3T's (`m3t_like.toml`)", "**the true outline** (oracle)"))


def _seen(answers: list[dict], level: str) -> list[dict]:
    """The answers on instances at least as visible as the level's goal asks (REGION_GOALS; 30 % by default)."""
    min_v = REGION_GOALS.get(level, (0.3, "-"))[0]
    return [a for a in answers if (a["visib"] or 0) >= min_v]


def _colour_ceiling(docs: dict[str, dict]) -> list[str]:
    """What the colour model costs: region's share under 5 px with its served settings and with M3T's, its first
    colours learned at the prior's outline (as served) or at the true one (`--colours-at-truth`), per prior level,
    with the goals under them (a table and a blank line; none before every run is stored). `docs`: the folder's
    results by file stem."""
    if any(name not in docs for name, _, _ in COLOUR_CEILING):
        return []
    runs = [(docs[name], settings, colours) for name, settings, colours in COLOUR_CEILING]
    levels = list(docs["lmo_region"]["levels"])

    def cell(doc: dict, level: str) -> str:
        return _share(_seen(doc["levels"][level]["answers"], level), _under_5)

    head = " | ".join(f"{level}, >= {100 * REGION_GOALS.get(level, (0.3, '-'))[0]:.0f} % visible" for level in levels)
    out = [f"| settings | first colours learned at | {head} |", "|---|---|" + "---:|" * len(levels)]
    out += [f"| {settings} | {colours} | " + " | ".join(cell(doc, level) for level in levels) + " |"
            for doc, settings, colours in runs]
    out.append("| goal | | " + " | ".join(REGION_GOALS.get(level, (0.3, "-"))[1] for level in levels) + " |")
    return [("Under 5 px, with the colours learned at the prior's outline (as served) or at the true outline (an "
             "oracle: `--colours-at-truth`), region's served settings and M3T's (every instance a fresh session, the "
             "same priors):"), "", *out, ""]


def _centre_lean(answers: list[dict]) -> list[str]:
    """Where the answers within 20 px put the object's centre in the image, against the truth (a sentence and a
    blank line; none for a run that did not record it). Within 20 px, not 5: a tighter cut would trim the lean it
    measures."""
    offsets = np.array([a["centre_offset_px"] for a in answers if "centre_offset_px" in a and a["proj_px"] < 20])
    if len(offsets) < 2:
        return []
    mean, se, median = offsets.mean(axis=0), offsets.std(axis=0, ddof=1) / np.sqrt(len(offsets)), np.median(offsets, 0)
    return [(f"The {len(offsets)} OK answers within 20 px put the object's centre {mean[0]:+.2f} +- {se[0]:.2f} px right "
             f"and {mean[1]:+.2f} +- {se[1]:.2f} px down of the truth's projection (mean +- its standard error; median "
             f"{median[0]:+.2f}, {median[1]:+.2f} px)."), ""]


@section("lmo_gt_offset")
def render_lmo_gt_offset(folder: Path) -> str:
    """`flextrack evaluate gt-offset`: where the meshes' vertex colours put the objects in the frames, against the
    ground truth's projection."""
    data = json.loads((folder / "lmo_gt_offset.json").read_text())
    p, e = data["pooled"], data["edges"]["pooled"]

    def edge_cells(x: dict) -> str:
        return f"{x['du_px']:+.2f}, {x['dv_px']:+.2f} | {x['wider_px']:+.2f}, {x['taller_px']:+.2f}"

    lines = [("| object | instances | vertex colours: best shift right, down (px) | correlation there | at the truth "
              "| edges: outline right, down (px) | edges: wider, taller (px) |"),
             "|---|---:|---|---:|---:|---|---|",
             (f"| **pooled** | {data['instances']} | **{p['du_px']:+.1f}, {p['dv_px']:+.1f}** | {p['ncc_peak']:.3f} | "
              f"{p['ncc_at_truth']:.3f} | **{e['du_px']:+.2f} +- {e['du_se_px']:.2f}, {e['dv_px']:+.2f} +- "
              f"{e['dv_se_px']:.2f}** | {e['wider_px']:+.2f}, {e['taller_px']:+.2f} |")]
    for obj, b in data["by_object"].items():
        lines.append(f"| {obj} | {b['instances']} | {b['du_px']:+.1f}, {b['dv_px']:+.1f} | {b['ncc_peak']:.3f} | "
                     f"{b['ncc_at_truth']:.3f} | {edge_cells(data['edges']['by_object'][obj])} |")
    reach = max(data["shifts_px"])
    return "\n".join([*lines, "", (f"Vertex colours: shifts tried every {data['shifts_px'][1] - data['shifts_px'][0]:g} px "
                      f"up to {reach:g} px each way; a peak at {reach:g} px is at the grid's edge (no peak within it). "
                      f"Edges: the strongest colour step within {reach:g} px along each outward normal of the truth's "
                      "outline, its mean offset per side and instance; the outline's shift is half the difference of "
                      "opposite sides (+- its standard error over the instances), its growth their sum."),
                      provenance_line(data, data.get("command")), f"Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


@section("jpeg_bound")
def render_jpeg_bound(folder: Path) -> str:
    """`flextrack bench jpeg-bound`: the CPU a hostile progressive JPEG's decode costs, and what is refused."""
    data = json.loads((folder / "jpeg_bound.json").read_text())
    lines = ["| frame | case | scans | bytes | CPU ms (median) | outcome |", "|---|---|---:|---:|---:|---|"]
    for r in data["rows"]:
        outcome = "refused" if r["outcome"].startswith("refused") else r["outcome"]
        lines.append(f"| {r['size'].replace('x', ' x ')} | {r['case']} | {r['scans']:,} | {r['bytes'] / 1e6:.2f} MB | "
                     f"{r['cpu_ms']:.1f} | {outcome} |")
    return "\n".join([*lines, "", provenance_line(data["provenance"], "flextrack bench jpeg-bound --repeat 3")
                      + f" Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


@section("sdk_memory")
def render_sdk_memory(folder: Path) -> str:
    """`flextrack bench sdk-memory`: the client's held RSS over a long run, and its slope after the first minute."""
    from flextrack.benchmarks.sdk_memory_bench import SETTLE_S

    labels = {"track-live": "`track --live` (the runner and its record)", "sdk": "the SDK alone"}
    lines = ["| runner | frames | held RSS at 60 s -> end | slope after the first minute |", "|---|---:|---:|---:|"]
    sources = []
    for path in sorted(folder.glob("*.json"), reverse=True):
        data = json.loads(path.read_text())
        prov = data["provenance"]
        rows = read_csv(folder / data["files"][0])
        t = np.array([_num(r["t_s"]) for r in rows])
        rss = np.array([_num(r["rss_mib"]) for r in rows])
        later = t >= SETTLE_S
        slope = float(np.polyfit(t[later], rss[later], 1)[0] * 60) if later.sum() > 1 else 0.0
        fps = prov["options"]["fps"]
        at_60 = rss[later][0] if later.any() else rss[-1]
        lines.append(f"| {labels.get(prov['options']['runner'], prov['options']['runner'])} | "
                     f"{int(_num(rows[-1]['frames'])):,} | {at_60:.1f} -> {rss[-1]:.1f} MiB | **{slope:+.3f} MiB/min** "
                     f"({slope * 1024 * 1024 / 60 / fps:+.0f} B a frame) |")
        sources.append("- " + provenance_line(prov, f"flextrack bench sdk-memory --duration {prov['options']['duration']:g} "
                                              f"--fps {fps:g} --runner {prov['options']['runner']}").removeprefix("Source: "))
    return "\n".join([*lines, "", "Sources:", *sources, f"Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


@section("pvnet_circular")
def render_pvnet_circular(folder: Path) -> str:
    """pvnet alone (no prior: the global path of a first pose) on frames of the circular programs."""
    lines = ["| program | seed | frames | pose found | < 5 px | ADD(-S) 10 % | median px |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    total = below = 0
    prov = {}
    for path in sorted(folder.glob("*.json")):
        data = json.loads(path.read_text())
        prov = data["provenance"]
        spec = prov.get("frames_generator") or {}
        r = data["summary"]["all"]
        total += r["frames"]
        below += round(r["proj_below_5px"] * r["frames"])
        add_s = r.get("add_s_below_10pct", r["add_below_10pct"])  # runs before ADD-S: the default object's ADD
        lines.append(f"| {spec.get('motion', '?')} {spec.get('level', '?')} | {spec.get('seed', '?')} | {r['frames']} | "
                     f"{r['found']} | **{100 * r['proj_below_5px']:.1f} %** | {100 * add_s:.1f} % | "
                     f"{r['median_proj_px']:.2f} |")
    lines.append(f"| all | | {total} | | **{100 * below / max(total, 1):.1f} %** | | |")
    return "\n".join([*lines, "", ("ADD(-S): ADD-S (BOP's `adi`) for an object whose models_info.json gives "
                                  "symmetries, ADD otherwise; the default object has none, so this column is its ADD."), "", provenance_line(prov, "flextrack train pvnet-eval --model "
                      "flextrack/assets/models/pvnet_default/pvnet.onnx --bop SEQUENCE --obj-id 1 --jpeg 90 --out OUT")
                      + f" (the last run; every file records its own). Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


@section("bench_region")
def render_bench_region(folder: Path) -> str:
    """`flextrack bench region`: the region estimator's CPU time a frame, and the service's frame rate with it."""
    data = json.loads((folder / "bench_region.json").read_text())
    local, served = data["in_process"], data["grpc"]
    return "\n".join([
        "| figure | value |", "|---|---:|",
        (f"| CPU ms a frame, the JPEG decode included (process time): median (p90) | **{local['cpu_ms_median']:.1f}** "
         f"({local['cpu_ms_p90']:.1f}) |"),
        f"| the refinement alone: median (p90) | {local['refine_cpu_ms_median']:.1f} ({local['refine_cpu_ms_p90']:.1f}) |",
        f"| through gRPC, {served['callers']} closed-loop callers: frames/s | **{served['frames_per_s']:.1f}** |",
        (f"| frames/s per core (the process's CPU a frame, callers included: {served['process_cpu_ms_per_frame']:.1f} ms)"
         f" | {served['frames_per_s_per_core']:.1f} |"),
        f"| latency ms: p50 / p99 | {served['latency_ms_p50']:.1f} / {served['latency_ms_p99']:.1f} |",
        f"| answers under 5 px | {100 * served['share_proj_5px']:.1f} % of {served['answers']} |", "",
        provenance_line(data["provenance"]) + f" Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


@section("bench_pvnet")
def render_bench_pvnet(folder: Path) -> str:
    """`flextrack bench pvnet --out`: the pvnet estimator's batch-1 stages, CPU a frame and accuracy, as served
    (searches on the int8 copy) and the float baseline turn about on the same frames."""
    data = json.loads((folder / "bench_pvnet.json").read_text())
    lines = [("| frames | estimator | CPU ms a frame | wall ms: decode / inference / voting / PnP / refinement = **sum** "
             "| found, 2D < 5 px, ADD < 10 % |"), "|---|---|---:|---|---|"]
    for key, label in (("whole", "whole 640x480"), ("crops", "the SDK's crops")):
        part = data[key]
        for name, m in part["models"].items():
            st = m["stage_ms"]
            lines.append(f"| {label} ({part['median_request_kb']:.1f} kB) | {name} | {m['cpu_ms']:.1f} | "
                         + " / ".join(f"{st[k]:.1f}" for k in ("decode", "inference", "voting", "pnp", "refine"))
                         + f" = **{m['sum_ms']:.1f}** | {m['found']}/{part['frames']}, {100 * m['proj_below_5px']:.0f} %, "
                         f"{100 * m['add_below_10pct']:.0f} % |")
        if "cpu_ratio" in part:
            lines.append(f"| | as served / baseline | x{part['cpu_ratio']:.2f} | | |")
    load = ", ".join(f"{x:.1f}" for x in data.get("load_average", []))
    return "\n".join([*lines, "", f"Load average at the end (1, 5, 15 min): {load}.",
                      provenance_line(data["provenance"]) + f" Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


@section("bench_capacity")
def render_bench_capacity(folder: Path) -> str:
    """`flextrack bench capacity --cpu-cost`: each backend's server CPU a frame at a fixed offered load, the
    30 FPS devices per core it gives, and the latency measured at that load."""
    data = json.loads((folder / "bench_capacity.json").read_text())
    cost = data["cpu_cost"]
    lines = [(f"| backend | request kB | server CPU ms a frame (rounds) | devices per core at {data['fps']:g} FPS | "
             f"p50 / p99 ms at {cost['devices']} devices | errors |"), "|---|---:|---|---:|---|---:|"]
    for name, e in cost["backends"].items():
        rounds = ", ".join(f"{x:.2f}" for x in e["rounds_cpu_ms"])
        lat = e["latency_ms"]
        lines.append(f"| {name} | {data['request_kb'][name]:.1f} | **{e['cpu_ms_per_frame']:.2f}** ({rounds}) | "
                     f"**{e['devices_per_core']:.1f}** | {lat['p50_ms']:.1f} / {lat['p99_ms']:.1f} | "
                     f"{100 * e['error_rate']:.1f} % |")
    return "\n".join([*lines, "", provenance_line(data["provenance"])
                      + f" Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


@section("nees")
def render_nees(folder: Path) -> str:
    """`flextrack evaluate nees`: each estimator's held-out mean NEES against chi2(6)'s interval."""
    from flextrack.evaluation.nees_calibration import table

    data = json.loads((folder / "nees.json").read_text())
    max_px = data["provenance"]["options"]["max_2d_px"]
    return "\n".join([table(data["estimators"], max_px), "",
                      provenance_line(data["provenance"]) + f" Files: `{RESULTS_DIR.as_posix()}/{folder.name}/` "
                      "(`answers.csv`: every held-out answer's NEES, 2D error and error)."])


@section("pnp_noise")
def render_pnp_noise(folder: Path) -> str:
    """`flextrack evaluate nees --estimators pnp --pnp-noise-px ...`: pnp's held-out NEES by keypoint noise."""
    data = json.loads((folder / "pnp_noise.json").read_text())
    prov = data["provenance"]
    opts = prov.get("options", {})
    lines = ["| keypoint noise, px | N | mean NEES | 95 % interval (chi2) | median | share > 12.59 | tuning set asks for |",
             "|---:|---:|---:|---|---:|---:|---:|"]
    for e in data["estimators"]:
        s = e["heldout_below_max_2d"]
        lines.append(f"| {e['settings']['noise_px']:g} | {s['n']} | **{s['mean']:.2f}** | [{s['interval'][0]:.2f}, "
                     f"{s['interval'][1]:.2f}] | {s['median']:.2f} | {100 * s['share_above_q95']:.1f} % | "
                     f"{e['fitted_inflation']:.3g} |")
    noise = " ".join(f"{x:g}" for x in opts.get("pnp_noise_px", []))
    ransac = data["estimators"][0]["settings"].get("ransac_px")
    return "\n".join([
        (f"The default object's 9 keypoints at random poses, {100 * opts.get('pnp_outliers', 0):.0f} % of the frames "
         f"with one keypoint 15-60 px off, `ransac_px` {ransac:g}; held-out seed {opts.get('seed')}, the inflation's "
         f"tuning seed {opts.get('tune_seed')} (the last column: the factor that set would ask for; 1 is stored)."),
        "", *lines, "",
        provenance_line(prov, f"flextrack evaluate nees --estimators pnp --pnp-noise-px {noise} --out out/pnp_noise")
        + f" Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


@section("timing")
def render_timing(folder: Path) -> str:
    """`flextrack experiment timing`: per-call raw medians of both trackers, measured in one run."""
    rows = read_csv(folder / "timing.csv")
    paper = {r["operation"]: r for r in rows if r["tracker"] == "paper"}
    from client_sdk.slowdown import PIXEL2_FACTOR

    header = (f"| operation | filter, us | paper's tracker, us | filter / paper | filter x {PIXEL2_FACTOR:.2f} | the paper "
              "(stretched), us | filter's budget, us |")
    lines = [header, "|---|---:|---:|---:|---:|---:|---:|"]
    for r in (r for r in rows if r["tracker"] == "filter"):
        med, base = _num(r["median_us"]), _num(paper[r["operation"]]["median_us"])
        paper_us = f"{1e3 * _num(r['paper_ms']):.0f}" if r["paper_ms"] else "-"
        budget = f"{_num(r['budget_us']):.0f}" + (" (met)" if med <= _num(r["budget_us"]) else " (**over**)") \
            if r["budget_us"] else "-"
        lines.append(f"| {r['operation']} | **{med:.1f}** | {base:.1f} | {med / base:.1f} | "
                     f"{_num(r['stretched_median_us']):.0f} | {paper_us} | {budget} |")
    prov = read_provenance(folder / "timing.json")
    return "\n".join(lines + ["", provenance_line(prov) + f" Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


@section("demo")
def render_demo(folder: Path) -> str:
    """`flextrack demo`: its table as it printed it; the replay rows are checked against a fresh replay by a test."""
    from flextrack.runners.results import Summary, format_table

    data = json.loads((folder / "demo.json").read_text())
    prov = data["provenance"]
    table = format_table([(r["run"], Summary(**r["summary"])) for r in data["runs"]])
    return "\n".join(["```", table, "```", "", provenance_line(prov) + f" Files: `{RESULTS_DIR.as_posix()}/"
                      f"{folder.name}/`. The live row varies with the machine's timing; the replay rows are the same "
                      "on every run (virtual time; `tests/test_demo_table.py` replays them and compares to the digit)."])


def render_recording(folder: Path) -> str:
    """`experiment euroc --data` on a hand-held recording: errors, FINE share, time offset against the
    cross-correlation's."""
    from flextrack.experiments.euroc import DOUBTFUL_AFTER_S, DOUBTFUL_BEFORE_S

    rows = read_csv(folder / "euroc.csv")
    prov = read_provenance(folder / "euroc.json")
    data = Path(prov.get("options", {}).get("data") or "?")
    xcorr = _num(rows[0].get("offset_xcorr_ms", ""))
    for r in rows:
        r["fine_pct"] = f"{100 * _num(r['fine_share']):.0f} %"
    return "\n".join([
        (f"`{data.name}` (real phone IMU, motion-capture truth, a virtual object, the noisy oracle); errors on the "
         "frames in view called FINE; the share of in-view frames called FINE; the filter's camera-IMU time offset "
         f"at the end with its sigma, against {xcorr:.2f} ms from the gyroscope cross-correlated with the truth's "
         f"angular rate (`flextrack calibrate imu`); the frames in view within {DOUBTFUL_BEFORE_S * 1e3:.0f} ms before "
         f"to {DOUBTFUL_AFTER_S * 1e3:.0f} ms after a moment the truth jumped where the gyro did not are set aside "
         "(counted in view, not scored), the worst FINE one among them beside."),
        "", *_cells(rows, [("variant", "variant", ""), ("2D px", "proj_px", ".2f"), ("FINE / in view", "fine_pct", ""),
                           ("NEES", "nees_mean", ".1f"), ("worst FINE px", "worst_fine_px", ".1f"),
                           ("jitter px", "jitter_px", ".2f"), ("offset ms", "time_offset_ms", ".2f"),
                           ("sigma ms", "time_offset_sigma_ms", ".2f"), ("set aside", "set_aside_frames", ""),
                           ("worst FINE px set aside", "worst_set_aside_px", ".1f")]),
        "", provenance_line(prov, f"flextrack experiment euroc --data {data.as_posix()} --out out/{folder.name}")
        + f" Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


def render_ablation_recording(folder: Path) -> str:
    """`experiment ablation --data` on a hand-held recording."""
    rows = read_csv(folder / "ablation.csv")
    prov = read_provenance(folder / "ablation.json")
    data = Path(prov.get("options", {}).get("data") or "?")
    lines = ["| variant | GT px | Noisy px | GT worst FINE px | Noisy worst FINE px |", "|---|---|---|---|---|"]
    for v in dict.fromkeys(r["variant"] for r in rows):
        cell = {r["backend"]: r for r in rows if r["variant"] == v}
        lines.append(f"| {v} | " + " | ".join(f"{_num(cell[b][c]):.2f}" for c in ("proj_px", "worst_fine_px")
                                               for b in ("gt", "noisy")) + " |")
    return "\n".join([
        (f"The ablation on `{data.name}`: 2D error on the frames in view called FINE; the paper's variants start "
         "while moving (`init_require_still=False`)."), "", *lines, "",
        provenance_line(prov, f"flextrack experiment ablation --data {data.as_posix()} --out out/{folder.name}")
        + f" Files: `{RESULTS_DIR.as_posix()}/{folder.name}/`."])


for _name in ("euroc_nexus5_ar_a", "euroc_nexus5_ar_b"):
    section(_name)(render_recording)
section("ablation_nexus5_ar_b")(render_ablation_recording)


# --- the command -----------------------------------------------------------------------------------


def render(name: str, root: Path) -> str:
    if name not in RENDERERS:
        raise KeyError(f"no renderer for results:{name} (known: {', '.join(sorted(RENDERERS))})")
    folder = root / RESULTS_DIR / name
    if not folder.is_dir():
        raise FileNotFoundError(f"results:{name}: {folder} does not exist")
    return RENDERERS[name](folder).rstrip("\n") + "\n"


def regenerate(text: str, root: Path) -> str:
    """`text` with every marked section replaced by what its stored results give."""
    return _MARKER.sub(lambda m: m.group(1) + render(m.group("name"), root) + m.group(4), text)


def pages(root: Path) -> list[Path]:
    return sorted({p for pattern in PAGES for p in root.glob(pattern) if p.is_file()})


def update(root: Path, check: bool = False) -> list[Path]:
    """The pages whose sections differ from their results; rewritten unless `check`."""
    stale = []
    for page in pages(root):
        text = page.read_text()
        new = regenerate(text, root)
        if new != text:
            stale.append(page)
            if not check:
                page.write_text(new)
    return stale


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--root", type=Path, default=Path("."), help="the repository (README.md, docs/, docs/results/)")
    parser.add_argument("--check", action="store_true", help="change nothing; exit 1 when a section differs")
    parser.add_argument("--list", action="store_true", help="list the known result sections and exit")


def run(args) -> int:
    if args.list:
        for name in sorted(RENDERERS):
            print(f"{name}: {(RENDERERS[name].__doc__ or '').strip()}")
        return 0
    if not (args.root / RESULTS_DIR).is_dir() or not pages(args.root):
        print(f"flextrack report: {args.root} holds no {RESULTS_DIR.as_posix()}/ or no pages; give the repository "
              f"with --root (or run it there)", file=sys.stderr)
        return 2
    try:
        stale = update(args.root, check=args.check)
    except (KeyError, FileNotFoundError, ValueError) as exc:
        print(f"flextrack report: {exc}", file=sys.stderr)
        return 2
    for page in stale:
        print(f"{'differs from its results' if args.check else 'regenerated'}: {page}")
    if not stale:
        print("every results section matches its stored results")
    return 1 if args.check and stale else 0
