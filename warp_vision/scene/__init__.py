"""What is rendered: meshes with materials, point lights, per-batch rigid transforms."""

from warp_vision.scene.scene import Material, PointLight, Scene, SceneObject

__all__ = ["Material", "PointLight", "Scene", "SceneObject"]
