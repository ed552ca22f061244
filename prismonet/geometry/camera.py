"""Pinhole camera in the OpenCV convention (x right, y down, z forward), built on kornia.

Pixel coordinates follow OpenCV: the centre of pixel ``(u, v)`` (column, row) sits at integer
coordinates, so the image spans ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from kornia.geometry.camera import PinholeCamera
from kornia.geometry.camera.perspective import project_points, unproject_points

from prismonet.geometry.transforms import invert_similarity


def _check_K(K: torch.Tensor) -> None:
    if not isinstance(K, torch.Tensor):
        raise TypeError(f"K: expected a torch.Tensor, got {type(K).__name__}")
    if K.shape[-2:] != (3, 3):
        raise ValueError(f"K: expected shape (..., 3, 3), got {tuple(K.shape)}")


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float, dtype=torch.float32) -> torch.Tensor:
    """The ``(3, 3)`` pinhole matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``."""
    if fx <= 0 or fy <= 0:
        raise ValueError(f"focal lengths must be positive, got fx={fx}, fy={fy}")
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype)


def project(x_cam: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Project camera-frame points ``(..., 3)`` to pixels ``(..., 2)`` (kornia ``project_points``).

    Points must have ``z > 0``; no clipping is done here.
    """
    _check_K(K)
    if x_cam.shape[-1] != 3:
        raise ValueError(f"x_cam: expected shape (..., 3), got {tuple(x_cam.shape)}")
    K = K.expand(*x_cam.shape[:-1], 3, 3) if K.dim() == 2 else K[..., None, :, :].expand(*x_cam.shape[:-1], 3, 3)
    return project_points(x_cam, K)


