"""Human (and human–object) demonstrations: one type, several readers.

World frame z-up, metres, quaternions wxyz. Human "parts" are the 22 SMPL-X body joints
(``retarget.human.PART_NAMES``); each part carries a rigid piece of the mannequin-x surface
expressed in that part's frame, so posing the surface at frame t is
``part_quat_w[t, k] ⊗ vertices_k + part_pos_w[t, k]``.

Readers (``load_demonstration`` dispatches on the file):

* our own ``.npz`` (``Demonstration.save``), validated on load;
* AMASS SMPL-X / SMPL-H parameter ``.npz`` (z-up already). AMASS ``trans`` follows MoSh++ / the
  ``smplx`` package: the root rotation turns the body about the pelvis joint, so the pelvis is
  at ``trans + J₀(β)``. SMPL-H files carry SMPL-H shape coefficients, which we read as the first
  ten SMPL-X coefficients (an approximation: the spaces differ, the leading components — size
  and girth — roughly agree);
* BVH skeletal motion capture (``retarget.bvh``: skeleton families, units, up axis, body fit);
* OMOMO in the InterMimic ``.pt`` layout (30 fps, z-up), with its object mesh. Part orientations
  come from the stored world body quaternions (right-multiplied by the fixed InterMimic -> SMPL-X
  frame change); the subject's shape is fitted to the stored joints.

Grounding (``ground=True``, the default): the body model is never the capture's own (mannequin-x
for SMPL-H, a refitted shape for OMOMO), so the human is shifted vertically until the median over
frames of its lowest surface point is z = 0 (this assumes the subject touches the floor in most
frames). Objects keep their track: they rest on the capture's floor. Measured shifts: OMOMO
sub3_largebox_003 floats 4.8 cm (its stored toe joints are 6–7 cm high), AMASS SMPL-H walk
sinks 8 cm, the SMPL-X squat 2 cm; ``source["ground_shift_m"]`` records it.
"""

from __future__ import annotations

import json
import pickle
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from otr_gym.io import save_npz
from otr_gym.rotations import quat_from_rotvec, quat_mul, quat_normalize, quat_to_matrix, xyzw_to_wxyz
from retarget.human_surface import HumanSurface
from retarget.meshes import InvalidMeshError, load_mesh

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
        if swapped:  # the file would claim the substitute was captured (retarget.substitute)
            raise InvalidDemonstrationError(f"{path}: objects {swapped} of {self.name!r} are substitutes; save the "
                                            "captured demonstration and substitute after loading it")
        return save_npz(path, _to_arrays(self))

    @classmethod
    def load(cls, path: str | Path) -> Demonstration:
        """Load and validate our ``.npz``; any problem raises InvalidDemonstrationError naming the file."""
        path = Path(path)
        if not path.is_file():
            raise DemonstrationFileNotFoundError(f"{path}: no such demonstration file")
        return _from_arrays(_read_npz(path), str(path))


# ------------------------------------------------------------------ validation


def scaled_object_positions(pos_w: np.ndarray, sc: float) -> np.ndarray:
    """An object's world positions (T, 3) in a scene scaled by ``sc`` whose objects keep their
    size (OmniRetarget's convention, measured on its sub3_largebox_003 file: x, y × sc; height
    z₀ + sc (z − z₀) about the first frame's), so that a box resting on the floor stays on it
    instead of sinking by (1 − sc) of its half height."""
    out = np.asarray(pos_w, dtype=float) * sc
    out[:, 2] = pos_w[0, 2] + sc * (pos_w[:, 2] - pos_w[0, 2])
    return out


def _fail(origin: str, problem: str):
    raise InvalidDemonstrationError(f"{origin}: {problem}")


def _check_finite(origin: str, key: str, arr: np.ndarray) -> None:
    if not np.isfinite(arr).all():
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(arr))[0])
        _fail(origin, f"{key} contains NaN/inf (first at index {bad})")


