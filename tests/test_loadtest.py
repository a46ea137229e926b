"""tools.loadtest (the load-test package) against the real service on loopback, and its guards."""

from __future__ import annotations

import json
import os

import pytest
from servers import running_service

from tools.loadtest.cli import main
from tools.loadtest.client import check_target
from tools.loadtest.report import server_latency_totals, server_rss_bytes
from tools.loadtest.workload import Mix


@pytest.fixture(scope="module")
def url(model_dir):
    with running_service(model_dir) as u:
        yield u


def test_loadtest_reports_every_endpoint_with_zero_errors(url, tmp_path):
    out = tmp_path / "load.json"
    report = main(
        [
            "--url",
            url,
            "--clients",
            "2",
            "--duration",
            "2",
            "--warmup",
            "0.2",
            "--k",
            "32",
            "--mix",
            "upload=1,score=4,once=1",
            "--json",
            str(out),
        ]
    )
    assert report["config"]["transport"] == "httpx"
    assert set(report["endpoints"]) == {"upload", "score_first", "score", "score_once"}
    assert all(e["requests"] > 0 and e["errors"] == 0 for e in report["endpoints"].values())
    assert report["errors"] == 0 and report["grasps_per_s"] > 0
    assert report["endpoints"]["score"]["server_mean_ms"] > 0  # read from the service's /metrics
    assert json.loads(out.read_text())["endpoints"]["score"]["p99_ms"] is not None


def test_single_client_uses_the_raw_transport_and_scores_every_call(url):
    report = main(["--url", url, "--clients", "1", "--duration", "1", "--warmup", "0", "--k", "16"])
    score = report["endpoints"]["score"]
    assert report["config"]["transport"] == "raw" and report["errors"] == 0
    assert score["requests"] > 0 and report["grasps_per_s"] > 0


@pytest.mark.parametrize("clients", [1, 2], ids=["raw", "httpx"])
def test_bad_requests_in_the_mix_all_get_a_named_4xx(url, clients):
    """`bad=N` rotates malformed requests (NaN depth, truncated .npy, corrupt PNG, zip bomb,
    broken JSON, zero quaternion, unknown id): every one must be a 4xx with a message."""
    report = main(
        [
            "--url",
            url,
            "--clients",
            str(clients),
            "--duration",
            "1.5",
            "--warmup",
            "0",
            "--k",
            "16",
            "--mix",
            "upload=1,score=1,once=0,bad=7",
        ]
    )
    bad = report["endpoints"]["bad"]
    assert bad["requests"] >= 7 and bad["errors"] == 0 and report["errors"] == 0, report["error_messages"]


def _windows_encoded(url) -> int:
    import httpx

    return httpx.get(url + "/v1/cache").json()["windows_encoded"]


def test_cached_score_mix_encodes_nothing_while_timed(url):
    """``upload=0,score=N``: each client's image is uploaded and its windows encoded before the
    run, so every timed call is a cached score (head only): the service encodes one window per
    client in all, however many calls the run makes."""
    before = _windows_encoded(url)
    report = main(
        [
            "--url",
            url,
            "--clients",
            "2",
            "--duration",
            "1",
            "--warmup",
            "0.2",
            "--k",
            "16",
            "--mix",
            "upload=0,score=4,once=0",
        ]
    )
    assert set(report["endpoints"]) == {"score"} and report["errors"] == 0
    assert report["endpoints"]["score"]["requests"] > 10
    assert _windows_encoded(url) - before == 2  # the two pinned images' windows, nothing while timed


def test_first_score_after_an_upload_is_reported_apart(url):
    """With uploads in the mix, the score call that encodes the new image's windows is the
    ``score_first`` row (one per upload), the rest are ``score``."""
    before = _windows_encoded(url)
    report = main(
        [
            "--url",
            url,
            "--clients",
            "1",
            "--duration",
            "1",
            "--warmup",
            "0",
            "--k",
            "16",
            "--mix",
            "upload=1,score=3,once=0",
        ]
    )
    e = report["endpoints"]
    assert set(e) == {"upload", "score_first", "score"} and report["errors"] == 0
    assert e["score_first"]["requests"] in (e["upload"]["requests"], e["upload"]["requests"] - 1)
    # the example's grasps need one window: each score_first call encoded it, no score call did
    assert _windows_encoded(url) - before == e["score_first"]["requests"]
    assert e["score"]["requests"] >= e["score_first"]["requests"]


