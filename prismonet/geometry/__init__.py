"""Camera and pose geometry (OpenCV camera, z-up world), built on kornia."""

from prismonet.geometry.camera import (
    Camera,
    camera_rays,
    crop_intrinsics,
    intrinsics_matrix,
    look_at,
    pixel_grid,
    project,
    resize_intrinsics,
    unproject,
)
from prismonet.geometry.pose import (
    EPS_YAW_NORM,
    rotation_from_axis_cos_sin,
    T_world_obj_from_extrinsics,
    yaw_to_cos_sin,
)
from prismonet.geometry.transforms import compose, invert_similarity, transform_points

__all__ = [
    "Camera",
    "EPS_YAW_NORM",
    "T_world_obj_from_extrinsics",
    "camera_rays",
    "compose",
    "crop_intrinsics",
    "intrinsics_matrix",
    "invert_similarity",
    "look_at",
    "pixel_grid",
    "project",
    "resize_intrinsics",
    "rotation_from_axis_cos_sin",
    "transform_points",
    "unproject",
    "yaw_to_cos_sin",
]
