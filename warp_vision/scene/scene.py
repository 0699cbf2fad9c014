"""What the eyes see: triangle meshes with materials, point lights and per-batch rigid transforms.

A :class:`Scene` holds objects (a trimesh mesh in its own object frame, a :class:`Material` and a
world-from-object rigid transform) and point lights. The meshes become ``wp.Mesh`` BVHs once, in their
object frames; moving an object (or giving each batch element its own pose, so that one launch renders
B different ball positions) only changes a transform. Objects added with ``static=True`` (walls, floor,
furniture) are merged into one BVH in the world frame, so a ray pays one traversal for all of them
instead of one per object; moving a static object rebuilds that merged BVH.

Per batch element (so that one launch of B samples renders B different scenes), each may be shared
(one value) or given B values: a dynamic object's transform (:meth:`Scene.set_transform`) and
visibility (:meth:`Scene.set_visible`), any object's material (:meth:`Scene.set_material`: diffuse,
specular, shininess, reflectivity and emission; ``smooth`` and ``vertex_colors`` stay per object), the
point lights' positions, colours and intensities, and the ambient light (:meth:`Scene.set_ambient`).
The mesh geometry and the background are shared by the whole batch. Every per-batch quantity must
have the same B (:meth:`Scene.batch_size`).

Units: metres and the world frame of docs/ARCHITECTURE.md (+z up). Radiance is linear, in arbitrary but
consistent units: a point light of ``intensity`` I and ``color`` c gives irradiance I c / d^2 at
distance d.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from warp_vision.frames import translation


@dataclass
class Material:
    """Phong material.

    diffuse: RGB albedo in [0, 1] (ignored where ``vertex_colors`` is on and the mesh has colours).
    specular: Phong specular coefficient (>= 0), white highlights.
    shininess: Phong exponent (>= 1).
    reflectivity: mirror reflectance in [0, 1]; rays recurse while it is non-zero.
    emission: RGB radiance the surface emits itself (>= 0), seen whatever the lights (a glowing object).
    vertex_colors: use the mesh's per-vertex colours (trimesh ``visual.vertex_colors``) as albedo.
    smooth: interpolate vertex normals (smooth shading) instead of the flat face normal.
    """

    diffuse: tuple[float, float, float] = (0.7, 0.7, 0.7)
    specular: float = 0.0
    shininess: float = 32.0
    reflectivity: float = 0.0
    emission: tuple[float, float, float] = (0.0, 0.0, 0.0)
    vertex_colors: bool = False
    smooth: bool = False

    def __post_init__(self):
        d = np.asarray(self.diffuse, dtype=np.float64)
        if d.shape != (3,) or not np.all(np.isfinite(d)) or d.min() < 0 or d.max() > 1:
            raise ValueError(f"Material.diffuse: expected 3 values in [0, 1], got {self.diffuse}")
        if not np.isfinite(self.specular) or self.specular < 0:
            raise ValueError(f"Material.specular: expected >= 0, got {self.specular}")
        if not np.isfinite(self.shininess) or self.shininess < 1:
            raise ValueError(f"Material.shininess: expected >= 1, got {self.shininess}")
        if not 0 <= self.reflectivity <= 1:
            raise ValueError(f"Material.reflectivity: expected a value in [0, 1], got {self.reflectivity}")
        e = np.asarray(self.emission, dtype=np.float64)
        if e.shape != (3,) or not np.all(np.isfinite(e)) or e.min() < 0:
            raise ValueError(f"Material.emission: expected 3 finite values >= 0, got {self.emission}")


@dataclass
class PointLight:
    """A point light. position: [3] or [B, 3] m (world); color: [3] or [B, 3] RGB; intensity: scalar or [B]."""

    position: np.ndarray
    color: np.ndarray = field(default_factory=lambda: np.ones(3))
    intensity: np.ndarray | float = 1.0


@dataclass
class SceneObject:
    name: str
    mesh: trimesh.Trimesh
    material: Material
    transform: np.ndarray  # [1, 4, 4] or [B, 4, 4] world-from-object, rigid
    static: bool = False
    visible: np.ndarray = field(default_factory=lambda: np.ones(1, dtype=bool))  # [1] or [B]
    # One Material per batch element (set by Scene.set_material), overriding ``material``'s shading
    # values; None when the whole batch shares ``material``. Packed as numpy arrays in batch_material_arrays.
    batch_materials: tuple[Material, ...] | None = None
    batch_material_arrays: dict[str, np.ndarray] | None = field(default=None, repr=False)

    def material_for(self, batch: int) -> Material:
        """The material batch element ``batch`` sees (the shared one when there is no per-batch list)."""
        if self.batch_materials is None:
            return self.material
        return self.batch_materials[batch if len(self.batch_materials) > 1 else 0]


def _as_ambient(ambient) -> np.ndarray:
    a = np.array(ambient, dtype=np.float64)
    if a.ndim not in (1, 2) or a.shape[-1] != 3 or a.size == 0:
        raise ValueError(f"ambient: expected RGB [3] or one per batch element [B, 3], got shape {a.shape}")
    if not np.all(np.isfinite(a)) or a.min() < 0:
        raise ValueError("ambient: expected finite values >= 0")
    return a


#: The default world-from-object transform: one read-only array, shared by every object added without a transform.
IDENTITY = np.eye(4)
IDENTITY.setflags(write=False)


def _as_transforms(name: str, T) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape == (4, 4):
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected a [4, 4] or [B, 4, 4] transform, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    R = T[:, :3, :3]
    err = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max()
    if err > 1e-4 or np.any(np.linalg.det(R) < 0) or np.abs(T[:, 3] - [0, 0, 0, 1]).max() > 1e-9:
        raise ValueError(
            f"{name}: expected rigid transforms (orthonormal rotation, det +1, last row 0 0 0 1); "
            "put scale into the mesh instead"
        )
    return T


class Scene:
    """Meshes, materials, point lights and ambient light, rendered by :mod:`warp_vision.kernels.render`.

    ambient: RGB ambient irradiance (multiplies each surface's albedo): [3], or [B, 3] for one per batch
        element. Assigning ``scene.ambient`` validates like :meth:`set_ambient`.
    background: RGB radiance of rays that escape the scene.
    """

    def __init__(self, ambient=(0.05, 0.05, 0.05), background=(0.0, 0.0, 0.0)):
        self.objects: list[SceneObject] = []
        self.lights: list[PointLight] = []
        self.ambient = ambient
        self.background = np.asarray(background, dtype=np.float64)
        self._version = 0  # bumps when geometry changes (forces a BVH rebuild)
        self._materials_version = 0  # bumps when set_material changes a shared material (re-upload)
        self._gpu: dict = {}

    @property
    def ambient(self) -> np.ndarray:
        """RGB ambient irradiance, [3] (shared) or [B, 3] (float64)."""
        return self._ambient

    @ambient.setter
    def ambient(self, value) -> None:
        self._ambient = _as_ambient(value)

    # --- building -----------------------------------------------------------------------------
    def add(
        self, name: str, mesh: trimesh.Trimesh, material: Material | None = None, transform=IDENTITY,
        static: bool = False
    ) -> int:
        """Add a mesh (object frame, metres). Returns the object's index.

        static: the object does not move between renders and has one pose for the whole batch; static
        objects share one merged BVH (faster), and moving one rebuilds it.
        """
        if any(o.name == name for o in self.objects):
            raise ValueError(f"name: an object called {name!r} already exists")
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise ValueError(f"mesh: expected a non-empty trimesh.Trimesh, got {type(mesh).__name__}")
        if not np.all(np.isfinite(mesh.vertices)):
            raise ValueError(f"mesh {name!r}: vertices must be finite")
        T = _as_transforms(f"transform of {name!r}", transform)
        if static and T.shape[0] != 1:
            raise ValueError(f"transform of {name!r}: a static object has one [4, 4] pose, got {T.shape[0]}")
        self.objects.append(SceneObject(name, mesh, material or Material(), T, bool(static)))
        self._version += 1
        return len(self.objects) - 1

    def add_sphere(self, name, radius, centre=(0, 0, 0), material=None, subdivisions: int = 3, static=False) -> int:
        """An icosphere of ``radius`` m at ``centre``; smooth-shaded unless the material says otherwise.
        ``subdivisions`` (:data:`warp_vision.limits.SUBDIVISIONS`) is refused, before the mesh is built, where its
        triangles would not fit in memory."""
        from warp_vision.limits import SUBDIVISIONS, icosphere_bytes, require_int
        from warp_vision.resources import require_memory

        if not radius > 0:
            raise ValueError(f"radius: expected > 0, got {radius}")
        require_int(subdivisions, SUBDIVISIONS, "subdivisions")
        require_memory(icosphere_bytes(subdivisions), f"an icosphere of {subdivisions} subdivisions "
                       f"({20 * 4 ** subdivisions:,} triangles)", "subdivisions")
        m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
        mat = material or Material(smooth=True)
        return self.add(name, m, mat, translation(centre), static)

    def add_box(self, name, extents, transform=IDENTITY, material=None, static=False) -> int:
        """An axis-aligned box of ``extents`` (m) in its object frame, placed by ``transform``."""
        return self.add(name, trimesh.creation.box(extents=extents), material, transform, static)

    def add_plane(self, name, size, transform=IDENTITY, material=None, static=False) -> int:
        """A two-triangle rectangle of ``size`` (w, h) m in the object's xy plane, normal +z."""
        w, h = 0.5 * float(size[0]), 0.5 * float(size[1])
        v = np.array([[-w, -h, 0], [w, -h, 0], [w, h, 0], [-w, h, 0]], dtype=np.float64)
        m = trimesh.Trimesh(v, np.array([[0, 1, 2], [0, 2, 3]]), process=False)
        return self.add(name, m, material, transform, static)

    def add_light(self, position, color=(1.0, 1.0, 1.0), intensity=1.0) -> int:
        """A point light at ``position`` m; position [3] or [B, 3], color [3] or [B, 3], intensity scalar or [B]."""
        self.lights.append(PointLight(np.asarray(position, float), np.asarray(color, float),
                                      np.asarray(intensity, float)))
        return len(self.lights) - 1

    def index(self, name: str) -> int:
        for i, o in enumerate(self.objects):
            if o.name == name:
                return i
        raise KeyError(f"no object called {name!r}; have {[o.name for o in self.objects]}")

    def set_transform(self, name: str, transform) -> None:
        """Move an object: a [4, 4] world-from-object transform, or [B, 4, 4], one per batch element."""
        i = self.index(name)
        T = _as_transforms(f"transform of {name!r}", transform)
        if self.objects[i].static:
            if T.shape[0] != 1:
                raise ValueError(
                    f"transform of {name!r}: a static object has one [4, 4] pose; add it with static=False"
                )
            self._version += 1  # the merged static BVH must be rebuilt
        self.objects[i].transform = T

    def set_visible(self, name: str, visible) -> None:
        """Show or hide a dynamic object: a bool, or [B] bools (one per batch element). Hidden objects
        cost the tracer nothing (it skips them before any traversal)."""
        i = self.index(name)
        v = np.atleast_1d(np.asarray(visible, dtype=bool))
        if v.ndim != 1 or len(v) == 0:
            raise ValueError(f"visible: expected a bool or [B] bools, got shape {v.shape}")
        if self.objects[i].static and not v.all():
            raise ValueError(f"{name!r} is static: static objects cannot be hidden; add it with static=False")
        self.objects[i].visible = v

    def set_material(self, name: str, material) -> None:
        """Give an object a material: one :class:`Material` for the whole batch, or a sequence of B
        Materials, one per batch element.

        A single Material replaces ``obj.material`` and drops any per-batch list. Per-batch materials
        vary diffuse, specular, shininess, reflectivity and emission; they must agree with the object's
        own ``material`` on ``smooth`` and ``vertex_colors`` (how its mesh is shaded; change those with a
        single Material). Materials are uploaded per render: this never rebuilds a BVH or the scene's
        geometry, except that a single Material changing ``smooth`` or ``vertex_colors`` repacks the
        geometry's normals and colours (dynamic objects' BVHs stay cached). Takes effect on the next
        render. (Mutating a Material in place after a render is not seen: call set_material.)
        """
        i = self.index(name)
        o = self.objects[i]
        if isinstance(material, Material):
            if (material.smooth, material.vertex_colors) != (o.material.smooth, o.material.vertex_colors):
                self._version += 1  # the packed normals / vertex colours depend on these flags
            o.material = material
            o.batch_materials = o.batch_material_arrays = None
            self._materials_version += 1
            return
        if isinstance(material, (str, bytes)) or not hasattr(material, "__len__"):
            raise ValueError(f"material of {name!r}: expected a Material or a sequence of B Materials, got "
                             f"{type(material).__name__}")
        mats = tuple(material)
        if len(mats) == 0:
            raise ValueError(f"material of {name!r}: expected a Material or a non-empty sequence of Materials, got an "
                             "empty one")
        bad = [k for k, m in enumerate(mats) if not isinstance(m, Material)]
        if bad:
            raise ValueError(f"material of {name!r}: entry {bad[0]} is a {type(mats[bad[0]]).__name__}, not a Material")
        for k, m in enumerate(mats):
            if m.smooth != o.material.smooth or m.vertex_colors != o.material.vertex_colors:
                raise ValueError(
                    f"material of {name!r}: per-batch material {k} has smooth={m.smooth}, vertex_colors="
                    f"{m.vertex_colors} but the object has smooth={o.material.smooth}, vertex_colors="
                    f"{o.material.vertex_colors}; these flags are per object (set them with one Material first)"
                )
        o.batch_materials = mats
        from warp_vision.kernels.render.scene_data import material_arrays

        o.batch_material_arrays = material_arrays(mats)

    def set_ambient(self, ambient) -> None:
        """Set the RGB ambient irradiance: [3] for the whole batch or [B, 3], one per batch element
        (finite, >= 0). Same as assigning ``scene.ambient``; uploaded per render."""
        self.ambient = ambient

    # --- queries --------------------------------------------------------------------------------
    @property
    def num_triangles(self) -> int:
        return sum(len(o.mesh.faces) for o in self.objects)

    def batch_size(self) -> int:
        """The batch implied by per-batch transforms, visibility, lights, materials and ambient light (1
        when everything is shared)."""
        sizes = {o.transform.shape[0] for o in self.objects} | {len(o.visible) for o in self.objects}
        sizes |= {len(o.batch_materials) for o in self.objects if o.batch_materials is not None}
        for li in self.lights:
            sizes |= {np.atleast_2d(li.position).shape[0], np.atleast_2d(li.color).shape[0],
                      np.atleast_1d(li.intensity).shape[0]}
        sizes.add(np.atleast_2d(self.ambient).shape[0])
        sizes.discard(1)
        if len(sizes) > 1:
            raise ValueError(
                "scene: per-batch transforms, visibility, lights, materials and ambient light disagree on the "
                f"batch size: {sorted(sizes)}"
            )
        return sizes.pop() if sizes else 1

    def world_mesh(self, batch: int = 0) -> trimesh.Trimesh:
        """All objects merged in the world frame for batch element ``batch`` (for references and export)."""
        parts = []
        for o in self.objects:
            if not o.visible[batch if len(o.visible) > 1 else 0]:
                continue
            T = o.transform[batch if o.transform.shape[0] > 1 else 0]
            parts.append(o.mesh.copy().apply_transform(T))
        return trimesh.util.concatenate(parts)
