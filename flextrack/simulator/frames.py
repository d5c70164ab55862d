"""Frames of a sequence folder, rendered on demand (lazily) or all at once.

Everything needed is in the folder: the model (rig.yaml), the object's world pose T_WO, the
ground-truth T_CO per frame (scene_gt.json), the intrinsics, and the room's seed
(sequence.yaml `generator.scene_seed`). Frames are written BOP-style: rgb/%06d.png,
mask/%06d.png (0/255) and depth/%06d.png (uint16, mm, as scene_camera.json's depth_scale 1.0 says).
"""

from __future__ import annotations

from pathlib import Path
from typing import Self

import cv2
import numpy as np

from flextrack.formats.sequence import Sequence, load
from flextrack.simulator.render import RenderedFrame, Renderer
from flextrack.simulator.scene import make_scene


class SequenceFrames:
    """`frame(i)` renders frame i of a sequence (or reads it back when already on disk)."""

    def __init__(self, seq: Sequence | str | Path):
        self.seq = seq if isinstance(seq, Sequence) else load(seq)
        seed = int(self.seq.meta.get("generator", {}).get("scene_seed", 0))
        self._renderer: Renderer | None = None
        self._scene = make_scene(seed)

    def _gl(self) -> Renderer:
        if self._renderer is None:
            self._renderer = Renderer(self.seq.camera, self.seq.model_path, scene=self._scene, T_WO=self.seq.T_WO)
        return self._renderer

    def render(self, frame_id: int) -> RenderedFrame:
        if int(frame_id) not in self.seq.gt_T_CO:
            raise KeyError(f"frame {frame_id} is not in sequence {self.seq.name}")
        return self._gl().render(self.seq.gt_T_CO[int(frame_id)])

    def frame(self, frame_id: int) -> RenderedFrame:
        """The frame from disk when written, else rendered now (and written)."""
        paths = self.paths(frame_id)
        if all(p.exists() for p in paths):
            rgb = cv2.imread(str(paths[0]), cv2.IMREAD_COLOR)[..., ::-1]
            mask = cv2.imread(str(paths[1]), cv2.IMREAD_GRAYSCALE) > 127
            depth = cv2.imread(str(paths[2]), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000.0
            return RenderedFrame(np.ascontiguousarray(rgb), mask, depth)
        return self.write(frame_id)

    def paths(self, frame_id: int) -> tuple[Path, Path, Path]:
        name = f"{int(frame_id):06d}.png"
        return tuple(self.seq.root / d / name for d in ("rgb", "mask", "depth"))

    def write(self, frame_id: int) -> RenderedFrame:
        frame = self.render(frame_id)
        rgb_path, mask_path, depth_path = self.paths(frame_id)
        for p in (rgb_path, mask_path, depth_path):
            p.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(rgb_path), frame.rgb[..., ::-1])
        cv2.imwrite(str(mask_path), frame.mask.astype(np.uint8) * 255)
        cv2.imwrite(str(depth_path), np.clip(np.round(frame.depth * 1000.0), 0, 65535).astype(np.uint16))
        return frame

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def render_sequence(root: str | Path, frame_ids=None, progress: bool = False) -> int:
    """Render and write the given frames (all when None); returns how many were written."""
    with SequenceFrames(root) as frames:
        ids = frames.seq.frame_ids if frame_ids is None else frame_ids
        if progress:
            from tqdm import tqdm
            ids = tqdm(ids, desc="render", unit="frame")
        for i in ids:
            frames.write(int(i))
        return len(frames.seq.frame_ids if frame_ids is None else frame_ids)
