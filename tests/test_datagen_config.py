"""DatagenConfig: JSON round trip, overrides, errors that name the bad field."""

from __future__ import annotations

import json
import math

import pytest

from datagen.config import ConfigError, DatagenConfig, load_config, parse_override


def test_defaults_follow_the_spec():
    c = DatagenConfig()
    assert c.cameras_per_pose == 10
    assert c.stable_pose_min_probability == 0.01
    assert c.camera.phi_range[1] == pytest.approx(math.radians(70))
    assert c.with_overrides({"label.kind": "paper"}).label_threshold == 0.002  # the paper's label
    assert c.label.kind == "physics" and c.label_threshold == 0.5  # issue 17's default: see docs/labels.md


def test_json_round_trip(tmp_path):
    c = DatagenConfig().with_overrides({"cameras_per_pose": 3, "camera.d_range": [0.5, 0.9], "seed": 7})
    p = tmp_path / "c.json"
    p.write_text(json.dumps(c.to_dict()))
    c2 = load_config(p)
    assert c2 == c
    assert c2.camera.d_range == (0.5, 0.9)


def test_partial_file_keeps_defaults(tmp_path):
    p = tmp_path / "c.json"
    p.write_text(json.dumps({"antipodal": {"num_samples": 20}}))
    c = load_config(p)
    assert c.antipodal.num_samples == 20 and c.antipodal.friction_coef == 0.5 and c.cameras_per_pose == 10


@pytest.mark.parametrize(
    "override, field",
    [
        ({"cameras_per_pose": 0}, "cameras_per_pose"),
        ({"camera.d_range": [1.0, 0.5]}, "d_range"),
        ({"antipodal.num_samples": -5}, "num_samples"),
        ({"stable_pose_min_probability": 1.5}, "stable_pose_min_probability"),
        ({"quality.sigma_friction": -0.1}, "sigma_friction"),
        ({"num_objects": "many"}, "num_objects"),
        ({"sampling.target_positivity": 0}, "target_positivity"),
        ({"antipodal.max_width": 0.08}, "max_width"),
    ],
)
def test_bad_values_name_the_field(override, field):
    with pytest.raises(ConfigError, match=field):
        DatagenConfig().with_overrides(override)


def test_unknown_keys_are_rejected(tmp_path):
    with pytest.raises(ConfigError, match="camera.bogus"):
        DatagenConfig().with_overrides({"camera.bogus": 1})
    p = tmp_path / "c.json"
    p.write_text(json.dumps({"mesh": {"scale_up": 2}}))
    with pytest.raises(ConfigError, match="scale_up"):
        load_config(p)


def test_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "missing.json")
    p = tmp_path / "c.json"
    p.write_text("{not json")
    with pytest.raises(ConfigError, match="not valid JSON"):
        load_config(p)


def test_parse_override():
    assert parse_override("camera.d_range=[0.5, 0.9]") == ("camera.d_range", [0.5, 0.9])
    assert parse_override("mesh.rescale=keep") == ("mesh.rescale", "keep")
    with pytest.raises(ConfigError):
        parse_override("seed")
