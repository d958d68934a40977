"""The demonstration type: a human (and its objects) posed over time, its checks and our ``.npz``.

World frame z-up, metres, quaternions wxyz. Human "parts" are the 22 SMPL-X body joints
(``retarget.inputs.human.PART_NAMES``); each part carries a rigid piece of the mannequin-x surface
expressed in that part's frame, so posing the surface at frame t is
``part_quat_w[t, k] ⊗ vertices_k + part_pos_w[t, k]``. The readers of capture formats build
on it: ``retarget.inputs.readers`` (AMASS, OMOMO, the dispatch) and ``retarget.inputs.bvh`` (BVH).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import NoReturn

import numpy as np

from otr_gym.io import NpzError, load_npz, save_npz
from otr_gym.rotations import quat_to_matrix
from retarget.inputs.human_surface import HumanSurface

#: Largest accepted deviation of a stored quaternion's norm from 1.
QUAT_UNIT_TOL = 1e-3
FORMAT_TAG = "otr-demonstration-v1"


class InvalidDemonstrationError(ValueError):
    """A demonstration file or array set that cannot be used; the message names the file and problem."""


class DemonstrationFileNotFoundError(InvalidDemonstrationError, FileNotFoundError):
    """A demonstration file, or a file it needs (object mesh), does not exist."""


@dataclass
class DemoObject:
    """A rigid object of the demonstration: its mesh (object frame, m) and world track."""

    name: str
    vertices: np.ndarray  # (V, 3) object frame
    faces: np.ndarray  # (F, 3)
    pos_w: np.ndarray  # (T, 3)
    quat_w: np.ndarray  # (T, 4) wxyz
    mesh_path: str | None = None  # file the mesh came from, when any
    static: bool = False  # True for furniture that never moves (tables)

    def posed_vertices(self, frames=slice(None)) -> np.ndarray:
        """World mesh vertices (T', V, 3) at ``frames``."""
        rot = quat_to_matrix(self.quat_w[frames])
        return np.einsum("...ij,vj->...vi", rot, self.vertices) + self.pos_w[frames][..., None, :]


@dataclass
class Demonstration:
    """A demonstration at its captured rate (``fps``) in a z-up world.

    ``part_pos_w``/``part_quat_w`` give the world pose of each human part frame (the SMPL-X
    joint frame: origin at the joint, axes of the SMPL-X body in its rest pose, i.e. y-up,
    z-forward, x-left of the subject when the part rotation is identity relative to a z-up
    world rotated by the root). ``shape`` holds the mannequin-x shape coefficients (10,).
    ``annotations`` holds per-frame labels of the source (leading axis T), e.g. OMOMO's
    ``object_contact`` flags.
    """

    name: str
    fps: float
    part_names: tuple[str, ...]
    part_parents: tuple[int, ...]
    part_pos_w: np.ndarray  # (T, P, 3)
    part_quat_w: np.ndarray  # (T, P, 4) wxyz
    surface: HumanSurface
    shape: np.ndarray  # (10,) mannequin-x shape coefficients
    stature_m: float
    objects: list[DemoObject] = field(default_factory=list)
    source: dict = field(default_factory=dict)  # format, path, subject, gender, …
    annotations: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.part_pos_w.shape[0])

    @property
    def duration_s(self) -> float:
        return (self.num_frames - 1) / self.fps

    def human_vertices_w(self, frames=slice(None)) -> np.ndarray:
        """Posed human surface (T', V, 3) at ``frames`` from the stored surface alone (no body model)."""
        return self.surface.posed_vertices(self.part_pos_w[frames], self.part_quat_w[frames])

    def object(self, name: str) -> DemoObject:
        for o in self.objects:
            if o.name == name:
                return o
        raise KeyError(f"demonstration {self.name!r} has no object {name!r} (has {[o.name for o in self.objects]})")

    # ------------------------------------------------------------ checks and IO

    def validate(self, origin: str | None = None) -> None:
        """Raise InvalidDemonstrationError naming ``origin`` (default: the name) on any inconsistency."""
        _validate(self, origin or self.name)

    def save(self, path: str | Path) -> Path:
        """Validate, then write our ``.npz`` atomically (temporary file in the same folder + rename)."""
        self.validate()
        swapped = [o.name for o in self.objects if getattr(o, "demonstrated_mesh", None) is not None]
        if swapped:  # the file would claim the substitute was captured (retarget.solver.substitute)
            raise InvalidDemonstrationError(f"{path}: objects {swapped} of {self.name!r} are substitutes; save the "
                                            "captured demonstration and substitute after loading it")
        return save_npz(path, _to_arrays(self))

    @classmethod
    def load(cls, path: str | Path) -> Demonstration:
        """Load and validate our ``.npz``; any problem raises InvalidDemonstrationError naming the file."""
        path = Path(path)
        if not path.is_file():
            raise DemonstrationFileNotFoundError(f"{path}: no such demonstration file")
        return from_arrays(read_npz(path), str(path))


