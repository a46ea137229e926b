"""Boxes on a table rendered by datagen (embree), for the planning tests."""

from __future__ import annotations

from vgq.camera import DEFAULT_INTRINSICS


def boxes_scene(extents=((0.03, 0.04, 0.05),), at=((0.0, 0.0),), d: float = 0.6, phi: float = 0.35, theta: float = 0.6):
    """(depth (300, 300) float32 metres, T_world_camera (4, 4), meshes in the world frame)
    of axis-aligned boxes resting on the table z = 0 at world (x, y) ``at``."""
    import trimesh

    from datagen.camera import look_at_table_origin
    from datagen.render import render_depth

    meshes = []
    for e, (x, y) in zip(extents, at):
        b = trimesh.creation.box(extents=e)
        b.apply_translation([x, y, e[2] / 2])
        meshes.append(b)
    T_wc = look_at_table_origin(d, phi, theta)[0]
    depth = render_depth(trimesh.util.concatenate(meshes), T_wc, DEFAULT_INTRINSICS)
    return depth, T_wc, meshes


def mesh_scene(mesh, d: float = 0.6, phi: float = 0.35, theta: float = 0.6):
    """(depth (300, 300) float32 metres, T_world_camera (4, 4)) of ``mesh`` (world frame,
    resting on the table z = 0) seen from distance ``d``, elevation pi/2 - ``phi``."""
    from datagen.camera import look_at_table_origin
    from datagen.render import render_depth

    T_wc = look_at_table_origin(d, phi, theta)[0]
    return render_depth(mesh, T_wc, DEFAULT_INTRINSICS), T_wc


def open_box(outer=(0.08, 0.08, 0.05), wall: float = 0.004):
    """An open-topped box (a container: walls and floor ``wall`` thick), world frame, on z = 0."""
    import trimesh

    o = trimesh.creation.box(extents=outer)
    inner = trimesh.creation.box(extents=(outer[0] - 2 * wall, outer[1] - 2 * wall, outer[2]))
    inner.apply_translation([0, 0, wall])
    cup = o.difference(inner, engine="manifold")
    cup.apply_translation([0, 0, outer[2] / 2])
    return cup
