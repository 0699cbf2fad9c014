"""What is rendered: meshes with materials, point lights and ambient light; rigid transforms, visibility,
materials, lights and ambient light may each differ per batch element."""

from warp_vision.scene.scene import Material, PointLight, Scene, SceneObject

__all__ = ["Material", "PointLight", "Scene", "SceneObject"]
