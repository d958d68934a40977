"""Unitree's original G1 meshes (the "true surface") and how far the shipped meshes are from them.

The shipped visual meshes (``otr_gym/assets/g1/meshes``) are decimations of the STL files in the
mjlab 1.6.0 wheel (``mjlab/asset_zoo/robots/unitree_g1/xmls/assets``), bounded in error by
``tools/build_g1_assets.py``. This module fetches the originals (``pip download`` of the wheel
into the cache, once), measures a shipped mesh against its original, and reads the per-link
error table written at build time (``assets/g1/mesh_error.json``), whose ``surface_error_mm``
is the margin that keeps contact and penetration checks conservative: every point of the
original surface lies within that distance of the shipped one.

The error measure of one link (all distances in mm, mesh files in their own frame):

* ``p99_mm`` / ``max_mm``: outer-surface samples of the original (points on its convex hull,
  snapped to the closest point of the original mesh, so interior geometry is ignored) against
  the shipped mesh — what a contact with the outside of the robot sees;
* ``surface_error_mm``: the largest distance from any original vertex, area sample or outer
  sample to the shipped mesh (interior included), the margin used by the solver and
  ``retarget.checks.verify``;
* ``hull_volume_change_pct``: convex-hull volume of the shipped mesh relative to the original;
* ``components``: pieces of at least 1 cm² in (original, shipped), vertices closer than 10 µm
  merged; a piece that falls apart raises the shipped count (twin walls a few µm apart that
  decimation fuses lower it, harmlessly).
"""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from otr_gym.robot import ASSETS_DIR

MJLAB_WHEEL = "mjlab==1.6.0"
WHEEL_PREFIX = "mjlab/asset_zoo/robots/unitree_g1/xmls/"
MESH_ERROR_JSON = ASSETS_DIR / "g1" / "mesh_error.json"
#: Original file stems that differ from our mesh names.
ORIGINAL_STEM = {"torso_link": "torso_link_rev_1_0", "waist_roll_link": "waist_roll_link_rev_1_0",
                 "waist_yaw_link": "waist_yaw_link_rev_1_0"}


class TrueSurfaceUnavailable(RuntimeError):
    """The mjlab wheel with Unitree's original meshes could not be found or downloaded."""


def cache_dir() -> Path:
    import os

    return Path(os.environ.get("OTR_CACHE_DIR", Path.home() / ".cache" / "otr-gym")) / "mjlab-g1"


def fetch_wheel(dest: Path) -> Path:
    """The mjlab wheel in ``dest`` (downloaded with pip, without dependencies, if absent)."""
    dest.mkdir(parents=True, exist_ok=True)
    found = sorted(dest.glob("mjlab-1.6.0-*.whl"))
    if found:
        return found[0]
    run = subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", MJLAB_WHEEL, "-d", str(dest)],
                         capture_output=True, text=True)
    found = sorted(dest.glob("mjlab-1.6.0-*.whl"))
    if run.returncode != 0 or not found:
        raise TrueSurfaceUnavailable(f"pip download {MJLAB_WHEEL} failed: {run.stderr.strip()[-400:]}")
    return found[0]


def read_wheel(wheel: Path) -> tuple[str, dict[str, bytes]]:
    """(g1.xml text, {original STL file name: bytes}) from the mjlab wheel."""
    try:
        with zipfile.ZipFile(wheel) as zf:
            xml_text = zf.read(WHEEL_PREFIX + "g1.xml").decode()
            meshes = {Path(n).name: zf.read(n) for n in zf.namelist()
                      if n.startswith(WHEEL_PREFIX + "assets/") and n.lower().endswith(".stl")}
    except (OSError, KeyError, zipfile.BadZipFile) as exc:
        raise TrueSurfaceUnavailable(f"{wheel}: not a usable mjlab wheel ({exc})") from exc
    return xml_text, meshes