def test_plans_in_the_mix_are_timed_and_checked(url):
    """``plan=N``: POST /v1/plan on a fresh image, its own row (client and server latency)."""
    report = main(
        [
            "--url",
            url,
            "--clients",
            "2",
            "--duration",
            "1.5",
            "--warmup",
            "0.2",
            "--mix",
            "upload=0,score=2,once=0,plan=1",
        ]
    )
    assert set(report["endpoints"]) == {"score", "plan"} and report["errors"] == 0
    plan = report["endpoints"]["plan"]
    assert plan["requests"] > 0 and plan["p50_ms"] > 0 and plan["server_mean_ms"] > 0


def test_mix_endpoints_name_what_each_mix_sends():
    assert Mix.parse("upload=1,score=8,once=1").endpoints() == ("upload", "score_first", "score", "score_once")
    assert Mix.parse("upload=0,score=0,once=0,plan=2").endpoints() == ("plan",)
    assert Mix.parse("upload=1,score=1,once=0").endpoints() == ("upload", "score_first")
    assert Mix.parse("upload=0,score=8,once=0").endpoints() == ("score",) and Mix.parse("upload=0,once=0").pinned
    with pytest.raises(ValueError, match="nothing to do"):
        Mix.parse("upload=0,score=0,once=0")


def test_loadtest_refuses_a_non_loopback_host():
    with pytest.raises(ValueError, match="non-loopback"):
        check_target("http://192.0.2.1:8000", allow_remote=False)
    assert check_target("http://localhost:8000/", allow_remote=False) == "http://localhost:8000"


