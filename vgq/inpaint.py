"""Missing depth: how a depth image with holes becomes a complete network input.

Real depth sensors return 0 ("no reading") at depth discontinuities, in the projector's
occlusion shadows and on dark or shiny spots. A pixel is *missing* when it is not a
reading by :func:`vgq.camera.valid_depth` (not finite, not > 0, or beyond 10 m). The network never saw a missing pixel in training, so every crop is
filled before it is resized. One definition, used by datagen's crop stage (training data)
and by the service (uploads), so training and serving see identical inputs.

The pipeline of one crop window (conventions of :mod:`vgq.crop`, source pixels):

1. take the window plus :data:`MARGIN_PX` pixels on each side
   (:func:`vgq.crop.crop_window`, edge-replicated where it leaves the image), so that a hole
   near the window border is filled from real neighbours outside the window;
2. fill every missing pixel with the depth of its nearest valid pixel (Euclidean distance,
   OpenCV's distance transform with per-pixel labels, 5 x 5 mask): :func:`fill_nearest`;
3. cut the window out of the filled patch;
4. resize it bilinearly to ``out`` x ``out`` (:func:`vgq.crop.resize`).

The missing fraction reported with a window counts step 1's missing pixels inside the window
(not the margin). ``python -m vgq.inpaint --bench`` times steps 1 to 3 per window.
"""

from __future__ import annotations

import argparse
import sys
import time

import cv2
import numpy as np

from .camera import valid_depth
from .crop import CropGeometry, crop_window, resize, window_center

MARGIN_PX = 12  # source px around the window that the fill may draw from


class NoValidDepth(ValueError):
    """A region to be filled holds no valid depth pixel (:func:`vgq.camera.valid_depth`)."""


def missing_mask(depth: np.ndarray) -> np.ndarray:
    """Boolean mask (same shape) of missing pixels: not :func:`vgq.camera.valid_depth`."""
    return ~valid_depth(depth)


def fill_nearest(depth: np.ndarray, missing: np.ndarray | None = None) -> np.ndarray:
    """``depth`` (H, W) metres as float32 with each missing pixel set to the depth of its
    nearest valid pixel (Euclidean, OpenCV 5 x 5 distance mask; ties broken by OpenCV).
    ``missing`` may pass a precomputed :func:`missing_mask`. Raises :class:`NoValidDepth`
    when no pixel is valid."""
    d = np.ascontiguousarray(depth, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"depth must be 2-D (H, W), got shape {d.shape}")
    miss = missing_mask(d) if missing is None else np.ascontiguousarray(missing, dtype=bool)
    if not miss.any():
        return d.copy()
    valid = ~miss
    if not valid.any():
        raise NoValidDepth(f"no valid depth pixel in the {d.shape[0]}x{d.shape[1]} region")
    # Each valid pixel (a zero of the source) gets its own label, 1, 2, ... in raster order
    # (OpenCV's DIST_LABEL_PIXEL; tests/test_vgq_inpaint.py holds it to the labels' own mapping);
    # every missing pixel gets the label of its nearest valid pixel. A label -> depth table
    # maps labels to depths: half the time of indexing the table by the labels of valid pixels.
    _, labels = cv2.distanceTransformWithLabels(
        miss.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5, labelType=cv2.DIST_LABEL_PIXEL
    )
    table = np.empty(int(np.count_nonzero(valid)) + 1, dtype=np.float32)
    table[0] = 0.0
    table[1:] = d[valid]
    return np.take(table, labels)


def filled_window(
    depth: np.ndarray, origin_uv, geom: CropGeometry, margin: int = MARGIN_PX
) -> tuple[np.ndarray, float]:
    """The ``window`` x ``window`` block of ``depth`` (H, W) metres at integer top-left
    ``origin_uv`` (u, v), with missing pixels filled from the window plus ``margin`` px.

    Returns (window float32, fraction of the window's pixels that were missing). Raises
    :class:`NoValidDepth` when the window and its margin hold no valid pixel."""
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    ou, ov = int(origin_uv[0]), int(origin_uv[1])
    big = CropGeometry(window=geom.window + 2 * margin, out=geom.window + 2 * margin, kappa_px=0)
    patch = crop_window(depth, (ou - margin, ov - margin), big)
    miss = missing_mask(patch)
    inner = (slice(margin, margin + geom.window), slice(margin, margin + geom.window))
    frac = float(miss[inner].mean())
    if frac == 0.0:
        return np.ascontiguousarray(patch[inner]), 0.0
    return np.ascontiguousarray(fill_nearest(patch, miss)[inner]), frac


