"""The body as the renderer takes it: its visible geoms as meshes, grouped by the bodies that move them
(:func:`visible_parts`), and which bodies the eyes do not see."""

from __future__ import annotations

import mujoco
import numpy as np

#: Bodies the eyes do not see: the skull and cervical spine around them (its inside would shadow every
#: ray) and the eyes themselves; a third-person camera sees them.
HIDDEN_FROM_EYES = ("head", "neck", "eye_left", "eye_right", "orbit_left", "orbit_right")
#: Each arm's parts that move as one in a rendered scene: humerus, ulna, radius and hand (the carpals
#: with the fingers, as posed when the meshes are taken).
ARM_PARTS = {"right": ("humerus_r", "ulna_r", "radius_r", "lunate_r"),
             "left": ("humerus_l", "ulna_l", "radius_l", "lunate_l")}


def geom_mesh(m: mujoco.MjModel, g: int):
    """Geom ``g`` of model ``m`` as a trimesh in the geom's frame (None for a type without one: planes,
    height fields)."""
    import trimesh

    t, s = int(m.geom_type[g]), m.geom_size[g]
    G = mujoco.mjtGeom
    if t == G.mjGEOM_MESH:
        i = m.geom_dataid[g]
        v = m.mesh_vert[m.mesh_vertadr[i]:m.mesh_vertadr[i] + m.mesh_vertnum[i]]
        f = m.mesh_face[m.mesh_faceadr[i]:m.mesh_faceadr[i] + m.mesh_facenum[i]]
        return trimesh.Trimesh(v.astype(np.float64), f, process=False)
    if t == G.mjGEOM_SPHERE:
        return trimesh.creation.icosphere(2, radius=s[0])
    if t == G.mjGEOM_CYLINDER:
        return trimesh.creation.cylinder(radius=s[0], height=2 * s[1], sections=24)
    if t == G.mjGEOM_BOX:
        return trimesh.creation.box(2 * s[:3])
    if t == G.mjGEOM_CAPSULE:
        return trimesh.creation.capsule(2 * s[1], s[0])
    return None


def visible_parts(body, anchors, exclude=()) -> dict[int, list]:
    """The :class:`~warp_vision.body.Body`'s visible geoms (group 0, not transparent) as meshes with their RGBA as
    vertex colours, grouped by anchor: {body id: [meshes in that body's frame]}. A geom belongs to the nearest of its
    body's ancestors (itself included) named in ``anchors``, else to the world (id 0: meshes in the
    world frame at the current pose). Bodies named in ``exclude`` (and their geoms) are left out."""
    m, d = body.model, body.data
    ids = {m.body(n).id for n in anchors if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) >= 0}
    skip = {m.body(n).id for n in exclude if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) >= 0}
    parts: dict[int, list] = {}
    for g in range(m.ngeom):
        b = int(m.geom_bodyid[g])
        if m.geom_group[g] != 0 or m.geom_rgba[g, 3] == 0 or b in skip:
            continue
        mesh = geom_mesh(m, g)
        if mesh is None:
            continue
        anchor = b
        while anchor not in ids and anchor != 0:
            anchor = int(m.body_parentid[anchor])
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = d.geom_xmat[g].reshape(3, 3), d.geom_xpos[g]
        mesh.apply_transform(np.linalg.inv(body.pose(anchor)) @ T)
        rgb = np.clip(m.geom_rgba[g, :3], 0, 1)
        mesh.visual.vertex_colors = np.tile(np.r_[rgb * 255, 255].astype(np.uint8), (len(mesh.vertices), 1))
        parts.setdefault(anchor, []).append(mesh)
    return parts
