"""placement-drift: clean vs sensor placement rows of the same grasps, column by column."""

import subprocess
import sys

import numpy as np
import pytest

from training.data import DatasetError
from training.placement_drift import compare
from training.synthetic import make_synthetic_crop_dataset


@pytest.fixture()
def pair(tmp_path):
    clean, sensor = tmp_path / "clean", tmp_path / "sensor"
    for p in (clean, sensor):
        make_synthetic_crop_dataset(p, 8, 8, 64, signal="placement", seed=3)
    place = np.load(sensor / "test" / "placement.npy")
    known = place[:, 0] > 0.5
    place[known, 1] += 0.004  # the sensor side's offset 4 mm further out, every other column as it was
    place[:8, 0] = 0.0  # and 8 rows it does not know
    place[:8, 1:] = 0.0
    np.save(sensor / "test" / "placement.npy", place)
    return clean, sensor, known


def test_a_shifted_column_and_lost_rows_are_measured(pair):
    clean, sensor, known = pair
    rec = compare(clean, sensor, max_n=0)
    assert rec["columns"]["offset"]["median_abs_diff_m"] == pytest.approx(0.004, abs=1e-5)
    assert rec["columns"]["height"]["median_abs_diff_m"] == 0.0
    assert rec["known_clean"] == pytest.approx(known.mean())
    assert rec["known_sensor"] == pytest.approx((known & (np.arange(64) >= 8)).mean())


def test_crops_of_other_grasps_are_refused(pair, tmp_path):
    clean, _, _ = pair
    make_synthetic_crop_dataset(tmp_path / "other", 8, 8, 64, signal="placement", seed=4)
    with pytest.raises(DatasetError, match="other 'test' rows"):
        compare(clean, tmp_path / "other")


def test_the_cli_prints_the_tables(pair):
    clean, sensor, _ = pair
    out = subprocess.run(
        [sys.executable, "-m", "training", "placement-drift", "--clean", str(clean), "--sensor", str(sensor)],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "| offset | 4.0 |" in out and "| family |" in out