def crop_filled(
    depth: np.ndarray, origin_uv, geom: CropGeometry, margin: int = MARGIN_PX
) -> tuple[np.ndarray, np.ndarray, float]:
    """The network input of the window at ``origin_uv``: :func:`filled_window`, then the
    bilinear resize of :mod:`vgq.crop`. Returns (image (out, out) float32 metres, window
    centre (2,) image px, missing fraction of the window)."""
    win, frac = filled_window(depth, origin_uv, geom, margin)
    return resize(win, geom.out), window_center(origin_uv, geom), frac


# --------------------------------------------------------------------------- benchmark


def _blob_holes(shape, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """A mask with discs of radius 2..6 px until ``fraction`` of the pixels are covered."""
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    m = np.zeros(shape, dtype=bool)
    while m.mean() < fraction:
        cv, cu, r = rng.integers(0, h), rng.integers(0, w), rng.integers(2, 7)
        m |= (yy - cv) ** 2 + (xx - cu) ** 2 <= r * r
    return m


def bench(reps: int = 500, fractions=(0.0, 0.02, 0.10, 0.50), margin: int = MARGIN_PX, seed: int = 0) -> list[dict]:
    """Milliseconds per window (median and p99 over ``reps``) of :func:`filled_window` on a
    300 x 300 table + box scene with ``fractions`` of the window missing (discs of 2..6 px),
    and of SciPy's exact nearest fill (``distance_transform_edt``) on the same patch when
    SciPy is installed, for comparison."""
    try:
        from scipy import ndimage
    except ImportError:  # the service install has no SciPy
        ndimage = None
    geom = CropGeometry()
    rng = np.random.default_rng(seed)
    depth = np.full((300, 300), 0.70, np.float32)
    depth[110:190, 120:180] = 0.64
    depth += (0.001 * rng.standard_normal(depth.shape)).astype(np.float32)
    origin = (102, 102)
    rows = []
    for frac in fractions:
        d = depth.copy()
        sl = (slice(origin[1], origin[1] + geom.window), slice(origin[0], origin[0] + geom.window))
        d[sl][_blob_holes((geom.window, geom.window), frac, rng)] = 0.0
        t = []
        for _ in range(reps):
            t0 = time.perf_counter()
            _, got = filled_window(d, origin, geom, margin)
            t.append(time.perf_counter() - t0)
        row = {"missing": got, "ms_median": 1e3 * float(np.median(t)), "ms_p99": 1e3 * float(np.percentile(t, 99))}
        if ndimage is not None:
            patch = crop_window(
                d,
                (origin[0] - margin, origin[1] - margin),
                CropGeometry(geom.window + 2 * margin, geom.window + 2 * margin, 0),
            )
            t = []
            for _ in range(reps):
                t0 = time.perf_counter()
                miss = missing_mask(patch)
                if miss.any():
                    idx = ndimage.distance_transform_edt(miss, return_distances=False, return_indices=True)
                    patch[idx[0], idx[1]]
                t.append(time.perf_counter() - t0)
            row["scipy_edt_ms_median"] = 1e3 * float(np.median(t))
        rows.append(row)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m vgq.inpaint", description="Time the missing-depth fill per crop window."
    )
    p.add_argument("--bench", action="store_true", help="run the benchmark (the only action)")
    p.add_argument("--reps", type=int, default=500)
    a = p.parse_args(argv)
    if not a.bench:
        p.print_help()
        return 0
    if a.reps < 1:
        print("vgq.inpaint: error: --reps must be >= 1", file=sys.stderr)
        return 2
    g = CropGeometry()
    print(
        f"fill per window: {g.window}x{g.window} window + {MARGIN_PX} px margin, OpenCV {cv2.__version__}, "
        f"{cv2.getNumThreads()} OpenCV threads, {a.reps} reps"
    )
    for r in bench(a.reps):
        extra = f"  (scipy EDT {r['scipy_edt_ms_median']:.3f} ms)" if "scipy_edt_ms_median" in r else ""
        print(f"missing {100 * r['missing']:5.1f}%: median {r['ms_median']:.3f} ms, p99 {r['ms_p99']:.3f} ms{extra}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
