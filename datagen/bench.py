"""Throughput benchmark: labelled datapoints (grasp rows) per minute and the native
positivity rate of a small generation run on this machine."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Callable

from .config import DatagenConfig


def run_bench(config: DatagenConfig, workers: int = 1, out: str | Path | None = None, log: Callable[[str], None] = print) -> dict:
    """Generate ``config`` (use a small ``num_objects``) into ``out`` (a temporary folder when
    None) and report wall time, datapoints per minute and positivity."""
    from .pipeline import run_generate

    with tempfile.TemporaryDirectory(prefix="datagen-bench-") as tmp:
        root = Path(out) if out is not None else Path(tmp) / "ds"
        t0 = time.perf_counter()
        m = run_generate(root, config, workers=workers, progress=False, log=log)
        wall = time.perf_counter() - t0
    c = m["counts"]
    res = {
        "objects": c["objects"],
        "objects_done": c["objects_done"],
        "objects_skipped": c["objects_skipped"],
        "images": c["images"],
        "datapoints": c["grasps"],
        "positive": c["positive"],
        "positivity_rate": c["positivity_rate"],
        "collision_free_rate": c["collision_free"] / c["grasps"] if c["grasps"] else 0.0,
        "wall_s": wall,
        "datapoints_per_minute": 60.0 * c["grasps"] / wall if wall > 0 else 0.0,
        "workers": workers,
        "cameras_per_pose": config.cameras_per_pose,
    }
    log(
        f"bench: {res['objects_done']}/{res['objects']} objects ({res['objects_skipped']} skipped), "
        f"{res['images']} images, {res['datapoints']} labelled datapoints in {wall:.1f} s with {workers} worker(s)"
    )
    log(f"bench: {res['datapoints_per_minute']:.0f} datapoints/min")
    log(
        f"bench: native positivity rate {100 * res['positivity_rate']:.1f}% "
        f"(collision-free {100 * res['collision_free_rate']:.1f}%; VG-dset ~6%, Dex-Net 2.0 ~19%)"
    )
    for o in m["objects"]:
        if o.get("status") == "skipped":
            log(f"bench: skipped {o['name']}: {o.get('reason')}")
    return res