def test_loadtest_cli_exits_with_a_message_for_a_remote_url(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--url", "http://example.com:8000", "--duration", "1"])
    assert e.value.code == 2 and "--allow-remote" in capsys.readouterr().err


def test_mix_parses_counts_and_rejects_unknown_keys():
    assert Mix.parse("upload=2,score=5") == Mix(upload=2, score=5, once=1)
    with pytest.raises(ValueError, match="bad --mix entry"):
        Mix.parse("scores=5")


def test_server_rss_reads_this_process():
    rss = server_rss_bytes(os.getpid())
    assert rss["rss_bytes"] > 0 and os.getpid() in rss["pids"]


def test_server_latency_totals_sum_over_status_labels():
    text = "\n".join(
        [
            "# TYPE vgq_request_seconds histogram",
            'vgq_request_seconds_bucket{endpoint="score",le="0.001"} 3.0',
            'vgq_request_seconds_count{endpoint="score"} 4.0',
            'vgq_request_seconds_sum{endpoint="score"} 0.008',
            'vgq_request_seconds_count{endpoint="upload"} 1.0',
            'vgq_request_seconds_sum{endpoint="upload"} 0.005',
        ]
    )
    assert server_latency_totals(text) == {"score": (0.008, 4.0), "upload": (0.005, 1.0)}


def test_locustfile_runs_the_same_cycle_headless(url, tmp_path):
    """tools/loadtest/locustfile.py with Locust (optional extra ``locust``): every request type
    is sent and none fails."""
    import csv
    import importlib.util
    import subprocess
    import sys
    from pathlib import Path

    if importlib.util.find_spec("locust") is None:  # not imported here: gevent would patch this process
        pytest.skip("locust not installed (pip install 'vgq-cnn[locust]')")
    root = Path(__file__).resolve().parent.parent
    prefix = tmp_path / "run"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "locust",
            "-f",
            str(root / "tools" / "loadtest" / "locustfile.py"),
            "--host",
            url,
            "--headless",
            "--users",
            "2",
            "--spawn-rate",
            "2",
            "--run-time",
            "3s",
            "--csv",
            str(prefix),
            "--only-summary",
        ],
        cwd=root,
        env={**os.environ, "VGQ_LOADTEST_K": "16", "VGQ_LOADTEST_MIX": "upload=1,score=2,once=1"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    rows = {row["Name"]: row for row in csv.DictReader(open(f"{prefix}_stats.csv"))}
    assert {"upload", "score", "score_once"} <= set(rows), r.stderr[-2000:]
    assert all(
        int(rows[n]["Request Count"]) > 0 and int(rows[n]["Failure Count"]) == 0
        for n in ("upload", "score", "score_once")
    )


def test_sweep_measures_each_setting_and_plots(model_dir, tmp_path):
    from tools.loadtest.sweep import main as sweep_main

    png = tmp_path / "sweep.png"
    points = sweep_main(
        [
            "--clients",
            "1,2",
            "--workers",
            "1",
            "--threads",
            "1",
            "--duration",
            "1.5",
            "--k",
            "16",
            "--mix",
            "upload=1,score=1,once=1",
            "--model-dir",
            str(model_dir),
            "--plot",
            str(png),
            "--json",
            str(tmp_path / "s.json"),
        ]
    )
    assert [(p["workers"], p["threads"], p["clients"]) for p in points] == [(1, 1, 1), (1, 1, 2)]
    assert all(p["errors"] == 0 and p["endpoints"]["score_once"]["requests"] > 0 for p in points)
    assert png.read_bytes()[:4] == b"\x89PNG" and json.loads((tmp_path / "s.json").read_text())[1]["clients"] == 2


def test_overhead_benchmark_measures_every_row_against_a_real_service(model_dir):
    """tools.loadtest.overhead: in-process model and route steps, and a real service over HTTP,
    in one interleaved run; every row measured, the ratios computed from them."""
    from tools.loadtest.overhead import main as overhead_main
    from tools.loadtest.overhead import process_cpu_seconds

    assert process_cpu_seconds(os.getpid()) > 0
    rep = overhead_main(["--model-dir", str(model_dir), "--k", "16", "--rounds", "2", "--calls", "3"])
    rows = {
        "model encoder + head",
        "model head",
        "steps one-shot",
        "steps cached score",
        "this: HTTP one-shot",
        "this: HTTP cached score",
        "HTTP floor: one-shot",
        "HTTP floor: cached score",
    }
    assert set(rep["median_ms"]) == rows and all(v > 0 for v in rep["median_ms"].values())
    # in-process rows: this thread's CPU clock; HTTP rows: the service process's schedstat, which the
    # kernel brings up to date at the thread's next context switch, so a call of tens of
    # microseconds (the floor app) can read 0 when its answer arrives first (seen on a Zen 5)
    cpu = rep["cpu_mean_ms"]
    assert all(v > 0 for k, v in cpu.items() if not k.startswith(("this:", "HTTP floor"))) and min(cpu.values()) >= 0
    assert rep["service_model_mean_ms"]["this"]["head"] > 0  # read from the service's /metrics
    r = rep["services"]["this"]
    assert (
        r["one_shot_over_model"] == rep["median_ms"]["this: HTTP one-shot"] / rep["median_ms"]["model encoder + head"]
    )
    assert rep["floor"]["cached_minus_head_ms"] == rep["median_ms"]["HTTP floor: cached score"]


def test_wrk_driver_reads_its_summary_line_and_refuses_bad_settings():
    from tools.loadtest import wrk

    out = 'Running 2s test\nVGQ_WRK {"requests": 10, "duration_us": 2000000, "connect": 0, "read": 1, "write": 0, '
    out += '"status": 2, "timeout": 0, "p50_us": 1500, "p90_us": 2000, "p99_us": 3000, "p999_us": 3100, '
    out += '"max_us": 3200, "mean_us": 1600.0}\n'
    rep = wrk.report(wrk.parse_summary(out), k=128)
    assert rep["errors"] == 3 and rep["req_per_s"] == 5.0 and rep["grasps_per_s"] == 8 * 128 // 2
    assert rep["p99_ms"] == 3.0
    with pytest.raises(ValueError, match="no summary"):
        wrk.parse_summary("Running 2s test\nunable to connect\n")
    with pytest.raises(SystemExit) as e:
        wrk.main(["--connections", "0"])
    assert e.value.code == 2


def test_breakdown_times_every_step_in_each_tree_and_compares_their_answers(model_dir, capsys):
    """tools.loadtest.breakdown: every step of the cached score call timed (CPU us) in each
    source tree's own process, trees in turn, and their binary answers compared."""
    from tools.loadtest.breakdown import main as breakdown_main
    from tools.loadtest.workload import ROOT

    here = str(ROOT)
    rep = breakdown_main(
        ["--model-dir", str(model_dir), "--k", "16", "--number", "2", "--repeat", "1", "--rounds", "1"]
        + ["--service", f"a={here}", "--service", f"b={here}"]
    )
    assert rep["answers_identical"] and set(rep["us"]) == {"a", "b"}
    steps = rep["us"]["a"]
    assert "ASGI app without the head" in steps and all(v > 0 for v in steps.values())
    assert steps["score_cached without the head"] < steps["score_cached (route steps)"]
    assert "| Service.place |" in capsys.readouterr().out


def test_overhead_rows_run_a_placement_head_with_its_rows():
    """A model whose head reads placement rows (the bundle, since 2026-12-07) gets them in the
    in-process model rows, as the service appends them."""
    from tools.loadtest.overhead import in_process_calls
    from vgq.model_card import ModelCard

    assert ModelCard.load("models/fast-vgqcnn-default").head_pose_width == 14
    tasks = in_process_calls("models/fast-vgqcnn-default", 1, 16)
    for name in ("model encoder + head", "model head", "steps one-shot", "steps cached score"):
        t = tasks[name]
        t.fn(t.prepare()) if t.prepare else t.fn()
