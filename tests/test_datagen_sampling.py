"""Sampling stage (SPEC section 3) on synthetic arrays and a small fake dataset."""

from __future__ import annotations

import math

import numpy as np
import pytest
from datagen_fakes import fake_dataset

from datagen import storage
from datagen.sampling import (
    SamplingParams,
    angle_bins,
    equalise_positivity,
    psi_mask,
    sample_dataset,
    sample_rates,
    split_objects,
    uniform_over_bins,
)


def test_sample_rates_follow_the_paper_formula():
    p = np.array([6.0, 10.0, 19.0, 40.0])
    neg, pos = sample_rates(p, 19.0)
    expected_neg = (100 / 19 * p - p) / (100 - p)
    np.testing.assert_allclose(neg, np.minimum(expected_neg, 1))
    np.testing.assert_allclose(pos, np.minimum(1 / expected_neg, 1))
    assert neg[2] == pytest.approx(1.0) and pos[2] == pytest.approx(1.0)
    assert neg[3] == 1.0 and pos[3] < 1.0


def test_sample_rates_reach_the_target_positivity():
    for p in (3.0, 12.0, 50.0):
        neg, pos = sample_rates(np.array([p]), 19.0)
        new = p * pos[0] / (p * pos[0] + (100 - p) * neg[0])
        assert new == pytest.approx(0.19)


def test_sample_rates_edge_bins():
    neg, pos = sample_rates(np.array([0.0, 100.0, np.nan]), 19.0)
    assert neg.tolist() == [0.0, 1.0, 1.0]
    assert pos.tolist() == [1.0, 0.0, 1.0]


def test_equalisation_flattens_positivity_over_beta():
    rng = np.random.default_rng(0)
    n = 200_000
    beta = rng.uniform(0, np.radians(90), n)
    native = 0.3 - 0.25 * beta / np.radians(90)  # positivity declines with beta, as in the paper
    labels = rng.random(n) < native
    keep = equalise_positivity(labels, beta, SamplingParams(), rng)
    bins = angle_bins(beta[keep], np.radians(5))
    for b in range(18):
        assert labels[keep][bins == b].mean() == pytest.approx(0.19, abs=0.02)


def test_psi_filter_drops_90_degrees_and_above():
    psi = np.radians([0.0, 89.9, 90.0, 120.0])
    assert psi_mask(psi, math.pi / 2).tolist() == [True, True, False, False]


def test_uniform_undersampling_equalises_bin_counts():
    rng = np.random.default_rng(1)
    phi = np.radians(np.concatenate([np.full(100, 2.0), np.full(30, 7.0), np.full(55, 12.0)]))
    beta = np.radians(np.concatenate([np.full(100, 1.0), np.full(30, 1.0), np.full(55, 6.0)]))
    keep = uniform_over_bins(phi, beta, SamplingParams(), rng)
    assert keep[:100].sum() == 30 and keep[100:130].sum() == 30 and keep[130:].sum() == 30


def test_split_is_deterministic_and_covers_all_splits():
    ids = list(range(20))
    a = split_objects(ids, (0.8, 0.1, 0.1), seed=3)
    assert a == split_objects(ids, (0.8, 0.1, 0.1), seed=3)
    assert a != split_objects(ids, (0.8, 0.1, 0.1), seed=4)
    assert sorted(a.values()).count("train") == 16
    assert sorted(a.values()).count("val") == 2
    assert set(split_objects([5, 9, 11], (0.8, 0.1, 0.1), 0).values()) == {"train", "val", "test"}


def test_bad_sampling_params_name_the_field():
    with pytest.raises(ValueError, match="target_positivity"):
        SamplingParams(target_positivity=150)
    with pytest.raises(ValueError, match="split_fractions"):
        SamplingParams(split_fractions=(0.5, 0.1, 0.1))


def test_sample_dataset_writes_object_wise_split(tmp_path):
    fake_dataset(tmp_path / "raw", n_objects=5, n_grasps=300)
    logs = []
    stats = sample_dataset(tmp_path / "raw", tmp_path / "s", SamplingParams(uniform_quantile=0.5), log=logs.append)
    ds = storage.open_dataset(tmp_path / "s")
    m = ds.manifest
    assert sorted(sum(m["splits"].values(), [])) == [0, 1, 2, 3, 4]  # every object in exactly one split
    for sh in ds:
        assert sh.object_id in m["splits"][m["objects"][sh.object_id]["split"]]
        assert np.all(sh.grasps["psi"] < np.pi / 2)
        assert sh.grasps["image_index"].max() < len(sh.images["depth"])
    assert m["counts"]["grasps"] == stats["steps"]["uniform"]["grasps"]
    assert stats["steps"]["psi"]["grasps"] < stats["steps"]["native"]["grasps"]
    assert any("beta bin" in line for line in logs)
    assert (tmp_path / "s" / "plots" / "positivity_by_beta.png").stat().st_size > 1000


def test_workers_write_the_same_sampled_dataset(tmp_path):
    """Shards read and written by two processes: the same manifest and byte-identical shards as one."""
    fake_dataset(tmp_path / "raw", n_objects=4, n_grasps=200)
    params = SamplingParams(uniform_quantile=0.5)
    for w in (1, 2):
        sample_dataset(tmp_path / "raw", tmp_path / f"s{w}", params, log=lambda s: None, plot=False, workers=w)
    one, two = (storage.open_dataset(tmp_path / f"s{w}").manifest for w in (1, 2))
    assert one["shards"] == two["shards"] and one["objects"] == two["objects"] and one["splits"] == two["splits"]
    assert one["counts"] == two["counts"] and one["counts"]["shards"] == 4


def test_dataset_without_positives_is_refused(tmp_path):
    fake_dataset(tmp_path / "raw", n_objects=2, n_grasps=20, positive_rate=0.0)
    with pytest.raises(ValueError, match="no positive grasp"):
        sample_dataset(tmp_path / "raw", tmp_path / "s", log=lambda s: None)
    assert not (tmp_path / "s").exists()


def test_split_over_a_larger_population_splits_as_the_whole_run(tmp_path):
    """A partly generated run (objects 0-4 of 12) sampled with --split-over the whole run's ids puts
    each object where the whole run's split puts it, and records the population."""
    fake_dataset(tmp_path / "raw", n_objects=5, n_grasps=120)
    whole = list(range(12))
    sample_dataset(tmp_path / "raw", tmp_path / "s", SamplingParams(seed=4), log=lambda s: None, split_over=whole)
    m = storage.open_dataset(tmp_path / "s").manifest
    want = split_objects(whole, SamplingParams().split_fractions, 4)
    assert {i: s for s, ids in m["splits"].items() for i in ids} == {i: want[i] for i in range(5)}
    assert m["split_object_ids"] == whole
    with pytest.raises(ValueError, match="not among the manifest's split_object_ids"):
        sample_dataset(tmp_path / "raw", tmp_path / "t", log=lambda s: None, split_over=[0, 1])


def test_split_over_file_must_list_object_ids(tmp_path, capsys):
    from datagen.__main__ import main

    fake_dataset(tmp_path / "raw", n_objects=2, n_grasps=20)
    (tmp_path / "ids.json").write_text('{"ids": [0, 1]}')
    args = ["sample", "--in", str(tmp_path / "raw"), "--out", str(tmp_path / "s"), "--split-over"]
    assert main([*args, str(tmp_path / "ids.json")]) == 2
    assert "must hold a JSON list of object ids" in capsys.readouterr().err
    assert main([*args, str(tmp_path / "missing.json")]) == 2
