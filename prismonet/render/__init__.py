"""The differentiable SDF raycaster of the paper, and z-buffer composition.

``render_scene`` is the fast path; ``render_scene_reference`` is the straightforward one
(every pixel, every sample under autograd) that the fast path is tested and benchmarked against.
"""

from prismonet.render.composite import Composite, composite
from prismonet.render.renderer import RenderSettings, ObjectRender, SceneParams, render_objects, render_scene, render_scene_reference

__all__ = [
    "Composite",
    "ObjectRender",
    "RenderSettings",
    "SceneParams",
    "composite",
    "render_objects",
    "render_scene",
    "render_scene_reference",
]
