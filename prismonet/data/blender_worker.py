"""Renders scene layouts with Blender Cycles and CLEVR's original assets (run under bpy's Python).

This file imports neither torch nor the rest of the package: ``bpy`` pins ``numpy<2`` and lives in its
own environment (``scripts/setup_blender.sh``), which runs this file as a script::

    .venv-blender/bin/python prismonet/data/blender_worker.py JOB_DIR

``JOB_DIR/job.json`` holds the rung's settings and the scenes (camera, ground, objects with a mesh id,
a 4x4 object-to-world matrix, an RGB colour and a material); ``JOB_DIR/meshes.npz`` the meshes in their
object frames (``v{id}``, ``f{id}``). The worker writes ``JOB_DIR/rgb.npy`` (N, H, W, 3) uint8 and prints
``done I`` after each scene, for the caller's progress bar. One Blender session renders every scene of
the job: the base scene, node groups and meshes are loaded once, objects are made and removed per scene.

The camera conversion (``blender_camera``) is plain numpy so that the package's tests check it without
Blender; the measured facts behind it are in ``../shared/clevr_blender/README.md`` and the README.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

OPENCV_TO_BLENDER = np.diag([1.0, -1.0, -1.0, 1.0])
"""OpenCV camera axes (x right, y down, z forward) to Blender's (x right, y up, looking along -z)."""


def blender_camera(K: np.ndarray, T_world_cam: np.ndarray, width: int, height: int, sensor_width: float = 32.0) -> dict:
    """Blender camera settings equal to the OpenCV camera ``K``, ``T_world_cam``.

    With ``S = max(width, height)`` and the sensor fitted to the larger side: ``fx = lens / sensor_width * S``,
    ``cx = width / 2 - 0.5 - shift_x * S`` and ``cy = height / 2 - 0.5 + shift_y * S`` (pixel centres at
    integers, OpenCV's convention). Blender models one focal length, so ``fx`` must equal ``fy`` and the
    skew must be 0.
    """
    K = np.asarray(K, dtype=np.float64)
    if abs(K[0, 0] - K[1, 1]) > 1e-6 * K[0, 0] or abs(K[0, 1]) > 1e-9:
        raise ValueError(f"Blender cameras have square pixels and no skew; got K = {K.tolist()}")
    S = max(width, height)
    return {
        "lens": float(K[0, 0] * sensor_width / S),
        "sensor_width": float(sensor_width),
        "shift_x": float((width / 2.0 - 0.5 - K[0, 2]) / S),
        "shift_y": float((K[1, 2] - height / 2.0 + 0.5) / S),
        "matrix_world": (np.asarray(T_world_cam, dtype=np.float64) @ OPENCV_TO_BLENDER).tolist(),
    }


