"""Novel views of a latent scene: render it from any camera, or orbit around it as a GIF.

The orbit keeps the original camera's intrinsics, height above the ground and distance to the
orbit centre (where the original optical axis meets the ground, or the objects' centroid), and
turns the camera about the vertical axis through that centre.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from prismonet.files import write_image
from prismonet.geometry.camera import Camera, look_at, resize_intrinsics
from prismonet.scene.latent_scene import LatentScene


def orbit_center(scene: LatentScene) -> torch.Tensor:
    """Where the camera's optical axis meets the ground, else the centroid of the objects."""
    T = scene.camera.T_world_cam
    c, axis = T[:3, 3], T[:3, 2]
    if axis[2] < -1e-6:
        t = (scene.ground_z - c[2]) / axis[2]
        return c + t * axis
    return scene.position.mean(0)


def orbit_cameras(scene: LatentScene, frames: int = 24, degrees: float = 360.0, size: int | None = None) -> list[Camera]:
    """``frames`` cameras turning ``degrees`` about the vertical through ``orbit_center`` (the first
    is the scene's own camera, up to float rounding). ``size``: square image side (default: as is)."""
    if frames <= 0:
        raise ValueError(f"frames must be positive, got {frames}")
    cam = scene.camera
    center = orbit_center(scene)
    eye0 = cam.T_world_cam[:3, 3]
    rel = eye0 - center
    K, H, W = cam.K, cam.height, cam.width
    if size is not None:
        K, H, W = resize_intrinsics(cam.K, size / cam.width, size / cam.height), size, size
    cams = []
    step = degrees / frames if abs(degrees) >= 360 else degrees / max(frames - 1, 1)
    for i in range(frames):
        a = math.radians(step * i)
        R = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
        cams.append(Camera(K, look_at(center + R @ rel, center), H, W))
    return cams


@torch.no_grad()
def render_view(model, scene: LatentScene, camera: Camera, supersample: int = 1):
    """``(image (3, H, W), depth (H, W), instance (H, W))`` of the scene seen from ``camera``; with ``supersample``
    ``S > 1`` the image is anti-aliased, ``S x S`` rays per pixel (``prismonet.render.supersample``)."""
    comp = scene.render(model, camera)[0]
    image = comp.image[0]
    if supersample > 1:
        from prismonet.render.supersample import supersampled_image

        dtype = scene.z_sh.dtype
        image = supersampled_image(model.sdf_fn, model.color_fn, scene.params(), scene.bg_color[None], camera.K[None].to(dtype),
                                   camera.T_world_cam[None].to(dtype), camera.height, camera.width,
                                   torch.tensor([scene.ground_z], dtype=dtype), supersample, model.render_settings())[0]
    return image, comp.depth[0, 0], comp.instance[0]


def to_uint8(image: torch.Tensor) -> np.ndarray:
    return (image.detach().clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)


def write_gif(frames: list[np.ndarray], path: str | Path, fps: float = 12.0) -> Path:
    """An endlessly looping animated GIF of ``(H, W, 3)`` uint8 frames (Pillow)."""
    from PIL import Image

    if not frames:
        raise ValueError("write_gif: no frames")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(f) for f in frames]
    tmp = path.with_name(f".{path.stem}.tmp.gif")
    images[0].save(tmp, save_all=True, append_images=images[1:], duration=int(round(1000 / fps)), loop=0)
    tmp.replace(path)
    return path


def render_orbit(model, scene: LatentScene, out_dir: str | Path, frames: int = 24, size: int = 128,
                 fps: float = 12.0, progress: bool = True, supersample: int = 1) -> tuple[list[Path], Path]:
    """Render an orbit into ``out_dir``: ``view_<i>.png`` per frame and ``orbit.gif`` (``supersample``: as
    ``render_view``)."""
    from tqdm import tqdm

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pngs, frames_u8 = [], []
    for i, cam in enumerate(tqdm(orbit_cameras(scene, frames, size=size), desc="orbit", unit="view", disable=not progress)):
        img = to_uint8(render_view(model, scene, cam, supersample)[0])
        frames_u8.append(img)
        pngs.append(out / f"view_{i:03d}.png")
        write_image(pngs[-1], img[..., ::-1])
    return pngs, write_gif(frames_u8, out / "orbit.gif", fps)
