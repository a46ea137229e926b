"""CLI: bad input exits 2 with a message naming the problem."""

import subprocess
import sys

from training.__main__ import main
from training.synthetic import make_synthetic_crop_dataset


def test_cli_missing_data_folder_exits_2(tmp_path):
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "training",
            "train",
            "--data",
            str(tmp_path / "missing"),
            "--out",
            str(tmp_path / "run"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2
    assert "missing" in r.stderr and "does not exist" in r.stderr and "Traceback" not in r.stderr


def test_cli_wrong_arch_for_dataset_exits_2(tmp_path, capsys):
    make_synthetic_crop_dataset(tmp_path / "d", 8, 4, 4, arch="gqcnn", kappa_px=0.0)
    rc = main(
        ["train", "--data", str(tmp_path / "d"), "--arch", "fast_vgqcnn", "--out", str(tmp_path / "r"), "--no-progress"]
    )
    assert rc == 2 and "cannot train 'fast_vgqcnn'" in capsys.readouterr().err


def test_cli_evaluate_without_run_exits_2(tmp_path, capsys):
    make_synthetic_crop_dataset(tmp_path / "d", 8, 4, 4)
    rc = main(["evaluate", "--run", str(tmp_path / "norun"), "--data", str(tmp_path / "d"), "--no-progress"])
    assert rc == 2 and "norun" in capsys.readouterr().err


def test_cli_bad_option_value_exits_2(tmp_path, capsys):
    make_synthetic_crop_dataset(tmp_path / "d", 8, 4, 4)
    rc = main(["train", "--data", str(tmp_path / "d"), "--out", str(tmp_path / "r"), "--batch-size", "0"])
    assert rc == 2 and "batch_size" in capsys.readouterr().err


def test_cli_bench_measures_precisions_side_by_side(capsys):
    import json

    assert main(["bench", "--steps", "2", "--warmup", "0", "--batch-size", "4", "--precision", "fp32", "bf16"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert set(r["precisions"]) == {"fp32", "bf16"} and r["precisions"]["fp32"]["speedup"] == 1.0
    assert r["precisions"]["bf16"]["samples_per_s"] > 0


def test_cli_bench_times_the_predict_pass_per_batch_size(capsys):
    import json

    argv = ["bench", "--steps", "1", "--warmup", "0", "--batch-size", "4", "--precision", "fp32", "bf16"]
    assert main([*argv, "--predict-rows", "8", "--predict-batch-sizes", "2", "8"]) == 0
    r = json.loads(capsys.readouterr().out)["predict_rows_per_s"]
    assert set(r) == {"fp32", "bf16"} and set(r["fp32"]) == {"2", "8"} and min(r["bf16"].values()) > 0
    assert main([*argv, "--predict-rows", "8", "--predict-batch-sizes", "0"]) == 2
    assert "batch size" in capsys.readouterr().err
