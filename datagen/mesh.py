"""Object meshes: find sources, load and repair them, rescale, and compute stable poses.

Units: metres after :func:`load_object`. The object frame has its origin at the centre of
mass and keeps the orientation of the source file. World frame of a stable pose: table
surface z = 0, z up.

Repairs (each one is recorded in :attr:`GraspableObject.repairs`): non-finite vertices or an
empty mesh are not repairable (:class:`MeshError`); degenerate and duplicate faces are
dropped; every connected body that is open gets its holes filled, and becomes its convex
hull when that is not enough; bodies are then merged into one solid (boolean union, so
overlaps leave no inner walls) or only the largest is kept (``MeshParams.fragments``).
"""

from __future__ import annotations

import os
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

MESH_SUFFIXES = (".obj", ".stl", ".ply")
SOURCE_SUFFIXES = MESH_SUFFIXES + (".urdf",)


class MeshError(Exception):
    """An unusable mesh; the message names the file and the reason."""


@dataclass(frozen=True)
class MeshSource:
    """One object to load: ``path`` is a mesh file (or a URDF when its scale is not uniform),
    ``scale`` the URDF ``<mesh scale>`` (1 for plain mesh files).

    A procedural object (:mod:`datagen.families`) has ``family`` and ``params`` set: its
    mesh is built from them (``path`` only names it, ``family:<name>``) and keeps its
    physical size (no rescale)."""

    name: str
    path: Path
    scale: float = 1.0
    family: str | None = None
    params: dict | None = field(default=None, hash=False)


@dataclass(frozen=True)
class MeshParams:
    """How to prepare a mesh.

    rescale: ``"min_extent"`` scales the object so that its smallest principal extent
    (extent along the principal axes of inertia) is ``target_min_extent`` metres (Dex-Net);
    ``"keep"`` keeps the source units times the URDF scale (metres assumed).
    max_faces: meshes with more faces are simplified when a simplifier is available
    (``fast_simplification``) and the result stays watertight; otherwise they are kept.
    fragments: ``"merge"`` unites all connected bodies into one rigid object (as pybullet
    does with a multi-body mesh); ``"largest"`` keeps the body with the largest volume.
    min_fragment_fraction: bodies with less than this fraction of the largest body's volume
    are dropped before merging (dust, slivers).
    """

    rescale: str = "min_extent"
    target_min_extent: float = 0.04
    max_faces: int = 5000
    fragments: str = "merge"
    min_fragment_fraction: float = 0.0

    def __post_init__(self) -> None:
        if self.rescale not in ("min_extent", "keep"):
            raise ValueError(f"MeshParams.rescale must be 'min_extent' or 'keep', got {self.rescale!r}")
        if self.fragments not in ("merge", "largest"):
            raise ValueError(f"MeshParams.fragments must be 'merge' or 'largest', got {self.fragments!r}")
        if not (np.isfinite(self.target_min_extent) and self.target_min_extent > 0):
            raise ValueError(f"MeshParams.target_min_extent must be > 0 metres, got {self.target_min_extent}")
        if self.max_faces < 4:
            raise ValueError(f"MeshParams.max_faces must be >= 4, got {self.max_faces}")
        if not (0.0 <= self.min_fragment_fraction < 1.0):
            raise ValueError(f"MeshParams.min_fragment_fraction must be in [0, 1), got {self.min_fragment_fraction}")


@dataclass
class GraspableObject:
    """A prepared object: ``mesh`` in the object frame (centre of mass at the origin,
    metres, watertight). ``scale`` is the factor applied to the file's coordinates;
    ``repairs`` lists what was changed."""

    name: str
    source: str
    mesh: trimesh.Trimesh
    scale: float = 1.0
    repairs: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------- sources


def default_source_dir() -> Path:
    """pybullet_data's ``random_urdfs`` folder (1000 objects, URDF scale 0.015)."""
    try:
        import pybullet_data
    except ImportError as e:  # pragma: no cover - pybullet is a datagen dependency
        raise FileNotFoundError("no mesh source given and pybullet_data is not installed (pip install pybullet)") from e
    return Path(pybullet_data.getDataPath()) / "random_urdfs"