# ------------------------------------------------------------------ validation


def scaled_object_positions(pos_w: np.ndarray, sc: float) -> np.ndarray:
    """An object's world positions (T, 3) in a scene scaled by ``sc`` whose objects keep their
    size (OmniRetarget's convention, measured on its sub3_largebox_003 file: x, y × sc; height
    z₀ + sc (z − z₀) about the first frame's), so that a box resting on the floor stays on it
    instead of sinking by (1 − sc) of its half height."""
    out = np.asarray(pos_w, dtype=float) * sc
    out[:, 2] = pos_w[0, 2] + sc * (pos_w[:, 2] - pos_w[0, 2])
    return out


def fail(origin: str, problem: str) -> NoReturn:
    raise InvalidDemonstrationError(f"{origin}: {problem}")


def check_finite(origin: str, key: str, arr: np.ndarray) -> None:
    if not np.isfinite(arr).all():
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(arr))[0])
        fail(origin, f"{key} contains NaN/inf (first at index {bad})")


def check_unit(origin: str, key: str, q: np.ndarray) -> None:
    err = np.abs(np.linalg.norm(q, axis=-1) - 1.0)
    if err.size and err.max() > QUAT_UNIT_TOL:
        idx = tuple(int(i) for i in np.unravel_index(np.argmax(err), err.shape))
        fail(origin, f"{key} is not unit-norm (|q| = {1 + err[idx]:.4f} at index {idx})")


def check_shape(origin: str, key: str, arr: np.ndarray, shape: tuple) -> None:
    """``shape`` may hold None for a free axis."""
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape, strict=True)):
        expected = "(" + ", ".join("·" if s is None else str(s) for s in shape) + ")"
        fail(origin, f"{key} must have shape {expected}, got {arr.shape}")


