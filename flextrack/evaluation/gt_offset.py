"""`flextrack evaluate gt-offset`: does a BOP dataset's ground truth sit where its images show the objects?

An estimator that fits the image is scored against the ground truth; where the truth is off in the image by a
constant, every answer is "wrong" by it. This checks the truth with evidence no estimator shapes: the meshes'
own vertex colours (scanned with the object, not fitted to these frames). For each well-visible instance, the
vertex colours of the faces turned to the camera are correlated (normalised cross-correlation over R, G, B)
with the frame's pixels at the vertices' projections moved by every image shift of a grid; the pooled
correlation's peak is where the images put the objects relative to the truth.

A second, independent measure: the frames' own edges. Along the truth's outline (the mesh's, drawn at the true
pose), the strongest colour step within `--reach-px` along each outward normal; per instance the mean offset of
the lines that face up, down, left and right. Half the difference of opposite sides is where the frames'
outline sits against the truth's (a shift moves them the same way), their sum how much wider or taller it is
(a size or depth difference, or a blurred rim, moves them apart). The scanned colours weigh the interior, where
lighting differs from the scan's; the edges weigh only the outline.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from flextrack.evaluation.prior_eval import bop_instances, object_ids
from flextrack.provenance import command_line, of_args

FACING_COS = 0.3  # vertices whose normal turns at least this much to the camera: seen, not grazing
EDGE_STEP_PX = 0.25  # the samples along each normal
EDGE_MIN_CHANGE = 20.0  # colour change (0-255, over 1 px each side) below which a line finds no edge
SIDE_COS = 0.8  # a line faces a side (up, down, left, right) when its normal is this near that direction
SIDES = {"top": (0, -1), "bottom": (0, 1), "left": (-1, 0), "right": (1, 0)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--bop", type=Path, required=True, help="BOP folder (models/ with vertex-coloured .ply)")
    parser.add_argument("--obj-id", default="all", help="BOP object id, a comma list, or 'all' of models/")
    parser.add_argument("--split", default="test", help="the BOP split folder under --bop")
    parser.add_argument("--min-visib", type=float, default=0.8,
                        help="instances at least this visible (occluders' pixels would read as the object's)")
    parser.add_argument("--reach-px", type=float, default=3.0, help="largest image shift tried, each axis; how far along each normal an edge is looked for")
    parser.add_argument("--step-px", type=float, default=0.5, help="the grid's step")
    parser.add_argument("--out", type=Path, default=None, help="result JSON (default: print only)")


def coloured_vertices(mesh, ply: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (m), their normals and RGB colours of the BOP mesh read from `ply` (`load_model`); ValueError when
    it has none."""
    if getattr(mesh.visual, "kind", None) != "vertex":  # trimesh makes up grey ones for a mesh without
        raise ValueError(f"{ply} has no vertex colours")
    return (np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals),
            np.asarray(mesh.visual.vertex_colors)[:, :3].astype(np.float32))


def outline_of(mesh):
    """The mesh's outline at a pose, as the pvnet refinement draws it (`ContourRefiner.outline`; no keypoints:
    only the outline is used)."""
    from estimators.contour_refine import ContourRefineConfig, ContourRefiner

    return ContourRefiner(np.asarray(mesh.vertices), np.asarray(mesh.faces), np.zeros((1, 3)),
                          ContourRefineConfig(points=200))


