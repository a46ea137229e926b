"""Placement rows from a depth image (vgq.placement, planning.placement)."""

import numpy as np
import pytest

from planning.placement import ImagePlacement, placement_rows, region_at
from vgq.camera import DEFAULT_INTRINSICS as INTR
from vgq.placement import MAX_REGION_DISTANCE_PX, PLACEMENT_COLUMNS

TABLE_Z, BOX_TOP_Z = 0.7, 0.6  # camera looking straight down: the table 0.7 m away, a 10 cm tall box
IDENTITY = np.array([[1.0, 0.0, 0.0, 0.0]])  # jaw axis along camera x, approach along camera z


def box_scene() -> np.ndarray:
    depth = np.full((INTR.height, INTR.width), TABLE_Z, np.float32)
    depth[130:170, 120:180] = BOX_TOP_Z  # 60 x 40 px top face around the image centre
    return depth


def test_a_grasp_at_the_top_face_centre_is_at_the_object_centre_line():
    row = placement_rows(box_scene(), INTR, np.array([[149.5, 149.5, 0.65]]), IDENTITY)[0]
    known, offset, along, across, depth, height, top = row
    assert len(row) == len(PLACEMENT_COLUMNS) and known == 1
    assert offset == pytest.approx(0, abs=1e-3)
    assert along == pytest.approx(0, abs=1e-3) and across == pytest.approx(0, abs=1e-3)
    assert depth == pytest.approx(0, abs=1e-3)  # the guess sits at half the top's height: 5 cm, the grasp's
    assert height == pytest.approx(0.05, abs=1e-3) and top == pytest.approx(0.1, abs=1e-3)


def test_an_off_centre_grasp_reads_its_offset_along_the_jaw_axis_in_metres():
    row = placement_rows(box_scene(), INTR, np.array([[169.5, 149.5, 0.65]]), IDENTITY)[0]
    assert row[2] == pytest.approx(20 * 0.65 / INTR.fx, rel=0.02)  # 20 px off, the grasp 0.65 m away
    assert row[1] == pytest.approx(row[2], rel=1e-3)  # the offset is horizontal: all of it, in the table plane


def test_a_jaw_axis_turned_a_quarter_reads_the_same_offset_across():
    q = np.array([[np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)]])  # a quarter turn about the approach
    row = placement_rows(box_scene(), INTR, np.array([[169.5, 149.5, 0.65]]), q)[0]
    assert row[2] == pytest.approx(0, abs=1e-3) and row[3] == pytest.approx(20 * 0.65 / INTR.fx, rel=0.02)


def test_an_image_without_readings_gives_unknown_rows():
    rows = placement_rows(
        np.zeros((INTR.height, INTR.width), np.float32), INTR, np.array([[149.5, 149.5, 0.65]]), IDENTITY
    )
    assert (rows == 0).all()


def test_a_grasp_far_from_every_object_is_unknown_and_a_near_one_takes_the_nearest_object():
    place = ImagePlacement.analyse(box_scene(), INTR)
    rows = place.rows(np.array([[20.0, 20.0, 0.7], [185.0, 150.0, 0.65]]), np.repeat(IDENTITY, 2, 0))
    assert rows[0, 0] == 0 and (rows[0] == 0).all()
    assert rows[1, 0] == 1 and rows[1, 6] == pytest.approx(0.1, abs=1e-3)  # 5 px off the box: the box's


def test_the_analysis_is_the_same_for_the_same_image():
    a, b = ImagePlacement.analyse(box_scene(), INTR), ImagePlacement.analyse(box_scene(), INTR)
    assert np.array_equal(a.region, b.region) and np.array_equal(a.centres, b.centres)


def test_a_pixel_off_every_region_reads_the_nearest_region_pixel_within_reach():
    """On a table speckled with tiny regions (as a sensor's noise makes it), every pixel of the image
    reads the region of its nearest region pixel within MAX_REGION_DISTANCE_PX (ties: the smaller
    row, then column offset), or 0 beyond reach: checked against a brute-force search."""
    rng = np.random.default_rng(0)
    depth = box_scene()
    depth[200:230, 40:70] = BOX_TOP_Z  # a second object
    specks = rng.integers(0, (INTR.height, INTR.width), (30, 2))
    depth[specks[:, 0], specks[:, 1]] = TABLE_Z - 0.01  # 1 px regions 1 cm above the table
    region = ImagePlacement.analyse(depth, INTR).region
    u, v = rng.integers(0, INTR.width, 400), rng.integers(0, INTR.height, 400)
    ys, xs = np.nonzero(region)
    expect = []
    for uu, vv in zip(u, v):
        d2 = (ys - vv) ** 2 + (xs - uu) ** 2
        key = np.lexsort((xs - uu, ys - vv, d2))[0]
        expect.append(region[ys[key], xs[key]] if d2[key] <= MAX_REGION_DISTANCE_PX**2 else 0)
    got = region_at(region, u, v)
    assert np.array_equal(got, expect)
    assert (got == 0).any() and (region[v, u] == 0).sum() > (got == 0).sum()  # some found in reach, some not