def project_blender(cam: dict, width: int, height: int, x_world: np.ndarray) -> np.ndarray:
    """Pixel coordinates ``(n, 2)`` of world points seen by a Blender camera (``blender_camera``'s dict),
    computed the way Blender defines its camera: the inverse of ``blender_camera``, for tests."""
    M = np.asarray(cam["matrix_world"])
    x = (np.asarray(x_world, dtype=np.float64) - M[:3, 3]) @ M[:3, :3]  # Blender camera frame
    S = max(width, height)
    f = cam["lens"] / cam["sensor_width"] * S
    u = f * x[:, 0] / -x[:, 2] + width / 2.0 - 0.5 - cam["shift_x"] * S
    v = -f * x[:, 1] / -x[:, 2] + height / 2.0 - 0.5 + cam["shift_y"] * S
    return np.stack([u, v], 1)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (Blender's "Standard" view transform) on linear values."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


class Session:
    """One Blender session with the base scene, CLEVR's node groups and the job's meshes loaded."""

    def __init__(self, job: dict, meshes: dict[str, np.ndarray]) -> None:
        import bpy

        self.bpy, self.job = bpy, job
        assets = Path(job["assets"])
        bpy.ops.wm.open_mainfile(filepath=str(assets / "base_scene.blend"))
        for name in ("Rubber", "MyMetal"):
            with bpy.data.libraries.load(str(assets / "materials" / f"{name}.blend")) as (src, dst):
                dst.node_groups = [g for g in src.node_groups if g == name]
        sc = bpy.context.scene
        self.scene = sc
        r = job["rung"]
        sc.render.engine = "CYCLES"
        sc.cycles.device = "CPU"
        sc.cycles.samples = int(r["samples"])
        sc.cycles.use_adaptive_sampling = False
        sc.cycles.use_denoising = bool(r["denoise"])
        if r["denoise"]:
            sc.cycles.denoiser = "OPENIMAGEDENOISE"
        sc.cycles.filter_width = float(r["filter_width"])
        sc.cycles.seed = 0
        sc.render.resolution_x, sc.render.resolution_y = int(job["width"]), int(job["height"])
        sc.render.resolution_percentage = 100
        sc.render.threads_mode = "FIXED"
        sc.render.threads = int(job.get("threads", 1))
        sc.render.film_transparent = False
        sc.view_settings.view_transform = "Standard"
        sc.view_settings.look = "None"
        sc.view_settings.exposure = 0.0
        sc.view_settings.gamma = 1.0
        settings = sc.render.image_settings
        settings.file_format, settings.color_mode, settings.color_depth = "OPEN_EXR", "RGB", "32"

        # CLEVR's curved backdrop is not flat far from the origin: a large plane replaces it.
        bpy.data.objects.remove(bpy.data.objects["Ground"], do_unlink=True)
        plane = bpy.data.meshes.new("ground")
        h = 500.0
        plane.from_pydata([(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], [], [(0, 1, 2, 3)])
        self.ground = bpy.data.objects.new("ground", plane)
        sc.collection.objects.link(self.ground)
        self.ground_mat = bpy.data.materials.new("ground")
        self.ground_mat.use_nodes = True
        self.ground.data.materials.append(self.ground_mat)
        nodes, links = self.ground_mat.node_tree.nodes, self.ground_mat.node_tree.links
        nodes.clear()
        out = nodes.new("ShaderNodeOutputMaterial")
        if r["lights"] == "flat":
            # The training renderer's ground: an unshaded colour that lights nothing and casts no shadow.
            self.ground_shader = nodes.new("ShaderNodeEmission")
            self.ground_shader.inputs["Strength"].default_value = 1.0
            links.new(self.ground_shader.outputs["Emission"], out.inputs["Surface"])
            for attr in ("visible_diffuse", "visible_glossy", "visible_shadow", "visible_transmission"):
                setattr(self.ground, attr, False)
        else:
            self.ground_shader = nodes.new("ShaderNodeBsdfDiffuse")
            links.new(self.ground_shader.outputs["BSDF"], out.inputs["Surface"])

        lamps = [o for o in bpy.data.objects if o.type == "LIGHT"]
        if r["lights"] == "flat":
            for o in lamps:
                bpy.data.objects.remove(o, do_unlink=True)
            sun = bpy.data.lights.new("sun", "SUN")
            sun.energy = math.pi * float(job["diffuse"])  # radiance = albedo * diffuse * cos
            sun.use_shadow = False
            sun.angle = 0.0
            obj = bpy.data.objects.new("sun", sun)
            sc.collection.objects.link(obj)
            l = np.asarray(job["light_dir"], dtype=np.float64)
            obj.matrix_world = _frame_with_z(l / np.linalg.norm(l))
            world = sc.world
            world.use_nodes = True
            bg = world.node_tree.nodes["Background"]
            bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
            bg.inputs["Strength"].default_value = float(job["ambient"])  # radiance = albedo * ambient
        else:
            for o in lamps:
                o.data.use_shadow = True

        self.meshes = {}
        for key in meshes:
            if key.startswith("v"):
                mid = key[1:]
                m = bpy.data.meshes.new(f"shape{mid}")
                m.from_pydata(meshes[key].tolist(), [], meshes[f"f{mid}"].tolist())
                m.update()
                m.shade_smooth()
                m.set_sharp_from_angle(angle=math.radians(float(r["smooth_angle_deg"])))
                m.materials.append(None)  # one slot, filled per object (``_set_object_material``)
                self.meshes[int(mid)] = m
        self.camera = sc.camera
        self.objects: list = []

    def render(self, scene: dict, path: Path) -> np.ndarray:
        """Render one scene; returns its ``(H, W, 3)`` uint8 image."""
        bpy, r = self.bpy, self.job["rung"]
        for o in self.objects:
            bpy.data.objects.remove(o, do_unlink=True)
        for m in [m for m in bpy.data.materials if m.name.startswith("obj")]:
            bpy.data.materials.remove(m)
        self.objects = []
        W, H = int(self.job["width"]), int(self.job["height"])
        cam = blender_camera(np.asarray(scene["K"]), np.asarray(scene["T_world_cam"]), W, H)
        self.camera.data.sensor_fit = "AUTO"
        self.camera.data.sensor_width = cam["sensor_width"]
        self.camera.data.lens = cam["lens"]
        self.camera.data.shift_x, self.camera.data.shift_y = cam["shift_x"], cam["shift_y"]
        self.camera.data.clip_start, self.camera.data.clip_end = 0.01, 1000.0
        self.camera.matrix_world = _matrix(cam["matrix_world"])
        self.ground.location = (0.0, 0.0, float(scene["ground_z"]))
        ground = [c / 255.0 for c in scene["ground_color"]]
        self.ground_shader.inputs["Color"].default_value = (*ground, 1.0)
        for k, o in enumerate(scene["objects"]):
            obj = bpy.data.objects.new(f"obj{k}", self.meshes[int(o["mesh"])])
            obj.matrix_world = _matrix(o["matrix"])
            mat = bpy.data.materials.new(f"obj{k}")
            mat.use_nodes = True
            nodes = mat.node_tree.nodes
            nodes.clear()
            out = nodes.new("ShaderNodeOutputMaterial")
            group = nodes.new("ShaderNodeGroup")
            group.node_tree = bpy.data.node_groups["MyMetal" if o["material"] == "metal" else "Rubber"]
            group.inputs["Color"].default_value = (*[c / 255.0 for c in o["color"]], 1.0)  # as CLEVR's script
            mat.node_tree.links.new(group.outputs["Shader"], out.inputs["Surface"])
            _set_object_material(obj, mat)
            self.scene.collection.objects.link(obj)
            self.objects.append(obj)
        self.scene.render.filepath = str(path)
        bpy.ops.render.render(write_still=True)
        img = bpy.data.images.load(str(path))
        px = np.empty(W * H * 4, dtype=np.float32)
        img.pixels.foreach_get(px)
        bpy.data.images.remove(img)
        rgb = px.reshape(H, W, 4)[::-1, :, :3]  # Blender's rows run bottom to top
        if r["tone"] == "srgb":
            rgb = srgb_encode(rgb)
        return np.clip(np.rint(np.clip(rgb, 0.0, 1.0) * 255.0), 0, 255).astype(np.uint8)


def _set_object_material(obj, mat) -> None:
    """Give ``obj`` its own material on a shared mesh: one slot, linked to the object, not the mesh."""
    obj.material_slots[0].link = "OBJECT"
    obj.material_slots[0].material = mat


def _frame_with_z(z: np.ndarray):
    """A rotation whose local z axis is ``z`` (a sun light shines along its local -z)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    M = np.eye(4)
    M[:3, :3] = np.stack([x, y, z], 1)
    return _matrix(M.tolist())


def _matrix(rows):
    from mathutils import Matrix

    return Matrix([list(map(float, row)) for row in rows])


def main(job_dir: str) -> int:
    job_dir_p = Path(job_dir)
    job = json.loads((job_dir_p / "job.json").read_text())
    meshes = dict(np.load(job_dir_p / "meshes.npz"))
    session = Session(job, meshes)
    out = np.zeros((len(job["scenes"]), int(job["height"]), int(job["width"]), 3), np.uint8)
    for i, scene in enumerate(job["scenes"]):
        out[i] = session.render(scene, job_dir_p / "frame.exr")
        print(f"done {i}", flush=True)
    np.save(job_dir_p / "rgb.tmp.npy", out)
    (job_dir_p / "rgb.tmp.npy").rename(job_dir_p / "rgb.npy")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
