"""Offscreen rendering with pyrender on Mesa's software EGL: parts -> pyrender meshes, RGB + metric z-depth.

Lighting (fixed): objects are lit by two white directional lights fixed in the OBJECT frame (so a surface point
looks the same from every view, up to the weak specular term): a key light (intensity 2.5) from above-front-left
and a fill light (1.0) from above-behind-right, plus ambient 0.35 of the albedo; surfaces are double sided,
non-metallic, roughness 0.9. Drive scenes are rendered unlit (texture colour as is); TORCS textures carry their
own shading.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

# pyrender picks its OpenGL platform when OpenGL is first imported: EGL (headless, llvmpipe) unless the user
# chose another one (e.g. osmesa).
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import pyrender  # noqa: E402
from PIL import Image  # noqa: E402

# OpenCV camera (x right, y down, z forward) -> pyrender/OpenGL camera (x right, y up, z backward).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
ALPHA_CUTOFF = 0.5
AMBIENT = 0.35
# (direction the light travels, in the object frame: x right, y down, z away from the az=0 camera; intensity)
OBJECT_LIGHTS = (((0.5, 0.8, 0.6), 2.5), ((-0.6, 0.7, -0.5), 1.0))


def _light_pose(direction) -> np.ndarray:
    """Pose (4,4) of a pyrender directional light (it shines along its node's -z) travelling along `direction`."""
    z = -np.asarray(direction, dtype=np.float64)
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    return T


@dataclass
class Part:
    """Triangles sharing one material. positions (N,3), faces (M,3) int, uvs (N,2) or None, image RGBA or None,
    color (4,) in [0,1] multiplied with the texture."""

    positions: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None
    image: Image.Image | None
    color: np.ndarray


def transform_parts(parts: list[Part], A: np.ndarray, b: np.ndarray | None = None) -> list[Part]:
    """Apply x -> A x + b to every part's positions (A (3,3), b (3,))."""
    b = np.zeros(3) if b is None else b
    return [Part(p.positions @ A.T + b, p.faces, p.uvs, p.image, p.color) for p in parts]


def bounds(parts: list[Part]) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (3,), (3,) over the vertices that faces use."""
    used = [p.positions[np.unique(p.faces)] for p in parts if len(p.faces)]
    pts = np.concatenate(used)
    return pts.min(0), pts.max(0)


def _alpha_shader_dir() -> str:
    """A copy of pyrender's shaders whose fragment shaders discard texels with alpha < ALPHA_CUTOFF.

    Without it, sprite textures (trees, fences, chair weaving) write opaque rectangles into colour and depth.
    """
    src = Path(pyrender.__file__).parent / "shaders"
    dst = Path(tempfile.mkdtemp(prefix="nvs-shaders-"))
    for f in src.iterdir():
        shutil.copy(f, dst / f.name)
    for name in ("mesh.frag", "flat.frag"):
        text = (dst / name).read_text()
        pattern = r"(base_color = base_color \* [^\n]*texture\(material\.base_color_texture, uv_0\)\)?;)"
        patched, n = re.subn(pattern, r"\1\n    if (texture(material.base_color_texture, uv_0).a < "
                             f"{ALPHA_CUTOFF}) discard;", text)
        if n != 1:
            raise RuntimeError(f"cannot patch pyrender's {name} for alpha discard (pyrender version changed?)")
        (dst / name).write_text(patched)
    return str(dst)


def _texture(image: Image.Image) -> pyrender.Texture:
    im = image.convert("RGBA")
    sampler = pyrender.Sampler(magFilter=9729, minFilter=9987, wrapS=10497, wrapT=10497)  # linear, mip, repeat
    return pyrender.Texture(source=np.asarray(im), source_channels="RGBA", sampler=sampler)


def to_pyrender(parts: list[Part]) -> pyrender.Mesh:
    """Parts -> one pyrender mesh with flat (per-face) normals, opaque double-sided materials."""
    prims = []
    tex_cache: dict[int, pyrender.Texture] = {}
    for p in parts:
        if len(p.faces) == 0:
            continue
        f = p.faces.reshape(-1)
        pos = p.positions[f].astype(np.float32)
        tri = pos.reshape(-1, 3, 3)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        normals = np.repeat(n, 3, axis=0).astype(np.float32)
        color = np.asarray(p.color, dtype=np.float64).copy()
        color[3] = 1.0  # material transparency (glass) is rendered opaque; only texture alpha cuts out
        kwargs = {}
        if p.image is not None and p.uvs is not None:
            key = id(p.image)
            if key not in tex_cache:
                tex_cache[key] = _texture(p.image)
            # OBJ/AC3D uv origin is the image's bottom-left, as in OpenGL (pyrender uploads images bottom row first).
            kwargs = dict(texcoord_0=p.uvs[f].astype(np.float32))
            mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=color, baseColorTexture=tex_cache[key],
                                                     metallicFactor=0.0, roughnessFactor=0.9,
                                                     doubleSided=True, alphaMode="OPAQUE")
        else:
            mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=color, metallicFactor=0.0,
                                                     roughnessFactor=0.9, doubleSided=True, alphaMode="OPAQUE")
        prims.append(pyrender.Primitive(positions=pos, normals=normals, material=mat, **kwargs))
    if not prims:
        raise ValueError("no triangles")
    return pyrender.Mesh(prims)


_CONTEXTS_OPENED = 0


def contexts_opened() -> int:
    """Offscreen contexts this process has opened (a process that has opened one cannot fork renderers safely)."""
    return _CONTEXTS_OPENED


class Renderer:
    """One offscreen context of size x size rendering a pinhole camera given in OpenCV conventions."""

    def __init__(self, size: int, K: np.ndarray, znear: float, zfar: float, bg_color=(1.0, 1.0, 1.0),
                 lit: bool = True):
        global _CONTEXTS_OPENED
        _CONTEXTS_OPENED += 1
        self.size = size
        self.lit = lit
        self._r = pyrender.OffscreenRenderer(size, size)
        # pyrender measures the principal point from the image EDGE (pixel centres at +0.5) while our K puts
        # pixel centres at integer coordinates, hence +0.5 on both axes (pinned by the convention test).
        self.camera = pyrender.IntrinsicsCamera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2] + 0.5, cy=K[1, 2] + 0.5,
                                                znear=znear, zfar=zfar)
        self.scene = pyrender.Scene(bg_color=list(bg_color) + [1.0], ambient_light=[AMBIENT] * 3)
        self.cam_node = self.scene.add(self.camera)
        if lit:
            for direction, intensity in OBJECT_LIGHTS:
                self.scene.add(pyrender.DirectionalLight(color=np.ones(3), intensity=intensity),
                               pose=_light_pose(direction))
        self._r._renderer._program_cache = pyrender.shader_program.ShaderProgramCache(shader_dir=_alpha_shader_dir())
        self._mesh_nodes = []

    def set_mesh(self, mesh: pyrender.Mesh) -> None:
        for node in self._mesh_nodes:
            self.scene.remove_node(node)
        self._mesh_nodes = [self.scene.add(mesh)]

    def render(self, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """OpenCV camera-to-world (4,4) -> RGB (S,S,3) uint8, z-depth (S,S) float32 (0 = nothing hit)."""
        pose = T_world_cam @ CV_TO_GL
        self.scene.set_pose(self.cam_node, pose)
        flags = pyrender.RenderFlags.SKIP_CULL_FACES
        if not self.lit:
            flags |= pyrender.RenderFlags.FLAT
        color, depth = self._r.render(self.scene, flags=flags)
        return np.ascontiguousarray(color[..., :3]), np.ascontiguousarray(depth, dtype=np.float32)

    def close(self) -> None:
        self._r.delete()


def supersampled(renderer: Renderer, T_world_cam: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Render at factor x size (odd factor) and box-filter RGB; depth is the centre sample of each block.

    With an odd factor the centre sample lies exactly on the output pixel centre, so depth stays a point sample
    consistent with K at the output size, while colour is antialiased.
    """
    rgb, depth = renderer.render(T_world_cam)
    if factor == 1:
        return rgb, depth
    S = rgb.shape[0] // factor
    rgb = rgb.reshape(S, factor, S, factor, 3).astype(np.float32).mean(axis=(1, 3))
    c = factor // 2
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8), np.ascontiguousarray(depth[c::factor, c::factor])


def scaled_K(K256: np.ndarray, size: int) -> np.ndarray:
    """K (3,3) at 256^2 -> K (3,3) at size^2 (nvs.core.geometry.scale_intrinsics: cx' = (cx+0.5)s-0.5)."""
    import torch

    from nvs.core.geometry import scale_intrinsics

    return scale_intrinsics(torch.tensor(K256, dtype=torch.float64), size / 256.0).numpy()