def mesh_sources(source: str | Path | None = None) -> list[MeshSource]:
    """List the objects of ``source``, sorted by name.

    ``source``: None (pybullet_data random_urdfs), a folder searched recursively for
    .obj/.stl/.ply/.urdf files (meshes referenced by a URDF in the folder are listed only
    through that URDF), or a single such file. Raises FileNotFoundError for a missing path
    and ValueError for a folder without meshes or a file of another type.
    """
    root = default_source_dir() if source is None else Path(source).expanduser()
    if not root.exists():
        raise FileNotFoundError(f"mesh source {str(root)!r} does not exist")
    if root.is_file():
        if root.suffix.lower() not in SOURCE_SUFFIXES:
            raise ValueError(f"mesh source {str(root)!r} is not a {'/'.join(SOURCE_SUFFIXES)} file")
        files = [root]
        base = root.parent
    else:
        files = sorted(p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in SOURCE_SUFFIXES)
        base = root
        if not files:
            raise ValueError(f"mesh source folder {str(root)!r} holds no {'/'.join(SOURCE_SUFFIXES)} files")

    urdf_sources: list[tuple[Path, Path, float]] = []  # (urdf, path to load, scale)
    referenced: set[Path] = set()
    for f in files:
        if f.suffix.lower() == ".urdf":
            try:
                mesh_path, scale = parse_urdf(f)
            except MeshError:
                mesh_path, scale = f, 1.0  # load_object reports the problem for this one object
            else:
                referenced.add(mesh_path.resolve())
                if not np.allclose(scale, scale[0], rtol=1e-9, atol=0.0):
                    mesh_path, scale = f, np.ones(3)  # non-uniform: load_object re-reads the URDF
            urdf_sources.append((f, mesh_path, float(np.asarray(scale).reshape(-1)[0])))
    entries = [(f, f, 1.0) for f in files if f.suffix.lower() in MESH_SUFFIXES and f.resolve() not in referenced]
    entries += urdf_sources

    names = [_name(f, base, stem_only=True) for f, _, _ in entries]
    dup = {n for n in names if names.count(n) > 1}
    out = [
        MeshSource(name=_name(f, base, stem_only=n not in dup), path=p, scale=s) for (f, p, s), n in zip(entries, names)
    ]
    out.sort(key=lambda s: s.name)
    return out


def _name(f: Path, base: Path, stem_only: bool) -> str:
    if stem_only:
        return f.stem
    rel = f.relative_to(base).with_suffix("")
    return "__".join(rel.parts)


def parse_urdf(urdf: str | Path) -> tuple[Path, np.ndarray]:
    """(mesh file, scale (3,)) of the first collision mesh of a URDF (visual if none).

    ``package://`` prefixes are dropped; relative names resolve against the URDF's folder.
    Raises MeshError when the URDF cannot be read or names no existing mesh file.
    """
    urdf = Path(urdf)
    try:
        tree = ET.parse(urdf)
    except (ET.ParseError, OSError) as e:
        raise MeshError(f"{urdf}: cannot parse URDF ({e})") from e
    root = tree.getroot()
    meshes = root.findall(".//collision/geometry/mesh") or root.findall(".//visual/geometry/mesh")
    if not meshes:
        raise MeshError(f"{urdf}: URDF has no <mesh> geometry")
    el = meshes[0]
    fname = el.get("filename")
    if not fname:
        raise MeshError(f"{urdf}: <mesh> has no filename")
    for prefix in ("package://", "file://"):
        if fname.startswith(prefix):
            fname = fname[len(prefix) :]
    candidates = [Path(fname)] if os.path.isabs(fname) else []
    candidates += [urdf.parent / fname, urdf.parent / Path(fname).name]
    mesh_path = next((c for c in candidates if c.is_file()), None)
    if mesh_path is None:
        raise MeshError(f"{urdf}: mesh file {fname!r} not found")
    scale_txt = el.get("scale", "1 1 1")
    try:
        scale = np.array([float(x) for x in scale_txt.split()], dtype=np.float64)
    except ValueError as e:
        raise MeshError(f"{urdf}: bad <mesh scale> {scale_txt!r}") from e
    if scale.size == 1:
        scale = np.repeat(scale, 3)
    if scale.size != 3 or not np.all(np.isfinite(scale)) or np.any(scale == 0):
        raise MeshError(f"{urdf}: bad <mesh scale> {scale_txt!r}")
    return mesh_path, scale


# --------------------------------------------------------------------------- loading