def unproject(uv: torch.Tensor, depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Lift pixels ``(..., 2)`` with camera-z ``depth`` ``(..., 1)`` to camera-frame points ``(..., 3)``."""
    _check_K(K)
    if uv.shape[-1] != 2:
        raise ValueError(f"uv: expected shape (..., 2), got {tuple(uv.shape)}")
    if depth.shape != (*uv.shape[:-1], 1):
        raise ValueError(f"depth: expected shape {(*uv.shape[:-1], 1)}, got {tuple(depth.shape)}")
    K = K.expand(*uv.shape[:-1], 3, 3) if K.dim() == 2 else K[..., None, :, :].expand(*uv.shape[:-1], 3, 3)
    return unproject_points(uv, depth, K, normalize=False)


def pixel_grid(height: int, width: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """Pixel-centre coordinates ``(H, W, 2)`` as ``(u, v)`` = (column, row), OpenCV convention."""
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device),
        torch.arange(width, dtype=dtype, device=device),
        indexing="ij",
    )
    return torch.stack([u, v], dim=-1)


def camera_rays(K: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Ray directions in the camera frame with unit z, ``(H, W, 3)``: ``K^-1 [u, v, 1]``.

    Because the z component is 1, the ray parameter of a point equals its depth (camera z).
    """
    _check_K(K)
    if K.dim() != 2:
        raise ValueError(f"K: expected shape (3, 3), got {tuple(K.shape)}")
    uv = pixel_grid(height, width, dtype=K.dtype, device=K.device)
    return unproject(uv, torch.ones(height, width, 1, dtype=K.dtype, device=K.device), K)


def crop_intrinsics(K: torch.Tensor, x0: float, y0: float) -> torch.Tensor:
    """Intrinsics after cropping the image so that pixel ``(x0, y0)`` becomes ``(0, 0)``."""
    _check_K(K)
    K = K.clone()
    K[..., 0, 2] -= x0
    K[..., 1, 2] -= y0
    return K


def resize_intrinsics(K: torch.Tensor, scale_x: float, scale_y: float) -> torch.Tensor:
    """Intrinsics after resizing by ``(scale_x, scale_y)`` (new size / old size).

    With pixel centres at integers, a point at old pixel ``u`` lands at ``(u + 0.5) s - 0.5``,
    which is what ``cv2.resize`` does; so ``f' = s f`` and ``c' = s (c + 0.5) - 0.5``.
    """
    _check_K(K)
    if scale_x <= 0 or scale_y <= 0:
        raise ValueError(f"resize scales must be positive, got ({scale_x}, {scale_y})")
    K = K.clone()
    K[..., 0, 0] *= scale_x
    K[..., 1, 1] *= scale_y
    K[..., 0, 2] = (K[..., 0, 2] + 0.5) * scale_x - 0.5
    K[..., 1, 2] = (K[..., 1, 2] + 0.5) * scale_y - 0.5
    return K


def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor | None = None) -> torch.Tensor:
    """``T_world_cam`` ``(4, 4)`` of an OpenCV camera at ``eye`` looking at ``target``.

    The camera's y axis (down in the image) is aligned with ``-up`` (default world z).
    """
    up = torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype) if up is None else up
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, up)
    if x.norm() < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to the up vector")
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    T = torch.eye(4, dtype=eye.dtype)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def orbit_elevation(T_world_cam: torch.Tensor, ground_z: float, elevation_deg: float) -> torch.Tensor:
    """``T_world_cam`` ``(4, 4)`` of a level camera moved to another elevation about the ground point it looks at.

    The camera keeps that point (where its optical axis meets the plane ``z = ground_z``), its distance
    to it and its heading; ``elevation_deg`` is the angle between the optical axis and the ground, in
    (0, 90). The result is ``look_at``'s camera (no roll). For a camera whose axes fix no heading
    (looking straight down) it raises.
    """
    import math

    if not 0.0 < elevation_deg < 90.0:
        raise ValueError(f"elevation must be in (0, 90) degrees, got {elevation_deg}")
    T = T_world_cam.double()
    eye, axis = T[:3, 3], T[:3, 2]
    if axis[2] >= -1e-6 or eye[2] <= ground_z:
        raise ValueError("orbit_elevation: the camera must be above the ground and look down at it")
    dist = float((ground_z - eye[2]) / axis[2])
    target = eye + dist * axis
    back = eye[:2] - target[:2]
    if back.norm() < 1e-9:
        raise ValueError("orbit_elevation: a camera looking straight down has no heading to keep")
    az, e = math.atan2(float(back[1]), float(back[0])), math.radians(elevation_deg)
    new_eye = target + dist * torch.tensor([math.cos(e) * math.cos(az), math.cos(e) * math.sin(az), math.sin(e)], dtype=T.dtype)
    return look_at(new_eye, target).to(T_world_cam.dtype)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera with its pose.

    Attributes:
        K: ``(3, 3)`` intrinsics in pixels.
        T_world_cam: ``(4, 4)`` camera-to-world transform (OpenCV camera axes).
        height: image rows.
        width: image columns.
    """

    K: torch.Tensor
    T_world_cam: torch.Tensor
    height: int
    width: int

    def __post_init__(self) -> None:
        if tuple(self.K.shape) != (3, 3):
            raise ValueError(f"Camera.K: expected shape (3, 3), got {tuple(self.K.shape)}")
        if tuple(self.T_world_cam.shape) != (4, 4):
            raise ValueError(f"Camera.T_world_cam: expected shape (4, 4), got {tuple(self.T_world_cam.shape)}")
        if self.height <= 0 or self.width <= 0:
            raise ValueError(f"Camera: image size must be positive, got {self.height}x{self.width}")

    @property
    def T_cam_world(self) -> torch.Tensor:
        return invert_similarity(self.T_world_cam)

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world coordinates, ``(3,)``."""
        return self.T_world_cam[:3, 3]

    def to_kornia(self) -> PinholeCamera:
        """The same camera as a batch-of-one ``kornia.geometry.camera.PinholeCamera``."""
        K4 = torch.eye(4, dtype=self.K.dtype)
        K4[:3, :3] = self.K
        h = torch.tensor([self.height], dtype=self.K.dtype)
        w = torch.tensor([self.width], dtype=self.K.dtype)
        return PinholeCamera(K4[None], self.T_cam_world.to(self.K.dtype)[None], h, w)

    def world_to_pixels(self, x_world: torch.Tensor) -> torch.Tensor:
        """Project world points ``(N, 3)`` to pixels ``(N, 2)``."""
        return self.to_kornia().project(x_world[None])[0]

    def cropped(self, x0: int, y0: int, height: int, width: int) -> "Camera":
        return Camera(crop_intrinsics(self.K, x0, y0), self.T_world_cam, height, width)

    def resized(self, height: int, width: int) -> "Camera":
        K = resize_intrinsics(self.K, width / self.width, height / self.height)
        return Camera(K, self.T_world_cam, height, width)

    def to_dict(self) -> dict[str, Any]:
        return {
            "K": self.K.tolist(),
            "T_world_cam": self.T_world_cam.tolist(),
            "height": self.height,
            "width": self.width,
        }

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "Camera":
        try:
            return Camera(
                torch.tensor(d["K"], dtype=torch.float32),
                torch.tensor(d["T_world_cam"], dtype=torch.float32),
                int(d["height"]),
                int(d["width"]),
            )
        except KeyError as e:
            raise ValueError(f"camera: missing field {e.args[0]!r} (need K, T_world_cam, height, width)") from None
