"""Link geometry as triangle meshes: mesh files (STL/OBJ/DAE via trimesh), tessellated URDF
primitives, and decimation with fast-simplification cached on disk.

Cache entries live in ``$ROBOSEG_CACHE`` (default ``~/.cache/roboseg``) under ``decimated/``,
keyed by the mesh file's content hash (or the primitive's parameters) and the target reduction.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import unquote, urlparse

import fast_simplification
import numpy as np
import trimesh

from roboseg.errors import RobotModelError

from .urdf import Geometry

log = logging.getLogger(__name__)

CYLINDER_SECTIONS = 32  # segments around a cylinder
SPHERE_COUNT = (16, 32)  # latitude rings, longitude segments of a sphere
MIN_DECIMATED_FACES = 24  # decimation never goes below this many faces per shape
_CACHE_VERSION = "1"


@dataclass(frozen=True)
class MeshData:
    """A triangle mesh in its own coordinates; ``key`` identifies its source content."""

    vertices: np.ndarray  # [N, 3] float64
    faces: np.ndarray  # [M, 3] int64
    key: str


def default_cache_dir() -> Path:
    """``$ROBOSEG_CACHE`` or ``~/.cache/roboseg``."""
    env = os.environ.get("ROBOSEG_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "roboseg"


def _find_package(package: str, start: Path) -> Path | None:
    """Folder of ROS package ``package``: an ancestor of ``start`` with that name, a child of
    an ancestor with that name, or ``<prefix>/share/<package>`` of ``$ROS_PACKAGE_PATH`` /
    ``$AMENT_PREFIX_PATH`` entries."""
    for folder in (start, *start.parents):
        if folder.name == package:
            return folder
        if (folder / package).is_dir():
            return folder / package
    for var, sub in (("ROS_PACKAGE_PATH", ""), ("AMENT_PREFIX_PATH", "share")):
        for entry in filter(None, os.environ.get(var, "").split(os.pathsep)):
            candidate = Path(entry) / sub / package
            if candidate.is_dir():
                return candidate
    return None


def resolve_mesh_path(filename: str, urdf_path: Path, link: str) -> Path:
    """Resolve a ``<mesh filename>``: relative to the URDF, ``file://`` or ``package://``."""
    urdf_dir = urdf_path.resolve().parent
    if filename.startswith("package://"):
        rest = filename[len("package://") :]
        package, _, relative = rest.partition("/")
        root = _find_package(package, urdf_dir)
        if root is None:
            raise RobotModelError(
                f"{urdf_path}: link {link!r}: mesh {filename!r}: package {package!r} not found "
                f"in the folders above {urdf_dir} (nor $ROS_PACKAGE_PATH/$AMENT_PREFIX_PATH)"
            )
        path = root / unquote(relative)
    elif filename.startswith("file://"):
        parsed = urlparse(filename)
        path = Path(unquote(parsed.netloc + parsed.path))
    else:
        path = Path(filename)
    if not path.is_absolute():
        path = urdf_dir / path
    if not path.is_file():
        raise RobotModelError(f"{urdf_path}: link {link!r}: mesh file not found: {path}")
    return path


def load_mesh_file(path: Path) -> MeshData:
    """Triangles of a mesh file in file units (scenes, e.g. DAE, are merged with their node
    transforms); ``key`` is the SHA-256 of the file's bytes."""
    key = hashlib.sha256(path.read_bytes()).hexdigest()
    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as e:  # trimesh raises many types for unreadable files
        raise RobotModelError(f"mesh file {path} could not be read ({e})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise RobotModelError(f"mesh file {path} contains no triangles")
    return MeshData(
        np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64), key
    )


def primitive_mesh(geometry: Geometry) -> MeshData:
    """Tessellation of a URDF box / cylinder (axis z, centred) / sphere, in metres."""
    if geometry.kind == "box":
        mesh = trimesh.creation.box(extents=geometry.params)
    elif geometry.kind == "cylinder":
        radius, length = geometry.params
        mesh = trimesh.creation.cylinder(radius=radius, height=length, sections=CYLINDER_SECTIONS)
    elif geometry.kind == "sphere":
        mesh = trimesh.creation.uv_sphere(radius=geometry.params[0], count=list(SPHERE_COUNT))
    else:
        raise ValueError(f"not a primitive: {geometry.kind}")
    spec = f"{geometry.kind}{geometry.params}{CYLINDER_SECTIONS}{SPHERE_COUNT}"
    return MeshData(
        np.asarray(mesh.vertices, dtype=np.float64),
        np.asarray(mesh.faces, dtype=np.int64),
        hashlib.sha256(spec.encode()).hexdigest(),
    )


def geometry_mesh(geometry: Geometry, urdf_path: Path, link: str) -> tuple[MeshData, np.ndarray]:
    """Mesh of one shape in its own coordinates, and its per-axis scale [3]."""
    if geometry.kind == "mesh":
        path = resolve_mesh_path(geometry.filename or "", urdf_path, link)
        return load_mesh_file(path), np.asarray(geometry.params, dtype=np.float64)
    return primitive_mesh(geometry), np.ones(3)


def decimation_target(n_faces: int, reduction: float) -> int:
    """Faces to keep when removing the fraction ``reduction`` of ``n_faces`` (never fewer than
    :data:`MIN_DECIMATED_FACES`, never more than ``n_faces``)."""
    return min(n_faces, max(round(n_faces * (1.0 - reduction)), MIN_DECIMATED_FACES))


def _simplify(mesh: MeshData, target: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric decimation to about ``target`` faces, dropping vertices no face uses."""
    vertices, faces = fast_simplification.simplify(
        mesh.vertices, mesh.faces.astype(np.int32), target_count=target
    )
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return np.asarray(vertices[used], dtype=np.float64), remap[np.asarray(faces, dtype=np.int64)]


def decimate(mesh: MeshData, reduction: float, cache_dir: Path | None = None) -> MeshData:
    """Remove the fraction ``reduction`` of faces (paper: 0.95), reading/writing the disk cache.

    Shapes are never reduced below :data:`MIN_DECIMATED_FACES` faces.
    """
    if not 0.0 <= reduction < 1.0:
        raise RobotModelError(f"mesh reduction must be in [0, 1), got {reduction}")
    target = decimation_target(len(mesh.faces), reduction)
    if target >= len(mesh.faces):
        return mesh
    spec = f"{mesh.key}:{reduction:.6f}:{target}:{_CACHE_VERSION}"
    key = hashlib.sha256(spec.encode()).hexdigest()
    folder = (cache_dir or default_cache_dir()) / "decimated"
    entry = folder / f"{key}.npz"
    if entry.is_file():
        try:
            with np.load(entry) as data:
                log.debug("decimation cache hit %s", entry)
                return MeshData(data["vertices"], data["faces"], key)
        except (OSError, ValueError, KeyError):
            log.warning("ignoring unreadable cache entry %s", entry)
    vertices, faces = _simplify(mesh, target)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, suffix=".npz", delete=False) as tmp:
            np.savez(tmp, vertices=vertices, faces=faces)
        os.replace(tmp.name, entry)  # atomic: concurrent writers never expose half a file
    except OSError as e:
        log.warning("could not write decimation cache %s (%s)", entry, e)
    return MeshData(vertices, faces, key)