@lru_cache(maxsize=1)
def original_mesh_dir() -> Path:
    """Folder of Unitree's original STL files, named like ours (``torso_link.stl``, …)."""
    out = cache_dir() / "original_meshes"
    marker = out / ".complete"
    if not marker.is_file():
        _, meshes = read_wheel(fetch_wheel(cache_dir()))
        out.mkdir(parents=True, exist_ok=True)
        names = {v: k for k, v in ORIGINAL_STEM.items()}
        for file, data in meshes.items():
            stem = Path(file).stem
            tmp = out / f".{stem}.tmp"
            tmp.write_bytes(data)
            tmp.replace(out / f"{names.get(stem, stem)}.stl")
        marker.write_text(MJLAB_WHEEL)
    return out


def use_original_meshes() -> Path:
    """Make this process's G1 models (and so ``otr_gym.robot_geometry``) load Unitree's original
    meshes instead of the shipped ones; call before any G1 model is loaded."""
    import os

    folder = original_mesh_dir()
    os.environ["OTR_G1_MESH_DIR"] = str(folder)
    return folder


@dataclass(frozen=True)
class MeshError:
    """How far a shipped mesh is from its original (mm, %, piece counts); see the module doc."""

    p99_mm: float
    max_mm: float
    surface_error_mm: float
    hull_volume_change_pct: float
    components: tuple[int, int]
    faces: tuple[int, int]


def _distance_mm(points: np.ndarray, mesh) -> np.ndarray:
    import igl

    d2, _, _ = igl.point_mesh_squared_distance(np.asarray(points, np.float64), np.asarray(mesh.vertices, np.float64),
                                               np.asarray(mesh.faces, np.int64))
    return np.sqrt(d2) * 1e3


def outer_surface_samples(original, count: int = 4000, seed: int = 0) -> np.ndarray:
    """Points of the original's outer surface: convex-hull samples snapped to the mesh."""
    import igl
    import trimesh

    hull = trimesh.sample.sample_surface(original.convex_hull, count, seed=seed)[0]
    _, _, outer = igl.point_mesh_squared_distance(hull, np.asarray(original.vertices, np.float64),
                                                  np.asarray(original.faces, np.int64))
    return outer


def surface_pieces(mesh, min_area_m2: float = 1e-4) -> int:
    """Connected pieces of at least ``min_area_m2`` once vertices closer than 10 µm are merged."""
    merged = mesh.copy()
    merged.merge_vertices(digits_vertex=5)
    return sum(1 for piece in merged.split(only_watertight=False) if piece.area >= min_area_m2)


def mesh_error(original, shipped, samples: int = 4000) -> MeshError:
    """Measure ``shipped`` (trimesh) against ``original`` (trimesh), same frame."""
    import trimesh

    outer = _distance_mm(outer_surface_samples(original, samples), shipped)
    area = trimesh.sample.sample_surface(original, samples, seed=1)[0]
    every = _distance_mm(np.concatenate([original.vertices, area]), shipped)
    pieces = (surface_pieces(original), surface_pieces(shipped))
    return MeshError(float(np.percentile(outer, 99)), float(outer.max()), float(max(every.max(), outer.max())),
                     float(100.0 * (shipped.convex_hull.volume / original.convex_hull.volume - 1.0)), pieces,
                     (len(original.faces), len(shipped.faces)))


def write_error_table(table: dict[str, MeshError], path: Path = MESH_ERROR_JSON) -> None:
    from otr_gym.io import write_json

    write_json(path, {"source": MJLAB_WHEEL, "links": {k: asdict(v) for k, v in sorted(table.items())}})


@lru_cache(maxsize=1)
def surface_error_m() -> dict[str, float]:
    """Mesh name -> largest distance (m) of the original surface from the shipped mesh, from
    ``mesh_error.json`` (written by ``tools/build_g1_assets.py``)."""
    try:
        links = json.loads(MESH_ERROR_JSON.read_text())["links"]
        return {k: float(v["surface_error_mm"]) * 1e-3 for k, v in links.items()}
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise RuntimeError(f"{MESH_ERROR_JSON}: unreadable mesh error table ({exc}); "
                           "regenerate it with tools/build_g1_assets.py") from exc
