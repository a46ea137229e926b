"""Draw planned grasps over a depth image (Pillow): the jaw line of each grasp (from jaw to
jaw, opened to the contacts plus a margin), its contacts and its rank."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from vgq.camera import Intrinsics, project

from .types import PlannedGrasp


def depth_to_rgb(depth: np.ndarray) -> Image.Image:
    """Grey image of ``depth`` (near = light), missing readings black."""
    d = np.asarray(depth, dtype=np.float64)
    ok = np.isfinite(d) & (d > 0)
    g = np.zeros(d.shape, np.uint8)
    if ok.any():
        lo, hi = np.percentile(d[ok], [1, 99])
        g[ok] = np.clip(255 - 200 * (d[ok] - lo) / max(hi - lo, 1e-6), 30, 255).astype(np.uint8)
    return Image.fromarray(g).convert("RGB")


def _colour(rank: int, n: int) -> tuple[int, int, int]:
    if rank == 0:
        return (40, 220, 60)
    t = rank / max(n - 1, 1)
    return (int(255 * t), int(200 * (1 - t)) + 40, 255 - int(200 * t))


def overlay(
    depth: np.ndarray,
    intr: Intrinsics,
    grasps: tuple[PlannedGrasp, ...] | list,
    scale: int | None = None,
    margin: float = 0.005,
    zoom_margin: int = 40,
    size: int = 600,
) -> Image.Image:
    """An RGB image with each grasp's jaw line, contacts, TCP and rank (1 = best) drawn
    over the depth image: the part of it around the grasps (``zoom_margin`` px beyond
    them; the whole image when there are none), enlarged by ``scale`` (default: to about
    ``size`` px)."""
    d = np.asarray(depth)
    h, w = d.shape
    u0, v0, u1, v1 = 0, 0, w, h
    if len(grasps):
        uv = project(np.concatenate([np.asarray(g.contacts, dtype=np.float64) for g in grasps]), intr)[:, :2]
        u0, v0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - zoom_margin, 0)
        u1, v1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + zoom_margin + 1, [w, h])
    d = d[v0:v1, u0:u1]
    intr = Intrinsics(fx=intr.fx, fy=intr.fy, cx=intr.cx - u0, cy=intr.cy - v0, width=u1 - u0, height=v1 - v0)
    if scale is None:
        scale = max(1, size // max(d.shape))
    img = depth_to_rgb(d)
    img = img.resize((img.width * scale, img.height * scale), Image.Resampling.NEAREST)
    draw = ImageDraw.Draw(img)
    n = len(grasps)
    for rank in range(n - 1, -1, -1):  # best drawn last, on top
        g = grasps[rank]
        c = np.asarray(g.contacts, dtype=np.float64)
        axis = c[1] - c[0]
        axis /= max(np.linalg.norm(axis), 1e-12)
        ends = np.array([c[0] - margin * axis, c[1] + margin * axis])
        uv = project(np.vstack([ends, c]), intr)[:, :2]
        uv = (uv + 0.5) * scale - 0.5
        col = _colour(rank, n)
        draw.line([tuple(uv[0]), tuple(uv[1])], fill=col, width=max(2, scale))
        for p in uv[2:]:
            draw.ellipse([p[0] - 2 * scale, p[1] - 2 * scale, p[0] + 2 * scale, p[1] + 2 * scale], outline=col, width=2)
        tcp = (project(np.asarray(g.pose)[None, :3, 3], intr)[0, :2] + 0.5) * scale - 0.5
        draw.text((tcp[0] + 3 * scale, tcp[1] - 6 * scale), f"{rank + 1}: {g.score:.2f}", fill=col)
    return img
