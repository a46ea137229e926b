"""How much the sensor model moves the placement rows: the same grasps' rows from crops cut on the
sensor-corrupted images and on the clean renders (``datagen crops --sensor clean``, the recipe's
``crops_clean_test``), column by column and per family.

The two crop sets must hold the same rows (one ``datagen sample`` output, cut twice): checked by
the labels' and object ids' digest. Columns are in metres (``vgq.placement``); a row counts where
both sides know it (``known`` 1).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vgq.placement import PLACEMENT_COLUMNS

from .data import DatasetError, open_crop_dataset
from .metrics import sample_rows
from .teacher import rows_digest


def _column_stats(a: np.ndarray, b: np.ndarray) -> dict:
    if len(a) == 0:
        return {"median_abs_diff_m": float("nan"), "p90_abs_diff_m": float("nan"), "correlation": float("nan")}
    d = np.abs(a - b)
    corr = float(np.corrcoef(a, b)[0, 1]) if len(a) > 1 and a.std() > 0 and b.std() > 0 else float("nan")
    return {
        "median_abs_diff_m": float(np.median(d)),
        "p90_abs_diff_m": float(np.quantile(d, 0.9)),
        "correlation": corr,
    }


def compare(clean: str | Path, sensor: str | Path, split: str = "test", max_n: int = 200_000, seed: int = 0) -> dict:
    """Per column (clean vs sensor rows of the same grasps, both known) the median and 90th
    percentile absolute difference (metres) and the correlation; the share of rows each side knows;
    per family the same for ``offset``. ``max_n`` rows drawn at random (seed); 0: all."""
    c_ds, s_ds = open_crop_dataset(clean), open_crop_dataset(sensor)
    c, s = c_ds.split(split), s_ds.split(split)
    if len(c) != len(s) or rows_digest(c) != rows_digest(s):
        raise DatasetError(f"{clean} and {sensor} hold other {split!r} rows: cut both from the same sampled grasps")
    for ds, sp in ((clean, c), (sensor, s)):
        if "placement" not in sp.arrays:
            raise DatasetError(f"{ds}: split {split!r} has no placement rows (crop it again with this datagen)")
    n = len(c)
    rows = sample_rows(n, max_n, seed)  # the rows evaluate --max-n draws
    pc = np.asarray(c.arrays["placement"][rows], np.float64)
    ps = np.asarray(s.arrays["placement"][rows], np.float64)
    kc, ks = pc[:, 0] > 0.5, ps[:, 0] > 0.5
    both = kc & ks
    fams = s_ds.object_families()
    family = np.array([fams.get(int(o), "random_urdfs") for o in np.asarray(c.arrays["object_id"])[rows]])
    rec = {
        "split": split,
        "rows": int(len(rows)),
        "known_clean": float(kc.mean()),
        "known_sensor": float(ks.mean()),
        "known_both": float(both.mean()),
        "columns": {
            name: _column_stats(pc[both, i], ps[both, i]) for i, name in enumerate(PLACEMENT_COLUMNS) if name != "known"
        },
        "offset_by_family": {},
    }
    i = PLACEMENT_COLUMNS.index("offset")
    for f in sorted(set(family.tolist())):
        r = (family == f) & both
        rec["offset_by_family"][f] = {
            "known_clean": float(kc[family == f].mean()),
            "known_sensor": float(ks[family == f].mean()),
            **_column_stats(pc[r, i], ps[r, i]),
        }
    return rec


def table(rec: dict) -> str:
    """Markdown tables of :func:`compare`'s record (millimetres)."""
    lines = [
        f"{rec['rows']:,} {rec['split']} rows; known: clean {rec['known_clean']:.1%}, sensor {rec['known_sensor']:.1%}, "
        f"both {rec['known_both']:.1%}",
        "",
        "| column | median abs diff (mm) | 90th pct (mm) | correlation |",
        "|---|---:|---:|---:|",
    ]
    for name, s in rec["columns"].items():
        lines.append(
            f"| {name} | {1e3 * s['median_abs_diff_m']:.1f} | {1e3 * s['p90_abs_diff_m']:.1f} | {s['correlation']:.3f} |"
        )
    lines += [
        "",
        "| family | known clean | known sensor | offset median abs diff (mm) | 90th pct (mm) | correlation |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for f, s in rec["offset_by_family"].items():
        lines.append(
            f"| {f} | {s['known_clean']:.1%} | {s['known_sensor']:.1%} | {1e3 * s['median_abs_diff_m']:.1f} | "
            f"{1e3 * s['p90_abs_diff_m']:.1f} | {s['correlation']:.3f} |"
        )
    return "\n".join(lines)