def _check_unit(origin: str, key: str, q: np.ndarray) -> None:
    err = np.abs(np.linalg.norm(q, axis=-1) - 1.0)
    if err.size and err.max() > QUAT_UNIT_TOL:
        idx = tuple(int(i) for i in np.unravel_index(np.argmax(err), err.shape))
        _fail(origin, f"{key} is not unit-norm (|q| = {1 + err[idx]:.4f} at index {idx})")


def _check_shape(origin: str, key: str, arr: np.ndarray, shape: tuple) -> None:
    """``shape`` may hold None for a free axis."""
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape, strict=True)):
        expected = "(" + ", ".join("·" if s is None else str(s) for s in shape) + ")"
        _fail(origin, f"{key} must have shape {expected}, got {arr.shape}")


def _validate(demo: Demonstration, origin: str) -> None:
    if not np.isfinite(demo.fps) or demo.fps <= 0:
        _fail(origin, f"fps must be a positive number, got {demo.fps}")
    parts = len(demo.part_names)
    if len(demo.part_parents) != parts or len(demo.surface.vertices) != parts or len(demo.surface.faces) != parts:
        _fail(origin, f"{parts} part names but {len(demo.part_parents)} parents and "
                      f"{len(demo.surface.vertices)}/{len(demo.surface.faces)} surface pieces")
    if tuple(demo.surface.part_names) != tuple(demo.part_names):
        _fail(origin, "surface part names differ from the demonstration's part names")
    _check_shape(origin, "part_pos_w", demo.part_pos_w, (None, parts, 3))
    frames = demo.part_pos_w.shape[0]
    if frames < 1:
        _fail(origin, "no frames")
    _check_shape(origin, "part_quat_w", demo.part_quat_w, (frames, parts, 4))
    _check_shape(origin, "shape", demo.shape, (10,))
    for key in ("part_pos_w", "part_quat_w", "shape"):
        _check_finite(origin, key, getattr(demo, key))
    _check_unit(origin, "part_quat_w", demo.part_quat_w)
    if not np.isfinite(demo.stature_m) or not 0.5 < demo.stature_m < 2.5:
        _fail(origin, f"stature_m = {demo.stature_m} m is not a human stature (0.5 … 2.5 m)")
    for k, (v, f) in enumerate(zip(demo.surface.vertices, demo.surface.faces, strict=True)):
        _check_shape(origin, f"surface vertices of part {demo.part_names[k]}", v, (None, 3))
        _check_shape(origin, f"surface faces of part {demo.part_names[k]}", f, (None, 3))
        _check_finite(origin, f"surface vertices of part {demo.part_names[k]}", v)
        if len(f) and (f.min() < 0 or f.max() >= len(v)):
            _fail(origin, f"surface faces of part {demo.part_names[k]} index outside its {len(v)} vertices")
    for o in demo.objects:
        key = f"object {o.name!r}"
        _check_shape(origin, f"{key} vertices", o.vertices, (None, 3))
        _check_shape(origin, f"{key} faces", o.faces, (None, 3))
        if len(o.vertices) < 4 or len(o.faces) < 4:
            _fail(origin, f"{key} mesh has {len(o.vertices)} vertices and {len(o.faces)} faces (needs ≥ 4 each)")
        if o.faces.min() < 0 or o.faces.max() >= len(o.vertices):
            _fail(origin, f"{key} faces index outside its {len(o.vertices)} vertices")
        _check_shape(origin, f"{key} pos_w", o.pos_w, (frames, 3))
        _check_shape(origin, f"{key} quat_w", o.quat_w, (frames, 4))
        for name in ("vertices", "pos_w", "quat_w"):
            _check_finite(origin, f"{key} {name}", getattr(o, name))
        _check_unit(origin, f"{key} quat_w", o.quat_w)
    for key, value in demo.annotations.items():
        if np.ndim(value) < 1 or len(value) != frames:
            _fail(origin, f"annotation {key!r} must have {frames} frames on its first axis, "
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


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        raise InvalidDemonstrationError(f"{path}: not a readable .npz file ({exc})") from exc


def _split(origin: str, flat: np.ndarray, counts: np.ndarray, key: str) -> list[np.ndarray]:
    if counts.ndim != 1 or (counts < 0).any() or counts.sum() != len(flat):
        _fail(origin, f"{key} counts {counts.tolist()} do not add up to its {len(flat)} rows")
    return np.split(flat, np.cumsum(counts)[:-1])


def _from_arrays(data: dict[str, np.ndarray], origin: str) -> Demonstration:
    missing = [k for k in _REQUIRED_KEYS if k not in data]
    if missing:
        _fail(origin, f"missing keys {missing}")
    if str(data["format"]) != FORMAT_TAG:
        _fail(origin, f"format tag {str(data['format'])!r} is not {FORMAT_TAG!r}")
    if np.size(data["fps"]) != 1 or np.size(data["stature_m"]) != 1:
        _fail(origin, "fps and stature_m must be single numbers")
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
        _fail(origin, "object_names, object_static and object_mesh_paths differ in length")
    for i, name in enumerate(object_names):
        keys = [f"object{i}_{k}" for k in ("vertices", "faces", "pos_w", "quat_w")]
        absent = [k for k in keys if k not in data]
        if absent:
            _fail(origin, f"object {name!r}: missing keys {absent}")
        mesh_path = str(data["object_mesh_paths"][i])
        objects.append(DemoObject(
            name=name, vertices=np.asarray(data[keys[0]], np.float64), faces=np.asarray(data[keys[1]], np.int64),
            pos_w=np.asarray(data[keys[2]], np.float64), quat_w=np.asarray(data[keys[3]], np.float64),
            mesh_path=mesh_path or None, static=bool(data["object_static"][i])))
    annotations = {}
    for key in (str(n) for n in data["annotation_names"]):
        if f"annotation_{key}" not in data:
            _fail(origin, f"annotation {key!r} listed but its array is missing")
        annotations[key] = data[f"annotation_{key}"]
    demo = Demonstration(
        name=str(data["name"]), fps=float(data["fps"]), part_names=names,
        part_parents=tuple(int(p) for p in data["part_parents"]),
        part_pos_w=np.asarray(data["part_pos_w"], np.float64), part_quat_w=np.asarray(data["part_quat_w"], np.float64),
        surface=surface, shape=np.asarray(data["shape"], np.float64), stature_m=float(data["stature_m"]),
        objects=objects, source=source, annotations=annotations)
    demo.validate(origin)
    return demo


# ------------------------------------------------------------------ dispatch


def load_demonstration(path: str | Path, object_mesh: str | Path | None = None, *,
                       ground: bool = True, bvh=None) -> Demonstration:
    """Read any supported demonstration file (see the module docstring) into a validated Demonstration.

    ``object_mesh`` overrides the mesh lookup of OMOMO clips; ``ground`` puts the human's feet on
    z = 0 (module docstring); ``bvh`` (``retarget.bvh.BvhOptions``) says how to read ``.bvh``
    files (skeleton map, units, up axis). Any problem raises InvalidDemonstrationError naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise DemonstrationFileNotFoundError(f"{path}: no such demonstration file")
    if path.suffix.lower() == ".bvh":
        from retarget.bvh import read_bvh

        demo = read_bvh(path, bvh, ground)
    elif path.suffix == ".pt":
        demo = _read_omomo(path, None if object_mesh is None else Path(object_mesh), ground)
    elif path.suffix == ".npz":
        data = _read_npz(path)
        if "format" in data and "part_pos_w" in data:
            demo = _from_arrays(data, str(path))
        elif "poses" in data or "pose_body" in data:
            demo = _read_amass(path, data, ground)
        else:
            _fail(str(path), f"unknown .npz layout (keys {sorted(data)}): neither our demonstration format "
                             "nor AMASS parameters (poses / root_orient+pose_body)")
    else:
        _fail(str(path), f"unknown demonstration format {path.suffix!r} (expected .npz, .pt or .bvh)")
    demo.validate(str(path))
    return demo


def _ground_shift(surface: HumanSurface, part_pos_w: np.ndarray, part_quat_w: np.ndarray) -> float:
    """Vertical shift (m) that puts the median over frames of the lowest surface point on z = 0."""
    return -float(np.median(surface.lowest_z(part_pos_w, part_quat_w)))


# ------------------------------------------------------------------ AMASS


def _first_key(origin: str, data: dict, keys: tuple[str, ...], what: str) -> np.ndarray:
    for key in keys:
        if key in data:
            return data[key]
    _fail(origin, f"missing {what} (one of keys {list(keys)})")


def _amass_rows(origin: str, data: dict) -> tuple[np.ndarray, np.ndarray, str]:
    """(root_orient (T, 3), pose_body (T, 21, 3), body model) from either AMASS key layout."""
    if "poses" in data:
        poses = np.asarray(data["poses"], np.float64)
        widths = {165: "smplx", 156: "smplh"}
        if poses.ndim != 2 or poses.shape[1] not in widths:
            _fail(origin, f"poses must be (T, 165) for SMPL-X or (T, 156) for SMPL-H, got {poses.shape}")
        return poses[:, :3], poses[:, 3:66].reshape(-1, 21, 3), widths[poses.shape[1]]
    if "root_orient" not in data:
        _fail(origin, "pose_body present but root_orient missing")
    root, body = np.asarray(data["root_orient"], np.float64), np.asarray(data["pose_body"], np.float64)
    _check_shape(origin, "root_orient", root, (None, 3))
    _check_shape(origin, "pose_body", body, (len(root), 63))
    model = str(data["surface_model_type"]) if "surface_model_type" in data else (
        "smplx" if "pose_jaw" in data else "smplh")
    return root, body.reshape(-1, 21, 3), model


#: The pelvis joint of SMPL's template (model frame, y-up, m): J₀ of the mean shape, which
#: SMPL-H shares. AMASS SMPL-H ``trans`` places this joint (plus its shape offset).
SMPL_TEMPLATE_PELVIS = np.array([-0.00179506, -0.22333345, 0.02821913])


def _read_amass(path: Path, data: dict, ground: bool) -> Demonstration:
    from retarget.human import PART_NAMES, PART_PARENTS, HumanModel  # human.py builds on the types above

    origin = str(path)
    root, body, body_model = _amass_rows(origin, data)
    frames = len(root)
    trans = np.asarray(_first_key(origin, data, ("trans",), "root translation"), np.float64)
    _check_shape(origin, "trans", trans, (frames, 3))
    betas = np.asarray(_first_key(origin, data, ("betas",), "shape coefficients"), np.float64).ravel()
    if betas.size < 10:
        _fail(origin, f"betas has {betas.size} values, needs at least 10")
    rate = np.asarray(_first_key(origin, data, ("mocap_frame_rate", "mocap_framerate"), "frame rate"), np.float64)
    if rate.size != 1 or not np.isfinite(rate).all() or rate.item() <= 0:
        _fail(origin, f"frame rate must be one positive number, got {rate.tolist()}")
    fps = rate.item()
    for key, arr in (("root orientation", root), ("body pose", body), ("trans", trans), ("betas", betas)):
        _check_finite(origin, key, arr)
    if frames < 1:
        _fail(origin, "no frames")
    model = HumanModel(betas[:10])
    # MoSh++ turns the body about the pelvis, placed at trans + J₀(β) of the file's own body
    # model; HumanModel.pose turns it about the origin
    pelvis_rest = model.rest_joints[0]
    pelvis_file = pelvis_rest
    if body_model == "smplh":
        # mannequin-x's pelvis is SMPL-X's; an SMPL-H file's trans is for SMPL's, 11 cm away (model
        # y-up frame: −0.22 vs −0.35 m). Take SMPL's template pelvis and mannequin-x's shape offset.
        pelvis_file = SMPL_TEMPLATE_PELVIS + pelvis_rest - HumanModel(np.zeros(10)).rest_joints[0]
    transl = trans + pelvis_file - np.einsum("tij,j->ti", quat_to_matrix(quat_from_rotvec(root)), pelvis_rest)
    part_pos, part_quat = model.pose(root, transl, body)
    shift = _ground_shift(model.surface, part_pos, part_quat) if ground else 0.0
    part_pos[..., 2] += shift
    gender = str(data["gender"]) if "gender" in data else "unknown"
    return Demonstration(
        name=path.stem, fps=fps, part_names=PART_NAMES, part_parents=PART_PARENTS, part_pos_w=part_pos,
        part_quat_w=part_quat, surface=model.surface, shape=model.shape, stature_m=model.stature_m,
        source={"format": f"amass-{body_model}", "path": origin, "gender": gender, "num_betas_in_file": betas.size,
                "ground_shift_m": shift})


# ------------------------------------------------------------------ OMOMO (InterMimic layout)

OMOMO_FPS = 30.0
OMOMO_COLUMNS = 591
#: The 52 SMPL-H joints of the InterMimic layout, in storage order (fingers in SMPL-H order; only
#: the 22 body joints are read).
INTERMIMIC_JOINTS: tuple[str, ...] = (
    "Pelvis", "L_Hip", "L_Knee", "L_Ankle", "L_Toe", "R_Hip", "R_Knee", "R_Ankle", "R_Toe", "Torso", "Spine",
    "Chest", "Neck", "Head", "L_Thorax", "L_Shoulder", "L_Elbow", "L_Wrist",
    *(f"L_{f}{i}" for f in ("Index", "Middle", "Pinky", "Ring", "Thumb") for i in (1, 2, 3)),
    "R_Thorax", "R_Shoulder", "R_Elbow", "R_Wrist",
    *(f"R_{f}{i}" for f in ("Index", "Middle", "Pinky", "Ring", "Thumb") for i in (1, 2, 3)),
)
#: InterMimic names of the 22 SMPL-X parts, in PART_NAMES order.
INTERMIMIC_OF_PART = (
    "Pelvis", "L_Hip", "R_Hip", "Torso", "L_Knee", "R_Knee", "Spine", "L_Ankle", "R_Ankle", "Chest", "L_Toe",
    "R_Toe", "Neck", "L_Thorax", "R_Thorax", "Head", "L_Shoulder", "R_Shoulder", "L_Elbow", "R_Elbow", "L_Wrist",
    "R_Wrist",
)
_OMOMO_CLIP = re.compile(r"^(?P<subject>sub\d+)_(?P<object>[a-z_]+?)_(?P<take>\d+)$")


class _HeightsUnpickler(pickle.Unpickler):
    """subject_heights.pkl holds {str: numpy float32}; refuse any other class (pickle runs code)."""

    _ALLOWED = {("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"), ("numpy", "dtype")}

    def find_class(self, module, name):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name}")
        return super().find_class(module, name)


def _subject_stature(folder: Path, subject: str | None) -> float | None:
    heights = folder / "subject_heights.pkl"
    if subject is None or not heights.is_file():
        return None
    try:
        with heights.open("rb") as f:
            table = _HeightsUnpickler(f).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError) as exc:
        raise InvalidDemonstrationError(f"{heights}: not a table of subject heights ({exc})") from exc
    return float(table[subject]) if isinstance(table, dict) and subject in table else None


def _find_object_mesh(path: Path, object_name: str | None) -> Path:
    if object_name is None:
        _fail(str(path), "cannot infer the object name from the file name (expected sub<N>_<object>_<take>); "
                         "pass object_mesh")
    candidates = [folder / "objects" / f"{object_name}.obj" for folder in (path.parent, path.parent.parent)]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise DemonstrationFileNotFoundError(
        f"{path}: object mesh for {object_name!r} not found (looked for {[str(c) for c in candidates]}); "
        "pass object_mesh")


def _read_omomo(path: Path, object_mesh: Path | None, ground: bool) -> Demonstration:
    import torch  # only this reader needs it, and it is slow to import

    from retarget.human import PART_NAMES, PART_PARENTS, SMPLX_REST_QUAT_W, HumanModel, fit_shape

    origin = str(path)
    clip = _OMOMO_CLIP.match(path.stem)
    subject, object_name = (clip["subject"], clip["object"]) if clip else (None, None)
    mesh_path = object_mesh if object_mesh is not None else _find_object_mesh(path, object_name)
    if not mesh_path.is_file():
        raise DemonstrationFileNotFoundError(f"{path}: object mesh {mesh_path} not found")
    try:
        mesh = load_mesh(mesh_path)
    except InvalidMeshError as exc:
        raise InvalidDemonstrationError(f"{path}: object mesh unusable: {exc}") from exc

    try:
        tensor = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt or foreign files
        raise InvalidDemonstrationError(f"{origin}: not a readable torch tensor file ({type(exc).__name__}: {exc})") \
            from exc
    if not isinstance(tensor, torch.Tensor):
        _fail(origin, f"expected one tensor (T, {OMOMO_COLUMNS}), got {type(tensor).__name__}")
    x = tensor.detach().cpu().numpy().astype(np.float64)
    if x.ndim != 2 or x.shape[1] != OMOMO_COLUMNS or len(x) < 2:
        _fail(origin, f"expected an InterMimic tensor (T ≥ 2, {OMOMO_COLUMNS}), got {x.shape}")
    _check_finite(origin, "tensor", x)
    frames = len(x)
    columns = [INTERMIMIC_JOINTS.index(n) for n in INTERMIMIC_OF_PART]
    body_quat = xyzw_to_wxyz(x[:, 383:591].reshape(frames, 52, 4))[:, columns]
    _check_unit(origin, "body quaternions (columns 383:591)", body_quat)
    part_quat = quat_mul(quat_normalize(body_quat), SMPLX_REST_QUAT_W)
    joints = x[:, 162:318].reshape(frames, 52, 3)[:, columns]
    fit = fit_shape(joints, part_quat)
    model = HumanModel(fit.shape)
    part_pos = model.forward_kinematics(part_quat, fit.pelvis_pos_w)
    shift = _ground_shift(model.surface, part_pos, part_quat) if ground else 0.0
    part_pos[..., 2] += shift
    object_quat = xyzw_to_wxyz(x[:, 321:325])
    _check_unit(origin, "object quaternion (columns 321:325)", object_quat)
    box = DemoObject(name=object_name or mesh_path.stem, vertices=mesh.vertices, faces=mesh.faces,
                     pos_w=x[:, 318:321].copy(), quat_w=quat_normalize(object_quat), mesh_path=str(mesh_path))

    stature = _subject_stature(path.parent, subject)
    return Demonstration(
        name=path.stem, fps=OMOMO_FPS, part_names=PART_NAMES, part_parents=PART_PARENTS, part_pos_w=part_pos,
        part_quat_w=part_quat, surface=model.surface, shape=model.shape,
        stature_m=model.stature_m if stature is None else stature, objects=[box],
        source={"format": "omomo-intermimic", "path": origin, "subject": subject,
                "stature_source": "model" if stature is None else "subject_heights.pkl", "ground_shift_m": shift,
                "model_stature_m": model.stature_m, "joint_fit_mean_m": float(fit.joint_error_m.mean()),
                "joint_fit_max_m": float(fit.joint_error_m.max()), "intermimic_body_names": list(INTERMIMIC_JOINTS)},
        annotations={"object_contact": x[:, 330] > 0.5, "intermimic_body_contact": x[:, 331:383].astype(np.int8)})
