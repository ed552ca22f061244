"""Exporting a latent scene: coloured per-object meshes, the whole scene, and point clouds.

- Object meshes: marching cubes on the shape prior Phi(z_sh, .) in the object frame, vertex colours
  from the texture field Psi(z_tex, .) at the vertices, then posed into the world by T_world_obj.
- The scene: every object plus a ground quad in the background colour, one mesh (PLY, OBJ, GLB).
- Point clouds: RGB-D images back-projected through the camera into the world frame (open3d).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from prismonet.geometry.camera import Camera, unproject
from prismonet.geometry.transforms import transform_points
from prismonet.scene.latent_scene import LatentScene

MESH_FORMATS = (".ply", ".obj", ".glb")
POINT_FORMATS = (".ply", ".pcd", ".xyz")


def _check_suffix(path: Path, allowed: tuple[str, ...], what: str) -> None:
    if path.suffix.lower() not in allowed:
        raise ValueError(f"{path}: cannot write a {what} as {path.suffix or 'a file without extension'}; use {', '.join(allowed)}")


@torch.no_grad()
def object_mesh(model, scene: LatentScene, k: int, resolution: int = 48, world: bool = True):
    """Object ``k`` as a ``trimesh.Trimesh`` with vertex colours from Psi (world frame by default)."""
    from prismonet.shapes.mesh import extract_mesh

    scene.check_model(model)
    mesh = extract_mesh(model.prior.decoder, scene.z_sh[k], resolution)
    v_obj = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)
    rgb = model.color_fn(scene.z_tex[k : k + 1].expand(len(v_obj), -1), v_obj).clamp(0, 1)
    if world:
        mesh.vertices = transform_points(scene.T_world_obj()[k], v_obj).double().numpy()
    alpha = np.full((len(v_obj), 1), 255, np.uint8)
    mesh.visual.vertex_colors = np.concatenate([(rgb.numpy() * 255).round().astype(np.uint8), alpha], 1)
    return mesh


def ground_mesh(scene: LatentScene, half_size: float = 3.0):
    """A square of side ``2 half_size`` at ``z = ground_z`` in the background colour, facing up."""
    import trimesh

    h, z = half_size, scene.ground_z
    verts = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    color = np.append((scene.bg_color.clamp(0, 1).numpy() * 255).round(), 255).astype(np.uint8)
    return trimesh.Trimesh(verts, faces, vertex_colors=np.tile(color, (4, 1)), process=False)


def scene_mesh(model, scene: LatentScene, resolution: int = 48, ground: bool = True, ground_half_size: float = 3.0):
    """All objects (and the ground) as one ``trimesh.Trimesh`` in the world frame."""
    import trimesh

    parts = [object_mesh(model, scene, k, resolution) for k in range(scene.num_objects)]
    if ground:
        parts.append(ground_mesh(scene, ground_half_size))
    return trimesh.util.concatenate(parts)


def write_mesh(mesh, path: str | Path) -> Path:
    """Write a ``trimesh.Trimesh`` as PLY, OBJ or GLB (by extension), with its vertex colours."""
    path = Path(path)
    _check_suffix(path, MESH_FORMATS, "mesh")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    mesh.export(str(tmp))
    tmp.replace(path)
    return path


def point_cloud(rgb: torch.Tensor, depth: torch.Tensor, camera: Camera, valid: torch.Tensor | None = None,
                max_depth: float | None = None):
    """Back-project an RGB-D image into a coloured world-frame ``open3d.geometry.PointCloud``.

    Args:
        rgb: ``(3, H, W)`` in [0, 1]; depth: ``(H, W)`` or ``(1, H, W)`` camera z.
        valid: optional ``(H, W)`` bool of pixels to keep; by default pixels with
            ``0 < depth < max_depth`` (``max_depth`` default: no limit), finite.
    Returns one point per valid pixel, in row-major pixel order.
    """
    import open3d as o3d

    from prismonet.geometry.camera import pixel_grid

    depth = depth.detach().reshape(camera.height, camera.width).float()
    rgb = rgb.detach()
    if tuple(rgb.shape) != (3, camera.height, camera.width):
        raise ValueError(f"rgb: expected shape (3, {camera.height}, {camera.width}), got {tuple(rgb.shape)}")
    ok = torch.isfinite(depth) & (depth > 0)
    if max_depth is not None:
        ok &= depth < max_depth
    if valid is not None:
        ok &= valid.reshape(camera.height, camera.width).bool()
    uv = pixel_grid(camera.height, camera.width).reshape(-1, 2)[ok.reshape(-1)]
    x_cam = unproject(uv, depth.reshape(-1)[ok.reshape(-1), None], camera.K)
    x_world = transform_points(camera.T_world_cam, x_cam)
    colors = rgb.permute(1, 2, 0).reshape(-1, 3)[ok.reshape(-1)].clamp(0, 1)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(x_world.double().numpy()))
    pc.colors = o3d.utility.Vector3dVector(colors.double().numpy())
    return pc


def write_point_cloud(pc, path: str | Path) -> Path:
    import open3d as o3d

    path = Path(path)
    _check_suffix(path, POINT_FORMATS, "point cloud")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    if not o3d.io.write_point_cloud(str(tmp), pc):
        raise OSError(f"{path}: open3d could not write the point cloud")
    tmp.replace(path)
    return path


@torch.no_grad()
def export_scene(model, scene: LatentScene, out_dir: str | Path, fmt: str = "ply", resolution: int = 48,
                 input_rgbd: tuple[torch.Tensor, torch.Tensor] | None = None) -> dict[str, Path]:
    """Write a scene's files into ``out_dir``: ``scene.json``, ``scene.<fmt>`` (objects + ground),
    ``object_<k>.<fmt>``, ``points_rendered.ply`` and, given the input RGB-D, ``points_input.ply``.
    Returns the written paths by name."""
    out = Path(out_dir)
    fmt = fmt.lower().lstrip(".")
    _check_suffix(Path(f"x.{fmt}"), MESH_FORMATS, "mesh")
    written = {"scene_json": scene.save(out / "scene.json")}
    objects = []
    for k in range(scene.num_objects):
        objects.append(object_mesh(model, scene, k, resolution))
        written[f"object_{k}"] = write_mesh(objects[-1], out / f"object_{k}.{fmt}")
    import trimesh

    written["scene_mesh"] = write_mesh(trimesh.util.concatenate(objects + [ground_mesh(scene)]), out / f"scene.{fmt}")
    comp = scene.render(model)[0]
    far = model.render_settings().far_depth
    written["points_rendered"] = write_point_cloud(point_cloud(comp.image[0], comp.depth[0], scene.camera, max_depth=far),
                                                   out / "points_rendered.ply")
    if input_rgbd is not None:
        rgb, depth = input_rgbd
        written["points_input"] = write_point_cloud(point_cloud(rgb, depth, scene.camera, max_depth=far), out / "points_input.ply")
    return written
