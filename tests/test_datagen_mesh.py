"""datagen.mesh: mesh sources, loading with repair and rescale, stable poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from datagen.mesh import (
    GraspableObject,
    MeshError,
    MeshParams,
    MeshSource,
    load_object,
    mesh_sources,
    principal_extents,
    stable_poses,
)

KEEP = MeshParams(rescale="keep")


def write_box_obj(path: Path, extents=(2.0, 4.0, 6.0)) -> Path:
    trimesh.creation.box(extents=extents).export(path)
    return path


def write_urdf(path: Path, mesh_name: str, scale: str) -> Path:
    path.write_text(
        f"""<robot name="r"><link name="l">
  <visual><geometry><mesh filename="{mesh_name}" scale="{scale}"/></geometry></visual>
  <collision><geometry><mesh filename="{mesh_name}" scale="{scale}"/></geometry></collision>
</link></robot>"""
    )
    return path


def test_missing_folder_raises_file_not_found_naming_it(tmp_path):
    missing = tmp_path / "no_such_meshes"
    with pytest.raises(FileNotFoundError, match="no_such_meshes"):
        mesh_sources(missing)


def test_folder_without_meshes_raises_value_error(tmp_path):
    (tmp_path / "readme.txt").write_text("nothing here")
    with pytest.raises(ValueError, match="holds no"):
        mesh_sources(tmp_path)


def test_urdf_source_lists_scale_and_hides_its_mesh(tmp_path):
    write_box_obj(tmp_path / "box.obj")
    write_urdf(tmp_path / "thing.urdf", "box.obj", "0.01 0.01 0.01")
    write_box_obj(tmp_path / "other.obj")
    srcs = mesh_sources(tmp_path)
    assert [s.name for s in srcs] == ["other", "thing"]
    thing = srcs[1]
    assert thing.path.name == "box.obj" and thing.scale == pytest.approx(0.01)
    assert srcs[0].scale == 1.0


def test_load_urdf_applies_mesh_scale(tmp_path):
    write_box_obj(tmp_path / "box.obj", extents=(2.0, 4.0, 6.0))
    write_urdf(tmp_path / "thing.urdf", "box.obj", "0.01 0.01 0.01")
    obj = load_object(mesh_sources(tmp_path)[0], KEEP)
    assert np.allclose(np.sort(obj.mesh.extents), [0.02, 0.04, 0.06], atol=1e-9)
    assert obj.scale == pytest.approx(0.01)


def test_load_urdf_with_non_uniform_scale(tmp_path):
    write_box_obj(tmp_path / "box.obj", extents=(1.0, 1.0, 1.0))
    write_urdf(tmp_path / "thing.urdf", "box.obj", "0.01 0.02 0.03")
    obj = load_object(mesh_sources(tmp_path)[0], KEEP)
    assert np.allclose(obj.mesh.extents, [0.01, 0.02, 0.03], atol=1e-9)


def test_urdf_naming_a_missing_mesh_raises_mesh_error(tmp_path):
    write_urdf(tmp_path / "ghost.urdf", "nowhere.obj", "1 1 1")
    (src,) = mesh_sources(tmp_path)
    with pytest.raises(MeshError, match="ghost.urdf.*not found"):
        load_object(src)


def test_nan_vertices_raise_mesh_error_naming_file(tmp_path):
    p = tmp_path / "broken.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    with pytest.raises(MeshError, match=r"broken\.obj.*not finite"):
        load_object(MeshSource("broken", p, 1.0))


def test_empty_and_garbage_files_raise_mesh_error(tmp_path):
    empty = tmp_path / "empty.obj"
    empty.write_text("# no geometry\n")
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(b"\x00\x01 definitely not an stl")
    for p in (empty, garbage):
        with pytest.raises(MeshError, match=p.name):
            load_object(MeshSource(p.stem, p, 1.0))


def test_flat_mesh_raises_mesh_error(tmp_path):
    p = tmp_path / "plane.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n")
    with pytest.raises(MeshError, match="plane.obj.*volume"):
        load_object(MeshSource("plane", p, 1.0))


def test_open_mesh_gets_holes_filled(tmp_path):
    box = trimesh.creation.box(extents=(0.03, 0.04, 0.05))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)  # one side missing
    assert not open_box.is_watertight
    p = tmp_path / "open.stl"
    open_box.export(p)
    obj = load_object(MeshSource("open", p, 1.0), KEEP)
    assert obj.mesh.is_watertight
    assert obj.mesh.volume == pytest.approx(0.03 * 0.04 * 0.05, rel=1e-6)
    assert any("filled holes" in r for r in obj.repairs)


def test_unfillable_open_mesh_falls_back_to_convex_hull(tmp_path):
    cyl = trimesh.creation.cylinder(radius=0.02, height=0.05, sections=16)
    side = np.abs(cyl.face_normals[:, 2]) < 0.9
    p = tmp_path / "tube.ply"  # an open tube: both caps missing
    trimesh.Trimesh(cyl.vertices, cyl.faces[side], process=False).export(p)
    obj = load_object(MeshSource("tube", p, 1.0), KEEP)
    assert obj.mesh.is_watertight
    assert obj.mesh.volume == pytest.approx(cyl.volume, rel=1e-6)
    assert any("convex hull" in r for r in obj.repairs)


def test_fragments_merge_or_keep_largest(tmp_path):
    a = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    b = trimesh.creation.box(extents=(0.01, 0.01, 0.01))
    b.apply_translation([0.05, 0, 0])
    p = tmp_path / "two.stl"
    trimesh.util.concatenate([a, b]).export(p)
    merged = load_object(MeshSource("two", p, 1.0), KEEP)
    largest = load_object(MeshSource("two", p, 1.0), MeshParams(rescale="keep", fragments="largest"))
    assert merged.mesh.volume == pytest.approx(0.02**3 + 0.01**3, rel=1e-6)
    assert largest.mesh.volume == pytest.approx(0.02**3, rel=1e-6)
    assert merged.mesh.is_watertight and largest.mesh.is_watertight


def test_min_extent_rescale_and_centre_of_mass_at_origin(tmp_path):
    p = write_box_obj(tmp_path / "box.obj", extents=(2.0, 4.0, 6.0))
    obj = load_object(MeshSource("box", p, 1.0), MeshParams(target_min_extent=0.04))
    assert principal_extents(obj.mesh) == pytest.approx([0.04, 0.08, 0.12], rel=1e-9)
    assert np.allclose(obj.mesh.center_mass, 0.0, atol=1e-12)
    assert obj.scale == pytest.approx(0.02)


def test_bad_mesh_params_raise_value_error():
    with pytest.raises(ValueError, match="rescale"):
        MeshParams(rescale="huge")
    with pytest.raises(ValueError, match="target_min_extent"):
        MeshParams(target_min_extent=0.0)


def test_stable_poses_rest_on_table_with_valid_probabilities():
    obj = GraspableObject("box", "test", trimesh.creation.box(extents=(0.03, 0.04, 0.05)))
    T, p = stable_poses(obj, min_probability=0.12)
    assert len(T) == len(p) > 0
    assert np.all(p >= 0.12) and p.sum() <= 1 + 1e-9
    assert np.all(np.diff(p) <= 0)
    for t in T:
        assert np.allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-9)
        z = trimesh.transform_points(obj.mesh.vertices, t)[:, 2]
        assert z.min() == pytest.approx(0.0, abs=1e-12)
        assert np.allclose(t[:2, 3], 0.0)  # centre of mass above the world origin


def test_stable_poses_max_poses_keeps_most_probable():
    obj = GraspableObject("box", "test", trimesh.creation.box(extents=(0.03, 0.04, 0.05)))
    T_all, p_all = stable_poses(obj, min_probability=0.0)
    T2, p2 = stable_poses(obj, min_probability=0.0, max_poses=2)
    assert len(p2) == 2 and np.allclose(p2, p_all[:2])


def test_default_source_is_pybullet_random_urdfs_and_nan_mesh_is_skipped():
    srcs = mesh_sources()
    assert len(srcs) == 1000 and srcs[0].name == "000" and srcs[-1].name == "999"
    assert srcs[0].scale == pytest.approx(0.015)
    by_name = {s.name: s for s in srcs}
    with pytest.raises(MeshError, match="168.obj.*not finite"):
        load_object(by_name["168"])
    obj = load_object(by_name["000"])
    assert obj.mesh.is_watertight
    assert principal_extents(obj.mesh)[0] == pytest.approx(0.04, rel=1e-6)


def test_inside_out_mesh_gets_outward_normals(tmp_path):
    box = trimesh.creation.box(extents=(0.03, 0.04, 0.05))
    p = tmp_path / "inverted.stl"
    trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False).export(p)
    obj = load_object(MeshSource("inverted", p, 1.0), KEEP)
    assert obj.mesh.volume == pytest.approx(0.03 * 0.04 * 0.05, rel=1e-6)
    # outward: face normals point away from the centre of mass
    assert np.all(np.einsum("ij,ij->i", obj.mesh.face_normals, obj.mesh.triangles_center) > 0)