def shift_correlations(image: np.ndarray, K: np.ndarray, T_CO: np.ndarray, vertices: tuple,
                       shifts: np.ndarray) -> np.ndarray | None:
    """(len(shifts), len(shifts)) correlations, rows by the vertical shift, columns by the horizontal (px: the
    image content at the truth's projection plus the shift); None when too few vertices face the camera."""
    points, normals, colours = vertices
    P = points @ T_CO[:3, :3].T + T_CO[:3, 3]
    facing = np.einsum("ij,ij->i", normals @ T_CO[:3, :3].T, P) < -FACING_COS * np.linalg.norm(P, axis=1)
    if np.count_nonzero(facing) < 30:
        return None
    uv = (P[facing] @ K.T)[:, :2] / P[facing, 2:3]
    c = colours[facing] - colours[facing].mean(axis=0)
    dv, du = np.meshgrid(shifts, shifts, indexing="ij")
    at = (uv[None] + np.stack([du.ravel(), dv.ravel()], axis=1)[:, None, :]).astype(np.float32)  # (shift, N, 2)
    seen = cv2.remap(image, at[..., 0], at[..., 1], cv2.INTER_LINEAR)  # every shift's samples in one call
    s = seen - seen.mean(axis=1, keepdims=True)
    ncc = (s * c).sum(axis=(1, 2)) / (np.linalg.norm(s, axis=(1, 2)) * np.linalg.norm(c) + 1e-9)
    return ncc.reshape(len(shifts), len(shifts))


