"""Contact sheets of family objects: each object in a likely stable pose, rendered
by datagen's embree depth renderer from an oblique camera, hill-shaded, laid out with
matplotlib (Agg, PNG)."""

from __future__ import annotations

import io
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LightSource  # noqa: E402

from vgq import atomic  # noqa: E402
from vgq.camera import DEFAULT_INTRINSICS  # noqa: E402

VIEW_PHI = math.radians(50.0)  # camera elevation from the table normal
VIEW_THETA = math.radians(35.0)  # camera azimuth


def view_depth(mesh) -> tuple[np.ndarray, np.ndarray]:
    """(depth (H, W) float32 metres, object mask (H, W) bool) of ``mesh`` (object frame,
    metres) resting in a stable pose (of those with probability >= 5 %, the most upright:
    cups and bottles stand), seen from the oblique sheet camera at a distance that makes
    the object fill about half of the image."""
    from ..camera import look_at_table_origin
    from ..mesh import GraspableObject, stable_poses
    from ..render import render_depth

    m = mesh.copy()
    m.apply_translation(-m.center_mass)
    T, p = stable_poses(GraspableObject("view", "view", m), 0.0)
    likely = p >= min(0.05, p[0])
    up = np.where(likely, T[:, 2, 2], -np.inf)  # world z of the object's z axis: upright cups, bottles, mugs
    m.apply_transform(T[int(np.argmax(up))])
    m.apply_translation([0.0, 0.0, -0.5 * m.bounds[1, 2]])  # look at the object's middle, not its base
    radius = float(np.linalg.norm(m.extents)) / 2
    intr = DEFAULT_INTRINSICS
    d = max(0.15, 1.4 * radius * intr.fx / (0.5 * intr.width))
    T_wc = look_at_table_origin(d, VIEW_PHI, VIEW_THETA)[0]
    obj = render_depth(m, T_wc, intr, table=False)
    table = render_depth(None, _shift_table(T_wc, m.bounds[0, 2]), intr)  # the table under the object's base
    depth = np.where(obj > 0, obj, table)
    return depth, obj > 0


def _shift_table(T_wc: np.ndarray, z: float) -> np.ndarray:
    """The camera pose that sees the plane z = ``z`` where the renderer's table (z = 0) is."""
    T = T_wc.copy()
    T[2, 3] -= z
    return T


def shaded(depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """RGB (H, W, 3) hill shade of a depth image, the object tinted, cropped to the object."""
    ls = LightSource(azdeg=315, altdeg=45)
    z = -depth.astype(np.float64)
    rgb = ls.shade(z, cmap=plt.get_cmap("bone"), vert_exag=2000.0, blend_mode="soft", vmin=z.min(), vmax=z.max())
    rgb = rgb[..., :3]
    rgb[mask] = 0.55 * rgb[mask] + 0.45 * np.array([0.95, 0.6, 0.2])
    v, u = np.nonzero(mask)
    if len(v) == 0:
        return rgb
    c, r = ((u.min() + u.max()) // 2, (v.min() + v.max()) // 2), int(0.6 * max(np.ptp(u), np.ptp(v))) + 4
    v0, v1 = max(c[1] - r, 0), min(c[1] + r, depth.shape[0])
    u0, u1 = max(c[0] - r, 0), min(c[0] + r, depth.shape[1])
    return rgb[v0:v1, u0:u1]


def _label(obj) -> str:
    e = np.sort(obj.mesh.extents)[::-1] * 100
    kind = obj.params.get("kind") or obj.params.get("shape") or ""
    return f"{obj.name} {kind}\n{e[0]:.1f} x {e[1]:.1f} x {e[2]:.1f} cm"


def contact_sheet(
    rows: list[tuple[str, list]], path: str | Path, title: str, cols: int | None = None, cache: dict | None = None
) -> Path:
    """Write a PNG with one row of rendered objects per ``(row label, [FamilyObject])``
    (``cols`` images per row at most; a single row wraps). ``cache``: a dict that keeps the
    rendered views by object name across calls. Returns the path."""
    cache = {} if cache is None else cache
    if len(rows) == 1 and cols:
        label, objs = rows[0]
        rows = [(label if i == 0 else "", objs[i : i + cols]) for i in range(0, len(objs), cols)]
    ncols = max(len(objs) for _, objs in rows)
    fig, axes = plt.subplots(len(rows), ncols, figsize=(1.9 * ncols, 2.0 * len(rows) + 0.4), squeeze=False)
    for r, (label, objs) in enumerate(rows):
        for c in range(ncols):
            ax = axes[r, c]
            ax.set_xticks([])
            ax.set_yticks([])
            for s in ax.spines.values():
                s.set_visible(False)
            if c < len(objs):
                if objs[c].name not in cache:
                    cache[objs[c].name] = shaded(*view_depth(objs[c].mesh))
                ax.imshow(cache[objs[c].name])
                ax.set_title(_label(objs[c]), fontsize=6.5)
            if c == 0 and label:
                ax.set_ylabel(label, fontsize=9, fontweight="bold")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.3 / fig.get_figheight()))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=72)
    plt.close(fig)
    path = Path(path)
    atomic.write_bytes(path, buf.getvalue())
    return path
