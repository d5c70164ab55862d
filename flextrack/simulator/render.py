"""Offscreen rendering of a BOP model with pyrender on EGL: RGB, object mask and depth.

Two modes, one class:
- object only (`scene=None`): the object on a black background, lit by a directional light given
  in the camera frame, for training data (composite a background with the mask);
- scene (`scene=SceneStyle`, `T_WO`): the object standing on the textured table in the room.

Frames: pyrender's camera looks down its -z axis with y up; ours (OpenCV) looks down +z with
y down, so the GL camera sits at T_WC @ diag(1, -1, -1, 1). BOP models are in mm and are scaled to
metres on load. The RGB is antialiased (multisampled); mask and depth come from a second,
segmentation pass that samples every pixel at its centre, exactly as projecting the model does.
"""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from dataclasses import dataclass
from pathlib import Path
from typing import Self

import numpy as np
import pyrender
import trimesh

from flextrack.geometry import se3
from flextrack.geometry.camera import PinholeCamera
from flextrack.simulator.scene import SceneStyle, TexturedQuad

T_CG = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL camera frame -> OpenCV camera frame
DEFAULT_LIGHT_DIR_C = np.array([0.3, 0.6, 1.0]) / np.linalg.norm([0.3, 0.6, 1.0])  # from above-left


@dataclass
class RenderedFrame:
    rgb: np.ndarray  # (H, W, 3) uint8
    mask: np.ndarray  # (H, W) bool: visible object pixels
    depth: np.ndarray  # (H, W) float32 metres, 0 where nothing was hit


def load_model(model_path: str | Path) -> trimesh.Trimesh:
    """A BOP .ply (mm) as a trimesh in metres, keeping its vertex colours, texture and normals."""
    path = Path(model_path)
    if not path.is_file():
        raise FileNotFoundError(f"object model {path} does not exist")
    mesh = trimesh.load(path, process=False, force="mesh")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path} holds no triangle mesh")
    normals = mesh.vertex_normals.copy()
    mesh.apply_scale(0.001)
    mesh.vertex_normals = normals
    return mesh


def _light_pose(direction: np.ndarray) -> np.ndarray:
    """Pose of a pyrender light node that shines along `direction` (its -z axis)."""
    z = -np.asarray(direction, float) / np.linalg.norm(direction)
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return se3.make(np.stack([x, np.cross(z, x), z], axis=1), np.zeros(3))


def _quads_mesh(quads: list[TexturedQuad]) -> pyrender.Mesh:
    """Quads that share one texture as one mesh (one draw call, one texture upload)."""
    positions, normals, uvs, indices = [], [], [], []
    for k, quad in enumerate(quads):
        c = quad.corners
        normal = np.cross(c[1] - c[0], c[3] - c[0])
        u, v = quad.repeats
        positions.append(c)
        normals.append(np.tile(normal / np.linalg.norm(normal), (4, 1)))
        uvs.append([[0, 0], [u, 0], [u, v], [0, v]])
        indices.append(4 * k + np.array([[0, 1, 2], [0, 2, 3]]))
    texture = pyrender.Texture(source=quads[0].texture, source_channels="RGB")
    material = pyrender.MetallicRoughnessMaterial(baseColorTexture=texture, metallicFactor=0.0, roughnessFactor=0.9)
    primitive = pyrender.Primitive(
        positions=np.vstack(positions).astype(np.float32), normals=np.vstack(normals).astype(np.float32),
        texcoord_0=np.vstack(uvs).astype(np.float32), indices=np.vstack(indices).astype(np.uint32),
        material=material)
    return pyrender.Mesh([primitive])


