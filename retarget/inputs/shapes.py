"""Substitute object shapes: the paper's eight primitives (Sec. IV-D, Table IV), user meshes, resizing.

A shape is first built in its **canonical frame**: centred on its bounding box, z up, x along
its longer horizontal side. :func:`place_in_object_frame` then puts it in the demonstrated
object's frame, so that one track (the demonstrated object poses) carries either object:

* canonical z goes to the demonstrated object's axis that points most steadily up in the world
  over the demonstration (the OMOMO large box's is its −z), so a drum stands as the box stood;
* canonical x goes to the longer of the two remaining axes (the box's 0.47 m side), so the
  board's 0.38 m side and the beam's 0.46 m length lie where the box was longest;
* the shape's centre goes to the centre of the demonstrated object's bounding box.

Dimensions (m) are the paper's; the torus tube and the capsule caps are ours (see
``LIBRARY``). Sizes are resized uniformly (×s) or per canonical axis (×sx, ×sy, ×sz) about the
centre; ``original`` is the demonstrated object itself (resizing it is the paper's Fig. 5
sweep). A user mesh (.obj/.stl/.ply) is read in z-up convention and placed the same way, or,
with ``keep_frame``, taken as already expressed in the demonstrated object's frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from retarget.inputs.meshes import (
    InvalidMeshError,
    TriMesh,
    as_trimesh,
    load_mesh,
    object_mesh,
)

#: File types accepted for user meshes.
MESH_SUFFIXES = (".obj", ".stl", ".ply")
#: The name of the demonstrated object itself in shape lists.
ORIGINAL = "original"


class UnknownShapeError(ValueError):
    """A shape name that is neither in the library nor a mesh file; the message lists the choices."""


@dataclass(frozen=True)
class LibraryShape:
    """A primitive of the library: its label in tables and a builder of its canonical mesh."""

    label: str
    build: Callable[[], trimesh.Trimesh]


def _ellipsoid(dx: float, dy: float, dz: float) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    mesh.apply_scale([dx / 2, dy / 2, dz / 2])
    return mesh


#: The paper's substitutes (Table IV), canonical frame, z up. Our choices where the paper gives
#: one figure: the capsule's 0.36 m is its overall length (caps included); the torus' ∅0.36 is
#: its outer diameter, with a 0.12 m tube (a ring a person carries by its rim), axis up.
LIBRARY: dict[str, LibraryShape] = {
    "ball": LibraryShape("ball ∅0.34", lambda: trimesh.creation.icosphere(subdivisions=4, radius=0.17)),
    "drum": LibraryShape("drum ∅0.34×0.36", lambda: trimesh.creation.cylinder(radius=0.17, height=0.36, sections=96)),
    "capsule": LibraryShape("capsule ∅0.23×0.36",
                            lambda: trimesh.creation.capsule(height=0.36 - 0.23, radius=0.115, count=[64, 32])),
    "rugby": LibraryShape("rugby ball 0.43×0.31×0.28", lambda: _ellipsoid(0.43, 0.31, 0.28)),
    "torus": LibraryShape("torus ∅0.36",
                          lambda: trimesh.creation.torus(major_radius=0.12, minor_radius=0.06, major_sections=96,
                                                         minor_sections=32)),
    "cube": LibraryShape("cube 0.26", lambda: trimesh.creation.box(extents=(0.26, 0.26, 0.26))),
    "board": LibraryShape("board 0.38×0.30×0.12", lambda: trimesh.creation.box(extents=(0.38, 0.30, 0.12))),
    "beam": LibraryShape("beam 0.46×0.19×0.19", lambda: trimesh.creation.box(extents=(0.46, 0.19, 0.19))),
}

#: Every name a shape list may hold (besides mesh files).
SHAPE_NAMES = (ORIGINAL, *LIBRARY)


@dataclass(frozen=True)
class ShapeSpec:
    """One substitute: a library name, ``original`` or a mesh file, and its size factors.

    ``scale`` is (sx, sy, sz) along the canonical axes (x: longer horizontal side, z: up).
    """

    shape: str
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    keep_frame: bool = False  # user meshes only: already in the demonstrated object's frame

    def __post_init__(self) -> None:
        check_shape_name(self.shape)
        scale = tuple(float(s) for s in np.broadcast_to(np.asarray(self.scale, np.float64), (3,)))
        bad = [s for s in scale if not (np.isfinite(s) and s > 0)]
        if bad:
            raise ValueError(f"shape '{self.shape}': scale factors must be finite and > 0, got {self.scale}")
        object.__setattr__(self, "scale", scale)

    @property
    def is_file(self) -> bool:
        return is_mesh_file(self.shape)

    @property
    def is_native(self) -> bool:
        """The captured object at its own size: nothing is substituted."""
        return self.shape == ORIGINAL and self.scale == (1.0, 1.0, 1.0)

    @property
    def uniform(self) -> float | None:
        """The uniform factor, or None when the axes differ."""
        return self.scale[0] if self.scale[0] == self.scale[1] == self.scale[2] else None

    @property
    def name(self) -> str:
        """File-name-safe identifier, e.g. ``ball_x1.00``, ``original_x0.70``, ``beam_x1.00x1.00x1.50``."""
        base = Path(self.shape).stem if self.is_file else self.shape
        base = "".join(c if c.isalnum() or c in "-_" else "_" for c in base)
        return f"{base}_x{_scale_text(self)}"

    def label(self, original: str = "box") -> str:
        """Row label of the tables: 'ball ∅0.34', 'box ×1.3', 'beam 0.46×0.19×0.19 ×1.0×1.0×1.5'."""
        if self.shape == ORIGINAL:
            base = original
        elif self.is_file:
            base = Path(self.shape).name
        else:
            base = LIBRARY[self.shape].label
        return base if self.scale == (1.0, 1.0, 1.0) and self.shape != ORIGINAL else f"{base} ×{_scale_text(self, '×')}"


def _scale_text(spec: ShapeSpec, sep: str = "x") -> str:
    """File names keep two decimals (``1.30``); labels drop trailing zeros (``1.3``, ``1.0``)."""
    def fmt(v: float) -> str:
        text = f"{v:.2f}"
        return text if sep == "x" else text.rstrip("0").removesuffix(".") + (".0" if text.endswith(".00") else "")

    u = spec.uniform
    return fmt(u) if u is not None else sep.join(fmt(s) for s in spec.scale)


def is_mesh_file(shape: str) -> bool:
    return Path(shape).suffix.lower() in MESH_SUFFIXES


def check_shape_name(shape: str) -> None:
    """Raise UnknownShapeError unless ``shape`` is a library name, ``original`` or a mesh file name."""
    if shape in SHAPE_NAMES or is_mesh_file(shape):
        return
    raise UnknownShapeError(f"unknown shape '{shape}': choose from {', '.join(SHAPE_NAMES)} "
                            f"or give a mesh file ({'/'.join(MESH_SUFFIXES)})")


def canonical_mesh(shape: str) -> TriMesh:
    """The library primitive ``shape`` in its canonical frame (m); user meshes via :func:`load_shape_mesh`."""
    check_shape_name(shape)
    if shape not in LIBRARY:
        raise UnknownShapeError(f"'{shape}' is not a library primitive (those are {', '.join(LIBRARY)})")
    mesh = LIBRARY[shape].build()
    return as_trimesh(mesh.vertices - mesh.bounds.mean(axis=0), mesh.faces, shape)


def load_shape_mesh(path: str | Path) -> TriMesh:
    """A user mesh file (InvalidMeshError naming the file when it cannot be read); a surface that
    encloses no volume is a shell (``retarget.inputs.meshes.object_mesh``, with a warning)."""
    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InvalidMeshError(f"{path}: substitute meshes must be {'/'.join(MESH_SUFFIXES)} files")
    mesh = load_mesh(path)
    return object_mesh(mesh.vertices, mesh.faces, mesh.name)


# ------------------------------------------------------------------ frames


def up_axis(quat_w: np.ndarray) -> np.ndarray:
    """Signed unit axis (3,) of the object frame that points most steadily up in the world
    over a track of orientations (T, 4) wxyz: the median of each axis' world z decides."""
    from otr_gym.rotations import quat_to_matrix

    z_of_axes = np.median(quat_to_matrix(np.asarray(quat_w, np.float64).reshape(-1, 4))[:, 2, :], axis=0)
    k = int(np.argmax(np.abs(z_of_axes)))
    axis = np.zeros(3)
    axis[k] = 1.0 if z_of_axes[k] >= 0 else -1.0
    return axis


