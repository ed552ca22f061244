"""The inferred scene as an object: save and reload it, edit it, export it, view it anew."""

from prismonet.scene.latent_scene import LatentScene, LatentSceneError

__all__ = ["LatentScene", "LatentSceneError"]
