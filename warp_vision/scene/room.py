"""A furnished room with a white ball: the standard scene for benchmarks and the foveation task."""

from __future__ import annotations

import numpy as np

from warp_vision.frames import translation
from warp_vision.scene.scene import Material, Scene

#: The shapes of :func:`make_room`'s furniture, in turn: ``object_0`` is a box, ``object_1`` a cylinder, ...
FURNITURE_SHAPES = ("box", "cylinder")


def furniture_shape(name: str) -> str:
    """The shape (:data:`FURNITURE_SHAPES`) of :func:`make_room`'s piece of furniture called ``name``."""
    prefix, _, number = name.partition("_")
    if prefix != "object" or not number.isdigit():
        raise ValueError(f"furniture_shape: {name!r} is not one of make_room's pieces of furniture (object_<n>)")
    return FURNITURE_SHAPES[int(number) % len(FURNITURE_SHAPES)]


def make_room(
    size=(6.0, 6.0, 3.0),
    ball_radius: float = 0.1,
    ball_centre=(0.0, 1.5, 1.2),
    n_objects: int = 4,
    seed: int = 0,
    ball_subdivisions: int = 3,
) -> Scene:
    """A closed box room (floor, ceiling, four walls) centred on the world origin, floor at z = 0.

    ``n_objects`` coloured boxes and cylinders stand on the floor at seeded positions, one ceiling
    light, and a smooth white ball called ``"ball"`` (a dynamic object: move it with
    ``scene.set_transform("ball", ...)``, per batch element if you like). Everything else is static.
    size: (x, y, z) extents in metres.
    """
    import trimesh

    rng = np.random.default_rng(seed)
    sx, sy, sz = (float(v) for v in size)
    sc = Scene(ambient=(0.06, 0.06, 0.06), background=(0.0, 0.0, 0.0))
    t = 0.05
    sc.add_box("floor", (sx, sy, t), translation([0, 0, -t / 2]), Material((0.45, 0.42, 0.38), reflectivity=0.15),
               static=True)
    sc.add_box("ceiling", (sx, sy, t), translation([0, 0, sz + t / 2]), Material((0.8, 0.8, 0.8)), static=True)
    walls = [
        ("wall_north", (sx, t, sz), [0, sy / 2 + t / 2, sz / 2], (0.62, 0.55, 0.45)),
        ("wall_south", (sx, t, sz), [0, -sy / 2 - t / 2, sz / 2], (0.5, 0.55, 0.6)),
        ("wall_east", (t, sy, sz), [sx / 2 + t / 2, 0, sz / 2], (0.55, 0.6, 0.5)),
        ("wall_west", (t, sy, sz), [-sx / 2 - t / 2, 0, sz / 2], (0.6, 0.5, 0.5)),
    ]
    for name, ext, c, col in walls:
        sc.add_box(name, ext, translation(c), Material(col), static=True)
    for i in range(n_objects):
        col = tuple(float(v) for v in rng.uniform(0.1, 0.9, 3))
        h = float(rng.uniform(0.3, 1.2))
        x, y = rng.uniform(-0.4, 0.4, 2) * np.array([sx, sy])
        if furniture_shape(f"object_{i}") == "box":
            w = rng.uniform(0.2, 0.6, 2)
            mesh = trimesh.creation.box((w[0], w[1], h))
        else:
            mesh = trimesh.creation.cylinder(radius=float(rng.uniform(0.1, 0.3)), height=h, sections=24)
        rot = trimesh.transformations.rotation_matrix(float(rng.uniform(0, np.pi)), [0, 0, 1])
        sc.add(f"object_{i}", mesh, Material(col, specular=float(rng.uniform(0, 0.3)), shininess=16),
               translation([x, y, h / 2]) @ rot, static=True)
    sc.add_sphere("ball", ball_radius, ball_centre, Material((1.0, 1.0, 1.0), specular=0.4, shininess=32, smooth=True),
                  subdivisions=ball_subdivisions)
    sc.add_light((0.0, 0.0, sz - 0.1), color=(1.0, 0.97, 0.9), intensity=8.0)
    return sc
