"""Object families: watertight meshes of physical size, deterministic, graspable, and usable
by the datagen pipeline (load_object, stable poses, antipodal sampler)."""

from __future__ import annotations

import numpy as np
import pytest

from datagen.families import (FAMILIES, FamilyError, build_mesh, family_sources, make_object, object_name,
                              sample_params)
from datagen.grasps import AntipodalParams, sample_antipodal_grasps
from datagen.mesh import MeshError, MeshParams, MeshSource, load_object, stable_poses

ALL = list(FAMILIES)


def test_at_least_ten_families():
    assert len(FAMILIES) >= 10


@pytest.mark.parametrize("family", ALL)
def test_family_meshes_are_closed_single_bodies_within_their_size_range(family):
    lo, hi = FAMILIES[family].extent_range
    for seed, index in ((0, 0), (0, 1), (7, 3)):
        mesh = make_object(family, index, seed).mesh
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.is_volume, (family, seed, index)
        assert mesh.volume > 0
        assert len(mesh.split(only_watertight=False)) == 1, f"{family} {index}: more than one body"
        ext = mesh.extents
        assert lo - 1e-9 <= ext.min() and ext.max() <= hi + 1e-9, (family, index, ext)


@pytest.mark.parametrize("family", ALL)
def test_same_family_index_seed_gives_the_same_mesh(family):
    a, b = make_object(family, 2, 5), make_object(family, 2, 5)
    assert a.params == b.params and a.name == b.name == object_name(family, 2)
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    np.testing.assert_array_equal(a.mesh.faces, b.mesh.faces)
    assert sample_params(family, 3, 5) != a.params  # another index, another object
    assert sample_params(family, 2, 6) != a.params  # another run seed, another object


def _thinnest_wall(mesh, n: int = 400) -> float:
    """Smallest distance, over sampled surface points, from the point through the solid
    along the inward normal to where the ray leaves it (metres)."""
    pts, fi = mesh.sample(n, return_index=True, seed=0)
    inward = -mesh.face_normals[fi]
    origins = pts + 1e-6 * inward
    loc, ray_idx, _ = mesh.ray.intersects_location(origins, inward, multiple_hits=False)
    d = np.linalg.norm(loc - origins[ray_idx], axis=1)
    return float(d.min())


@pytest.mark.parametrize("family", ALL)
def test_every_object_has_a_dimension_the_5cm_jaws_can_span(family):
    for index in range(3):
        assert _thinnest_wall(make_object(family, index, 0).mesh) <= 0.05, (family, index)


@pytest.mark.parametrize("family", ALL)
def test_family_object_goes_through_load_stable_poses_and_the_antipodal_sampler(family):
    (src,) = family_sources({family: 1}, seed=0)
    built = make_object(family, 0, 0).mesh
    obj = load_object(src, MeshParams())  # default params rescale files, never a procedural object
    np.testing.assert_allclose(np.sort(obj.mesh.extents), np.sort(built.extents), rtol=1e-6, atol=1e-9)
    assert obj.scale == 1.0
    T, p = stable_poses(obj, 0.01)
    assert len(T) >= 1
    grasps = sample_antipodal_grasps(obj.mesh, AntipodalParams(num_samples=20), np.random.default_rng(0))
    assert len(grasps) > 0, f"{family}: no antipodal grasp"
    assert np.all(grasps.widths <= 0.05 + 1e-9)


def test_unknown_family_and_bad_parameters_are_named():
    with pytest.raises(FamilyError, match="unknown object family 'teapot'"):
        sample_params("teapot", 0)
    with pytest.raises(FamilyError, match="box: size"):
        build_mesh("box", {"size": [0.1, -0.02, 0.03]})
    with pytest.raises(FamilyError, match="cylinder: radius"):
        build_mesh("cylinder", {"radius": float("nan"), "height": 0.1})
    with pytest.raises(FamilyError, match="mug: missing parameter 'radius'"):
        build_mesh("mug", {})
    with pytest.raises(FamilyError, match="count"):
        family_sources({"box": -1})


def test_bad_family_parameters_are_a_mesh_error_for_the_pipeline(tmp_path):
    src = MeshSource("box_0000", tmp_path / "family:box_0000", 1.0, "box", {"size": [0.1, 0.02, 7.0]})
    with pytest.raises(MeshError, match="box: size"):
        load_object(src)