def canonical_to_object(object_mesh: TriMesh, quat_w: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) from a shape's canonical frame to the demonstrated object's frame
    (columns: where canonical x, y, z go), see the module docstring."""
    z = up_axis(quat_w)
    extent = np.ptp(object_mesh.vertices, axis=0)
    horizontal = [k for k in range(3) if z[k] == 0.0]
    x = np.zeros(3)
    x[max(horizontal, key=lambda k: extent[k])] = 1.0
    return np.column_stack([x, np.cross(z, x), z])


def place_in_object_frame(canonical: TriMesh, object_mesh: TriMesh, quat_w: np.ndarray,
                          scale=(1.0, 1.0, 1.0), name: str | None = None) -> TriMesh:
    """A canonical-frame mesh resized by ``scale`` (canonical axes) about its bounding-box
    centre, turned into the demonstrated object's frame and centred on that object's box."""
    rot = canonical_to_object(object_mesh, quat_w)
    centre = canonical.bounds.mean(axis=0)
    local = (canonical.vertices - centre) * np.asarray(scale, np.float64)
    return as_trimesh(local @ rot.T + object_mesh.bounds.mean(axis=0), canonical.faces, name or canonical.name)


def resize_in_object_frame(mesh: TriMesh, object_mesh: TriMesh, quat_w: np.ndarray, scale=(1.0, 1.0, 1.0),
                           name: str | None = None) -> TriMesh:
    """``mesh`` (already in the demonstrated object's frame) resized about its bounding-box
    centre by ``scale`` given along the canonical axes (x: longer horizontal side, z: up)."""
    if tuple(scale) == (1.0, 1.0, 1.0):
        return as_trimesh(mesh.vertices, mesh.faces, name or mesh.name)  # bit for bit: the captured object itself
    rot = canonical_to_object(object_mesh, quat_w)
    centre = mesh.bounds.mean(axis=0)
    stretch = rot @ np.diag(np.asarray(scale, np.float64)) @ rot.T
    return as_trimesh((mesh.vertices - centre) @ stretch.T + centre, mesh.faces, name or mesh.name)


def substitute_mesh(spec: ShapeSpec, object_mesh: TriMesh, quat_w: np.ndarray) -> TriMesh:
    """The mesh of ``spec`` in the demonstrated object's frame (m), given that object's mesh and
    world orientations (T, 4) wxyz. Unknown names raise UnknownShapeError, unreadable meshes
    InvalidMeshError, both naming the shape."""
    name = spec.name
    if spec.shape == ORIGINAL:
        return resize_in_object_frame(object_mesh, object_mesh, quat_w, spec.scale, name)
    if spec.is_file:
        mesh = load_shape_mesh(spec.shape)
        if spec.keep_frame:
            return resize_in_object_frame(mesh, object_mesh, quat_w, spec.scale, name)
        return place_in_object_frame(mesh, object_mesh, quat_w, spec.scale, name)
    return place_in_object_frame(canonical_mesh(spec.shape), object_mesh, quat_w, spec.scale, name)


# ------------------------------------------------------------------ parsing (CLI)


def parse_scales(text: str) -> list[tuple[float, float, float]]:
    """Scales from ``START:STOP:STEP`` (inclusive, uniform), comma-separated values, and
    per-axis ``SXxSYxSZ`` items, e.g. ``0.7:1.6:0.1``, ``1,1.2``, ``1x1x1.5``. Every factor must
    be > 0 (ValueError naming the item)."""
    out: list[tuple[float, float, float]] = []
    for item in (s.strip() for s in text.split(",")):
        if item:
            out += _parse_scale_item(item)
    if not out:
        raise ValueError(f"no scale in '{text}'")
    return out


def _parse_scale_item(item: str) -> list[tuple[float, float, float]]:
    try:
        if ":" in item:
            start, stop, step = (float(v) for v in item.split(":"))
            if not step > 0:
                raise ValueError("the step must be > 0")
            n = int(np.floor((stop - start) / step + 1e-9)) + 1
            scales = [(v, v, v) for v in (round(start + k * step, 10) for k in range(max(n, 0)))]
            if not scales:
                raise ValueError("the range is empty")
        elif "x" in item.lower():
            axes = tuple(float(v) for v in item.lower().split("x"))
            if len(axes) != 3:
                raise ValueError("a per-axis scale needs three factors SXxSYxSZ")
            scales = [axes]
        else:
            scales = [(float(item),) * 3]
    except ValueError as exc:
        raise ValueError(f"scale '{item}': {exc}") from None
    if any(not (np.isfinite(s) and s > 0) for t in scales for s in t):
        raise ValueError(f"scale '{item}': every factor must be > 0")
    return scales


def parse_shapes(text: str) -> list[str]:
    """Comma-separated shape names and mesh files; unknown names raise UnknownShapeError."""
    shapes = [s.strip() for s in text.split(",") if s.strip()]
    if not shapes:
        raise UnknownShapeError(f"no shape in '{text}' (choose from {', '.join(SHAPE_NAMES)} or mesh files)")
    for s in shapes:
        check_shape_name(s)
    return shapes