def load_object(src: MeshSource, params: MeshParams = MeshParams()) -> GraspableObject:
    """Load (or build, for a procedural ``src.family``), repair, rescale and centre one
    object; procedural objects keep their physical size. Raises MeshError naming the file
    and the reason when the mesh cannot be used (unreadable, empty, non-finite vertices,
    no volume, bad family parameters)."""
    path = Path(src.path)
    scale = np.full(3, float(src.scale))
    if src.family is None and path.suffix.lower() == ".urdf":
        mesh_path, urdf_scale = parse_urdf(path)
        scale = scale * urdf_scale
    else:
        mesh_path = path
    if not (np.all(np.isfinite(scale)) and np.all(scale != 0)):
        raise MeshError(f"{path}: bad scale {src.scale}")
    if src.family is not None:
        loaded = _family_mesh(src)
    elif not mesh_path.is_file():
        raise MeshError(f"{mesh_path}: file not found")
    else:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                loaded = trimesh.load(str(mesh_path), force="mesh", process=False)
        except Exception as e:  # trimesh raises many exception types for bad files
            raise MeshError(f"{mesh_path}: cannot read mesh ({type(e).__name__}: {e})") from e
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0 or len(loaded.vertices) == 0:
        raise MeshError(f"{mesh_path}: empty mesh (no faces)")
    verts = np.asarray(loaded.vertices, dtype=np.float64)
    bad = ~np.isfinite(verts).all(axis=1)
    if bad.any():
        raise MeshError(f"{mesh_path}: {int(bad.sum())} of {len(verts)} vertices are not finite (NaN/inf)")

    repairs: list[str] = []
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")
            mesh = trimesh.Trimesh(vertices=verts * scale, faces=np.asarray(loaded.faces), process=False)
            mesh = _repair(mesh, params, repairs)
            total_scale = float(np.mean(np.abs(scale)))
            if params.rescale == "min_extent" and src.family is None:  # procedural objects keep their size
                factor = params.target_min_extent / principal_extents(mesh).min()
                mesh.apply_scale(factor)
                total_scale *= factor
            mesh.apply_translation(-mesh.center_mass)
    except MeshError as e:
        raise MeshError(f"{mesh_path}: {e}") from None
    except Exception as e:  # a library failure deep inside repair: still one clean error
        raise MeshError(f"{mesh_path}: repair failed ({type(e).__name__}: {e})") from e
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(f"{mesh_path}: non-finite vertices after repair")
    return GraspableObject(name=src.name, source=str(path), mesh=mesh, scale=total_scale, repairs=repairs)


def _family_mesh(src: MeshSource) -> trimesh.Trimesh:
    """The procedural mesh of ``src`` (metres); MeshError naming it for bad parameters."""
    from .families import FamilyError, build_mesh

    try:
        return build_mesh(src.family, src.params if src.params is not None else {})
    except FamilyError as e:
        raise MeshError(f"{src.path}: {e}") from None


def principal_extents(mesh: trimesh.Trimesh) -> np.ndarray:
    """Extents (3,) of the mesh along its principal axes of inertia, ascending (metres)."""
    axes = mesh.principal_inertia_vectors
    proj = (mesh.vertices - mesh.center_mass) @ np.asarray(axes).T
    return np.sort(np.ptp(proj, axis=0))


def _clean(mesh: trimesh.Trimesh, repairs: list[str]) -> trimesh.Trimesh:
    n0 = len(mesh.faces)
    mesh.merge_vertices()
    mesh.update_faces(mesh.nondegenerate_faces(height=1e-12))
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) < n0:
        repairs.append(f"dropped {n0 - len(mesh.faces)} degenerate/duplicate faces")
    if len(mesh.faces) == 0:
        raise MeshError("no non-degenerate faces")
    return mesh


def _min_volume(mesh: trimesh.Trimesh) -> float:
    return 1e-9 * float(np.max(mesh.extents)) ** 3


def _repair_body(body: trimesh.Trimesh, repairs: list[str], i: int) -> trimesh.Trimesh | None:
    """A watertight, outward-facing version of one connected body, or None if flat."""
    if not body.is_watertight:
        trimesh.repair.fill_holes(body)
        if body.is_watertight:
            repairs.append(f"body {i}: filled holes")
    if body.is_watertight:
        trimesh.repair.fix_normals(body)
        if body.volume < 0:
            body.invert()
        body = _fresh(body)
    if not body.is_watertight or not body.is_winding_consistent:
        try:
            hull = body.convex_hull
        except Exception:  # qhull fails on flat / collinear bodies
            return None
        repairs.append(f"body {i}: not watertight, replaced by its convex hull")
        body = hull
    if not body.is_volume or body.volume <= _min_volume(body):
        return None
    return body