class Renderer:
    """Renders one object model with one camera; reuse it for many frames (GL context is kept).

    Renderer(camera, model_path)                          object only, black background
    Renderer(camera, model_path, scene=style, T_WO=T)     the object at T_WO in the room
    """

    def __init__(self, camera: PinholeCamera | None = None, model_path: str | Path | None = None, *,
                 scene: SceneStyle | None = None, T_WO: np.ndarray | None = None,
                 znear: float = 0.02, zfar: float = 20.0):
        from flextrack import assets

        self.camera = camera or PinholeCamera.linemod()
        self.model_path = Path(model_path) if model_path is not None else assets.default_object_model()
        if scene is not None and T_WO is None:
            raise ValueError("scene mode needs the object's world pose T_WO")
        self.T_WO = np.eye(4) if T_WO is None else np.asarray(T_WO, float)
        self.scene_style = scene
        self.mesh = load_model(self.model_path)
        object_mesh = pyrender.Mesh.from_trimesh(self.mesh, smooth=True)  # keeps vertex colours / texture
        for primitive in object_mesh.primitives:  # matte and opaque: a painted object, not metal
            primitive.material.metallicFactor = 0.0
            primitive.material.roughnessFactor = 0.7
            primitive.material.alphaMode = "OPAQUE"
        self._scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[0.3, 0.3, 0.3])
        self._object = self._scene.add(object_mesh, pose=self.T_WO)
        cam = self.camera
        # GL pixel centres sit at +0.5, OpenCV's at integers: shift the principal point by half a pixel.
        gl_camera = pyrender.IntrinsicsCamera(cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5, znear, zfar)
        self._camera = self._scene.add(gl_camera)
        self._sun = self._scene.add(pyrender.DirectionalLight(color=np.ones(3), intensity=3.0))
        self._room: list[pyrender.Node] = []
        if scene is not None:
            by_texture: dict[int, list[TexturedQuad]] = {}
            for quad in scene.quads:
                by_texture.setdefault(id(quad.texture), []).append(quad)
            self._room = [self._scene.add(_quads_mesh(group)) for group in by_texture.values()]
            light = scene.lighting
            self._scene.ambient_light = np.full(3, light.ambient)
            self._scene.set_pose(self._sun, _light_pose(light.sun_direction_W))
            self._sun.light.intensity = light.sun_intensity
            self._scene.add(pyrender.PointLight(color=light.lamp_colour, intensity=light.lamp_intensity),
                            pose=se3.make(np.eye(3), light.lamp_position_W))
        self._gl = pyrender.OffscreenRenderer(cam.width, cam.height)

    def render(self, T_CO: np.ndarray, *, light_dir_C: np.ndarray | None = None,
               light_intensity: float | None = None, ambient: float | None = None) -> RenderedFrame:
        """The frame seen with object pose T_CO (m). Light options apply to object-only mode."""
        T_CO = np.asarray(T_CO, float)
        if T_CO.shape != (4, 4) or not np.all(np.isfinite(T_CO)):
            raise ValueError("T_CO must be a finite 4x4 matrix")
        T_WC = self.T_WO @ se3.inverse(T_CO)
        self._scene.set_pose(self._camera, T_WC @ T_CG)
        if self.scene_style is None:
            direction_C = DEFAULT_LIGHT_DIR_C if light_dir_C is None else np.asarray(light_dir_C, float)
            self._scene.set_pose(self._sun, T_WC @ _light_pose(direction_C))
            self._sun.light.intensity = 3.0 if light_intensity is None else float(light_intensity)
            self._scene.ambient_light = np.full(3, 0.3 if ambient is None else float(ambient))
        rgb, _ = self._gl.render(self._scene)
        mask, depth = self._visible_mask_and_depth()
        return RenderedFrame(rgb, mask, depth.astype(np.float32))

    def _visible_mask_and_depth(self) -> tuple[np.ndarray, np.ndarray]:
        """Object pixels (occlusion by the room included) and depth, sampled at pixel centres.

        pyrender's segmentation pass draws without multisampling, so it samples each pixel at its
        centre, as projection does; the multisampled main pass resolves depth by taking one sample
        whose place in the pixel depends on the driver, which would shift a mask by up to half a pixel.
        """
        colours = {node: np.zeros(3) for node in self._room}
        colours[self._object] = np.full(3, 255)
        seg, depth = self._gl.render(self._scene, flags=pyrender.RenderFlags.SEG, seg_node_map=colours)
        return seg[..., 0] >= 128, depth

    def close(self) -> None:
        if self._gl is not None:
            self._gl.delete()
            self._gl = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