def _validate(demo: Demonstration, origin: str) -> None:
    if not np.isfinite(demo.fps) or demo.fps <= 0:
        fail(origin, f"fps must be a positive number, got {demo.fps}")
    parts = len(demo.part_names)
    if len(demo.part_parents) != parts or len(demo.surface.vertices) != parts or len(demo.surface.faces) != parts:
        fail(origin, f"{parts} part names but {len(demo.part_parents)} parents and "
                      f"{len(demo.surface.vertices)}/{len(demo.surface.faces)} surface pieces")
    if tuple(demo.surface.part_names) != tuple(demo.part_names):
        fail(origin, "surface part names differ from the demonstration's part names")
    check_shape(origin, "part_pos_w", demo.part_pos_w, (None, parts, 3))
    frames = demo.part_pos_w.shape[0]
    if frames < 1:
        fail(origin, "no frames")
    check_shape(origin, "part_quat_w", demo.part_quat_w, (frames, parts, 4))
    check_shape(origin, "shape", demo.shape, (10,))
    for key in ("part_pos_w", "part_quat_w", "shape"):
        check_finite(origin, key, getattr(demo, key))
    check_unit(origin, "part_quat_w", demo.part_quat_w)
    if not np.isfinite(demo.stature_m) or not 0.5 < demo.stature_m < 2.5:
        fail(origin, f"stature_m = {demo.stature_m} m is not a human stature (0.5 … 2.5 m)")
    for k, (v, f) in enumerate(zip(demo.surface.vertices, demo.surface.faces, strict=True)):
        check_shape(origin, f"surface vertices of part {demo.part_names[k]}", v, (None, 3))
        check_shape(origin, f"surface faces of part {demo.part_names[k]}", f, (None, 3))
        check_finite(origin, f"surface vertices of part {demo.part_names[k]}", v)
        if len(f) and (f.min() < 0 or f.max() >= len(v)):
            fail(origin, f"surface faces of part {demo.part_names[k]} index outside its {len(v)} vertices")
    for o in demo.objects:
        key = f"object {o.name!r}"
        check_shape(origin, f"{key} vertices", o.vertices, (None, 3))
        check_shape(origin, f"{key} faces", o.faces, (None, 3))
        if len(o.vertices) < 4 or len(o.faces) < 4:
            fail(origin, f"{key} mesh has {len(o.vertices)} vertices and {len(o.faces)} faces (needs ≥ 4 each)")
        if o.faces.min() < 0 or o.faces.max() >= len(o.vertices):
            fail(origin, f"{key} faces index outside its {len(o.vertices)} vertices")
        check_shape(origin, f"{key} pos_w", o.pos_w, (frames, 3))
        check_shape(origin, f"{key} quat_w", o.quat_w, (frames, 4))
        for name in ("vertices", "pos_w", "quat_w"):
            check_finite(origin, f"{key} {name}", getattr(o, name))
        check_unit(origin, f"{key} quat_w", o.quat_w)
    for key, value in demo.annotations.items():
        if np.ndim(value) < 1 or len(value) != frames:
            fail(origin, f"annotation {key!r} must have {frames} frames on its first axis, "
                          f"got shape {np.shape(value)}")


# ------------------------------------------------------------------ our .npz format


def _to_arrays(demo: Demonstration) -> dict[str, np.ndarray]:
    out = {
        "format": np.array(FORMAT_TAG),
        "name": np.array(demo.name),
        "fps": np.array(float(demo.fps)),
        "part_names": np.array(demo.part_names),
        "part_parents": np.array(demo.part_parents, dtype=np.int64),
        "part_pos_w": demo.part_pos_w,
        "part_quat_w": demo.part_quat_w,
        "shape": demo.shape,
        "stature_m": np.array(float(demo.stature_m)),
        "surface_vertex_counts": np.array([len(v) for v in demo.surface.vertices], dtype=np.int64),
        "surface_face_counts": np.array([len(f) for f in demo.surface.faces], dtype=np.int64),
        "surface_vertices": np.concatenate(demo.surface.vertices),
        "surface_faces": np.concatenate(demo.surface.faces).astype(np.int64),
        "source_json": np.array(json.dumps(demo.source, sort_keys=True)),
        "object_names": np.array([o.name for o in demo.objects], dtype=str),
        "object_static": np.array([o.static for o in demo.objects], dtype=bool),
        "object_mesh_paths": np.array([o.mesh_path or "" for o in demo.objects], dtype=str),
        "annotation_names": np.array(sorted(demo.annotations), dtype=str),
    }
    for i, o in enumerate(demo.objects):
        out.update({f"object{i}_vertices": o.vertices, f"object{i}_faces": np.asarray(o.faces, np.int64),
                    f"object{i}_pos_w": o.pos_w, f"object{i}_quat_w": o.quat_w})
    for key, value in demo.annotations.items():
        out[f"annotation_{key}"] = np.asarray(value)
    return out