def _repair(mesh: trimesh.Trimesh, params: MeshParams, repairs: list[str]) -> trimesh.Trimesh:
    mesh = _clean(mesh, repairs)
    bodies = mesh.split(only_watertight=False, repair=False)
    fixed = []
    for i, b in enumerate(bodies):
        r = _repair_body(b, repairs, i)
        if r is None:
            repairs.append(f"body {i}: dropped (flat, no volume)")
        else:
            fixed.append(r)
    if not fixed:
        raise MeshError("no body with a volume (flat or degenerate mesh)")
    vols = np.array([b.volume for b in fixed])
    if params.min_fragment_fraction > 0:
        keep = vols >= params.min_fragment_fraction * vols.max()
        if not keep.all():
            repairs.append(f"dropped {int((~keep).sum())} small fragments")
            fixed = [b for b, k in zip(fixed, keep) if k]
            vols = vols[keep]

    if len(fixed) == 1:
        out = fixed[0]
    else:
        try:
            out = trimesh.boolean.union(fixed, engine="manifold")
            repairs.append(f"merged {len(fixed)} bodies (union)")
        except Exception as e:  # manifold3d missing or failed: keep the shells as they are
            out = trimesh.util.concatenate(fixed)
            repairs.append(f"merged {len(fixed)} bodies by concatenation (union failed: {e})")
    if params.fragments == "largest":
        parts = out.split(only_watertight=False, repair=False)
        if len(parts) > 1:
            out = max(parts, key=lambda p: p.volume)
            repairs.append(f"kept the largest of {len(parts)} bodies")

    if not out.is_watertight or not out.is_winding_consistent or out.volume <= 0:
        try:
            out = mesh.convex_hull
        except Exception as e:
            raise MeshError(f"not repairable ({e})") from e
        repairs.append("merged mesh not watertight, replaced by the convex hull of the whole mesh")
    if out.volume <= _min_volume(out):
        raise MeshError("no volume (flat mesh)")

    if len(out.faces) > params.max_faces:
        out = _simplify(out, params.max_faces, repairs)
    return _fresh(out)


def _fresh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """A copy with no cached values: trimesh keeps stale face normals after in-place
    winding fixes (fix_normals / invert), and the samplers read face normals."""
    return trimesh.Trimesh(
        vertices=np.array(mesh.vertices, dtype=np.float64), faces=np.array(mesh.faces, dtype=np.int64), process=False
    )


def _simplify(mesh: trimesh.Trimesh, max_faces: int, repairs: list[str]) -> trimesh.Trimesh:
    try:
        small = mesh.simplify_quadric_decimation(face_count=max_faces)
    except Exception:  # fast_simplification not installed or it failed: keep the mesh
        repairs.append(f"kept {len(mesh.faces)} faces (> max_faces {max_faces}; no simplifier)")
        return mesh
    if small.is_watertight and small.volume > 0:
        repairs.append(f"simplified {len(mesh.faces)} -> {len(small.faces)} faces")
        return small
    repairs.append(f"kept {len(mesh.faces)} faces (simplified mesh was not watertight)")
    return mesh


# --------------------------------------------------------------------------- stable poses


def stable_poses(
    obj: GraspableObject, min_probability: float = 0.01, max_poses: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Stable resting poses of ``obj`` on the table (trimesh's quasi-static estimate).

    Returns ``(T_world_object (n, 4, 4), probability (n,))`` sorted by probability
    (descending), keeping poses with probability >= ``min_probability`` and at most
    ``max_poses``. Each pose rests the object on z = 0 (lowest vertex at z = 0) with its
    centre of mass above the world origin (x = y = 0). Raises ValueError for bad arguments
    and MeshError when the mesh has no stable poses to compute (degenerate hull).
    """
    if not (0.0 <= min_probability <= 1.0):
        raise ValueError(f"min_probability must be in [0, 1], got {min_probability}")
    if max_poses is not None and max_poses < 1:
        raise ValueError(f"max_poses must be >= 1 or None, got {max_poses}")
    mesh = obj.mesh
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")
            T, p = trimesh.poses.compute_stable_poses(
                mesh, center_mass=np.zeros(3), sigma=0.0, n_samples=1, threshold=0.0
            )
    except Exception as e:  # qhull / graph failures on degenerate hulls
        raise MeshError(f"{obj.source}: stable poses failed ({type(e).__name__}: {e})") from e
    T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    p = np.asarray(p, dtype=np.float64).reshape(-1)
    keep = np.isfinite(p) & (p >= min_probability)
    T, p = T[keep], p[keep]
    order = np.argsort(-p, kind="stable")
    if max_poses is not None:
        order = order[:max_poses]
    T, p = T[order].copy(), p[order].copy()
    hull = mesh.convex_hull.vertices
    for k in range(len(T)):
        z = hull @ T[k, 2, :3]
        T[k, :2, 3] = 0.0  # centre of mass (object origin) above the world origin
        T[k, 2, 3] = -z.min()
    return T, p