def outline_steps(image: np.ndarray, K: np.ndarray, T_CO: np.ndarray, refiner, reach_px: float) -> dict[str, float]:
    """Per side (top, bottom, left, right) of the truth's outline, the mean offset (px, outwards positive) of the
    frame's strongest colour step within reach_px along each outward normal; sides with fewer than 3 lines
    that find one are left out."""
    outline = refiner.outline(K, T_CO[:3, :3], T_CO[:3, 3], image.shape[:2])
    if outline is None:
        return {}
    points, normals, _ = outline
    k = round(1.0 / EDGE_STEP_PX)  # 1 px each side of a boundary
    offsets = np.arange(-(reach_px + 1.0), reach_px + 1.0 + 1e-9, EDGE_STEP_PX)
    at = (points[:, None, :] + offsets[None, :, None] * normals[:, None, :]).astype(np.float32)
    profile = cv2.remap(image, at[..., 0], at[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    change = np.linalg.norm(profile[:, 2 * k:] - profile[:, :-2 * k], axis=2)  # at the boundaries offsets[k:-k]
    boundary = offsets[k:-k]
    best = np.argmax(change, axis=1)
    found = (change[np.arange(len(best)), best] >= EDGE_MIN_CHANGE) & (best > 0) & (best < len(boundary) - 1)
    out = {}
    for side, direction in SIDES.items():
        lines = found & (normals @ np.array(direction, float) > SIDE_COS)
        if np.count_nonzero(lines) >= 3:
            out[side] = float(boundary[best[lines]].mean())
    return out


def edge_summary(per_instance: list[dict[str, float]]) -> dict:
    """Pooled over instances: each side's mean offset and its standard error, and from them where the frames'
    outline sits against the truth's (right, down) and how much wider and taller it is (px)."""
    sides = {}
    for side in SIDES:
        v = np.array([d[side] for d in per_instance if side in d])
        sides[side] = {"instances": len(v), "mean_px": float(v.mean()) if len(v) else float("nan"),
                       "se_px": float(v.std(ddof=1) / np.sqrt(len(v))) if len(v) > 1 else float("nan")}
    m = {side: sides[side]["mean_px"] for side in SIDES}
    se = {side: sides[side]["se_px"] for side in SIDES}
    return {"sides": sides, "du_px": (m["right"] - m["left"]) / 2, "dv_px": (m["bottom"] - m["top"]) / 2,
            "du_se_px": float(np.hypot(se["right"], se["left"]) / 2), "dv_se_px": float(np.hypot(se["bottom"], se["top"]) / 2),
            "wider_px": m["right"] + m["left"], "taller_px": m["bottom"] + m["top"]}


def peak(grid: np.ndarray, shifts: np.ndarray) -> dict:
    i, j = np.unravel_index(int(np.argmax(grid)), grid.shape)
    zero = len(shifts) // 2
    return {"du_px": float(shifts[j]), "dv_px": float(shifts[i]), "ncc_peak": float(grid[i, j]),
            "ncc_at_truth": float(grid[zero, zero])}


def run(args: argparse.Namespace) -> int:
    from flextrack.simulator.render import load_model

    prog = "flextrack evaluate gt-offset"
    if not (args.bop / args.split).is_dir():
        print(f"{prog}: no BOP split folder {args.bop / args.split}", file=sys.stderr)
        return 2
    if args.step_px <= 0 or args.reach_px < args.step_px:
        print(f"{prog}: --step-px must be positive and --reach-px at least one step", file=sys.stderr)
        return 2
    try:
        obj_ids = object_ids(args.obj_id, args.bop / "models")
        plys = {o: args.bop / "models" / f"obj_{o:06d}.ply" for o in obj_ids}
        meshes = {o: load_model(ply) for o, ply in plys.items()}  # once, for both measures
        vertices = {o: coloured_vertices(mesh, plys[o]) for o, mesh in meshes.items()}
        refiners = {o: outline_of(mesh) for o, mesh in meshes.items()}
    except (ValueError, OSError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    instances = bop_instances(args.bop, obj_ids, args.split, "all", args.min_visib)
    if not instances:
        print(f"{prog}: no instances at least {args.min_visib} visible under {args.bop / args.split}", file=sys.stderr)
        return 2
    n = round(args.reach_px / args.step_px)
    shifts = np.arange(-n, n + 1) * args.step_px
    grids: dict[int, list[np.ndarray]] = {}
    edges: dict[int, list[dict[str, float]]] = {}
    image, image_path = None, None
    for k, inst in enumerate(instances):
        if inst.rgb_path != image_path:
            image_path = inst.rgb_path
            bgr = cv2.imread(str(image_path))
            if bgr is None:
                print(f"{prog}: cannot read the image {image_path}", file=sys.stderr)
                return 2
            image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32)
        grid = shift_correlations(image, inst.K, inst.T_gt, vertices[inst.obj_id], shifts)
        if grid is not None:
            grids.setdefault(inst.obj_id, []).append(grid)
        edges.setdefault(inst.obj_id, []).append(outline_steps(image, inst.K, inst.T_gt, refiners[inst.obj_id],
                                                               args.reach_px))
        if (k + 1) % 100 == 0:
            print(f"  {k + 1} of {len(instances)} instances", file=sys.stderr, flush=True)
    if not grids:
        print(f"{prog}: no instance shows enough of its mesh's surface to the camera", file=sys.stderr)
        return 2
    pooled = np.mean([g for gs in grids.values() for g in gs], axis=0)
    result = {"command": command_line("evaluate", "gt-offset"), **of_args(args),
              "instances": sum(len(g) for g in grids.values()), "shifts_px": shifts.tolist(),
              "pooled": peak(pooled, shifts), "pooled_grid": pooled.round(5).tolist(),
              "by_object": {str(o): {"instances": len(g), **peak(np.mean(g, axis=0), shifts)}
                            for o, g in sorted(grids.items())},
              "edges": {"pooled": edge_summary([d for ds in edges.values() for d in ds]),
                        "by_object": {str(o): edge_summary(ds) for o, ds in sorted(edges.items())}}}
    p = result["pooled"]
    print(f"{result['instances']} instances at least {args.min_visib:g} visible: the vertex colours match the frames "
          f"best {p['du_px']:+.1f} px right and {p['dv_px']:+.1f} px down of the ground truth's projection "
          f"(correlation {p['ncc_peak']:.3f}, {p['ncc_at_truth']:.3f} at the truth)")
    for o, b in result["by_object"].items():
        print(f"  obj {o}: {b['instances']} instances, peak at ({b['du_px']:+.1f}, {b['dv_px']:+.1f}) px, "
              f"correlation {b['ncc_peak']:.3f} ({b['ncc_at_truth']:.3f} at the truth)")
    e = result["edges"]["pooled"]
    print(f"the frames' edges along the truth's outline: it sits {e['du_px']:+.2f} +- {e['du_se_px']:.2f} px right and "
          f"{e['dv_px']:+.2f} +- {e['dv_se_px']:.2f} px down of the truth's, {e['wider_px']:+.2f} px wider and "
          f"{e['taller_px']:+.2f} px taller")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.out}")
    return 0
