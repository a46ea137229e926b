"""export.evaluate: an exported folder scored on a crop dataset through its ONNX graphs, per family."""

from __future__ import annotations

import numpy as np
import pytest
from datagen_fakes import fake_dataset

from datagen import storage
from datagen.crops import make_crops
from export.evaluate import crop_rows, evaluate, main, raw_scores
from service.runtime import FastModel


@pytest.fixture(scope="module")
def crops(tmp_path_factory):
    root = tmp_path_factory.mktemp("ev")
    g = fake_dataset(root / "g", n_objects=10, n_images=1, n_grasps=12, seed=3)
    for o in g["objects"]:
        o["family"] = "mug" if o["object_id"] % 2 else "box"
    storage.write_manifest(root / "g", g)
    make_crops(root / "g", root / "c", "fast_vgqcnn", log=lambda s: None, sensor="clean")
    return root / "c"


def test_scores_are_each_crops_own_in_any_batch(model_dir, crops):
    rows = crop_rows(crops, "test", 50)
    batched = raw_scores(model_dir, rows["images"], rows["poses"], batch=7)
    m = FastModel(model_dir, threads=1, head_precision="fp32", encoder_precision="fp32")
    one = [m.score(m.encode(rows["images"][i]), rows["poses"][i : i + 1])[0] for i in range(len(batched))]
    np.testing.assert_allclose(batched, one, atol=1e-5)


def test_metrics_split_by_family_and_agree_with_the_whole():
    y = np.array([1, 0, 1, 0, 1, 0], bool)
    s = np.array([0.9, 0.2, 0.4, 0.6, 0.8, 0.1], np.float32)
    fam = np.array(["a", "a", "b", "b", "b", ""])
    r = evaluate(y, s, fam)
    assert r["all"]["tpr"] == pytest.approx(2 / 3) and r["all"]["tnr"] == pytest.approx(2 / 3)
    assert set(r["by_family"]) == {"a", "b"} and r["by_family"]["a"]["balanced_accuracy"] == 1.0
    assert r["by_family"]["b"]["tpr"] == 0.5 and r["by_family"]["b"]["tnr"] == 0.0


def test_metrics_by_the_approach_to_straight_down_in_15_degree_bins():
    y = np.array([1, 0, 1, 0], bool)
    s = np.array([0.9, 0.2, 0.4, 0.6], np.float32)
    r = evaluate(y, s, np.array(["a"] * 4), beta=np.radians([5.0, 10.0, 50.0, 55.0]))
    bins = r["by_approach_beta_deg"]
    assert list(bins) == ["0-15", "45-60"]
    assert bins["0-15"]["balanced_accuracy"] == 1.0 and bins["45-60"]["balanced_accuracy"] == 0.0


def test_cli_prints_a_row_per_family_and_refuses_a_folder_without_a_card(model_dir, crops, capsys, tmp_path):
    res = main(["--model-dir", str(model_dir), "--data", str(crops), "--split", "train", "--max-n", "40"])
    out = capsys.readouterr().out
    assert "| box |" in out and "| mug |" in out and set(res[str(model_dir)]["by_family"]) == {"box", "mug"}
    assert "beta (deg)" in out and res[str(model_dir)]["by_approach_beta_deg"]
    with pytest.raises(SystemExit) as e:
        main(["--model-dir", str(tmp_path), "--data", str(crops)])
    assert e.value.code == 2


def test_mirror_scores_each_crop_flipped_with_its_pose_mirrored_alone_and_averaged(model_dir, crops, capsys):
    from export.evaluate import mirrored

    d = str(model_dir)
    res = main(["--model-dir", d, "--data", str(crops), "--split", "train", "--max-n", "40", "--mirror"])
    out = capsys.readouterr().out
    assert set(res) == {d, f"{d} (mirrored)", f"{d} (mean of it and its mirror)"} and "correlation" in out
    rows = crop_rows(crops, "train", 40)
    images, poses = mirrored(rows["images"], rows["poses"])
    assert np.array_equal(images[..., ::-1], rows["images"]) and not np.array_equal(images, rows["images"])
    np.testing.assert_allclose(mirrored(images, poses)[1], rows["poses"], atol=1e-6)  # an involution
    both = 0.5 * (raw_scores(d, rows["images"], rows["poses"]) + raw_scores(d, images, poses))
    mean = res[f"{d} (mean of it and its mirror)"]["all"]
    direct = evaluate(rows["labels"], both, rows["family"])["all"]
    assert {k: mean[k] for k in ("auc", "tp", "tn", "fp", "fn")} == pytest.approx(
        {k: direct[k] for k in ("auc", "tp", "tn", "fp", "fn")}
    )
    assert -1.0 <= res[f"{d} (mirrored)"]["score_correlation_with_original"] <= 1.0


def test_a_model_is_not_scored_on_crops_cut_for_another_geometry_unless_asked(model_dir, crops, tmp_path, capsys):
    import json
    import shutil

    turned = tmp_path / "turned"
    shutil.copytree(crops, turned)
    m = json.loads((turned / "manifest.json").read_text())
    m["geometry"]["jaw_turns"] = 4
    (turned / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(SystemExit) as e:
        main(["--model-dir", str(model_dir), "--data", str(turned), "--split", "train", "--max-n", "20"])
    assert e.value.code == 2 and "(not turned)" in capsys.readouterr().err
    res = main(
        ["--model-dir", str(model_dir), "--data", str(turned), "--split", "train", "--max-n", "20", "--other-crops"]
    )
    assert res[str(model_dir)]["all"]["n"] == 20


def test_card_key_records_the_result_in_the_card_keeping_every_other_key(model_dir, crops, tmp_path, capsys):
    import json
    import shutil

    card = tmp_path / "m"
    shutil.copytree(model_dir, card)
    before = json.loads((card / "model_card.json").read_text())
    res = main(
        ["--model-dir", str(card), "--data", str(crops), "--split", "train", "--max-n", "40", "--card-key", "more"]
    )
    after = json.loads((card / "model_card.json").read_text())
    got = after["metrics"].pop("more")
    assert after == before  # nothing else touched
    assert got["all"] == res[str(card)]["all"] and got["split"] == "train" and got["max_n"] == 40
    for bad in ("test", "baseline_gbt", "Not-A-Key"):
        with pytest.raises(SystemExit) as e:
            main(["--model-dir", str(card), "--data", str(crops), "--card-key", bad])
        assert e.value.code == 2 and "--card-key" in capsys.readouterr().err