_REQUIRED_KEYS = ("format", "name", "fps", "part_names", "part_parents", "part_pos_w", "part_quat_w", "shape",
                  "stature_m", "surface_vertex_counts", "surface_face_counts", "surface_vertices", "surface_faces",
                  "source_json", "object_names", "object_static", "object_mesh_paths", "annotation_names")


def read_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of an .npz demonstration (``otr_gym.io.load_npz``: nothing unpickled)."""
    try:
        return load_npz(path)
    except (NpzError, OSError) as exc:  # the message names the file and the problem
        raise InvalidDemonstrationError(str(exc)) from exc


def _split(origin: str, flat: np.ndarray, counts: np.ndarray, key: str) -> list[np.ndarray]:
    if counts.ndim != 1 or (counts < 0).any() or counts.sum() != len(flat):
        fail(origin, f"{key} counts {counts.tolist()} do not add up to its {len(flat)} rows")
    return np.split(flat, np.cumsum(counts)[:-1])


def from_arrays(data: dict[str, np.ndarray], origin: str) -> Demonstration:
    missing = [k for k in _REQUIRED_KEYS if k not in data]
    if missing:
        fail(origin, f"missing keys {missing}")
    if str(data["format"]) != FORMAT_TAG:
        fail(origin, f"format tag {str(data['format'])!r} is not {FORMAT_TAG!r}")
    if np.size(data["fps"]) != 1 or np.size(data["stature_m"]) != 1:
        fail(origin, "fps and stature_m must be single numbers")
    try:
        source = json.loads(str(data["source_json"]))
    except json.JSONDecodeError as exc:
        raise InvalidDemonstrationError(f"{origin}: source_json is not valid JSON ({exc})") from exc
    names = tuple(str(n) for n in data["part_names"])
    surface = HumanSurface(
        part_names=names,
        vertices=_split(origin, np.asarray(data["surface_vertices"], np.float64), data["surface_vertex_counts"],
                        "surface_vertices"),
        faces=_split(origin, np.asarray(data["surface_faces"], np.int64), data["surface_face_counts"],
                     "surface_faces"),
    )
    objects = []
    object_names = [str(n) for n in data["object_names"]]
    if not len(data["object_static"]) == len(data["object_mesh_paths"]) == len(object_names):
        fail(origin, "object_names, object_static and object_mesh_paths differ in length")
    for i, name in enumerate(object_names):
        keys = [f"object{i}_{k}" for k in ("vertices", "faces", "pos_w", "quat_w")]
        absent = [k for k in keys if k not in data]
        if absent:
            fail(origin, f"object {name!r}: missing keys {absent}")
        mesh_path = str(data["object_mesh_paths"][i])
        objects.append(DemoObject(
            name=name, vertices=np.asarray(data[keys[0]], np.float64), faces=np.asarray(data[keys[1]], np.int64),
            pos_w=np.asarray(data[keys[2]], np.float64), quat_w=np.asarray(data[keys[3]], np.float64),
            mesh_path=mesh_path or None, static=bool(data["object_static"][i])))
    annotations = {}
    for key in (str(n) for n in data["annotation_names"]):
        if f"annotation_{key}" not in data:
            fail(origin, f"annotation {key!r} listed but its array is missing")
        annotations[key] = data[f"annotation_{key}"]
    demo = Demonstration(
        name=str(data["name"]), fps=float(data["fps"]), part_names=names,
        part_parents=tuple(int(p) for p in data["part_parents"]),
        part_pos_w=np.asarray(data["part_pos_w"], np.float64), part_quat_w=np.asarray(data["part_quat_w"], np.float64),
        surface=surface, shape=np.asarray(data["shape"], np.float64), stature_m=float(data["stature_m"]),
        objects=objects, source=source, annotations=annotations)
    demo.validate(origin)
    return demo


def ground_shift(surface: HumanSurface, part_pos_w: np.ndarray, part_quat_w: np.ndarray) -> float:
    """Vertical shift (m) that puts the median over frames of the lowest surface point on z = 0."""
    return -float(np.median(surface.lowest_z(part_pos_w, part_quat_w)))
