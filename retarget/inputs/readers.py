"""Human (and human–object) demonstrations from capture files: the readers (the type is
``retarget.inputs.demonstration``).

World frame z-up, metres, quaternions wxyz. Human "parts" are the 22 SMPL-X body joints
(``retarget.inputs.human.PART_NAMES``); each part carries a rigid piece of the mannequin-x surface
expressed in that part's frame, so posing the surface at frame t is
``part_quat_w[t, k] ⊗ vertices_k + part_pos_w[t, k]``.

Readers (``load_demonstration`` dispatches on the file):

* our own ``.npz`` (``Demonstration.save``), validated on load;
* AMASS SMPL-X / SMPL-H parameter ``.npz`` (z-up already). AMASS ``trans`` follows MoSh++ / the
  ``smplx`` package: the root rotation turns the body about the pelvis joint, so the pelvis is
  at ``trans + J₀(β)``. SMPL-H files carry SMPL-H shape coefficients, which we read as the first
  ten SMPL-X coefficients (an approximation: the spaces differ, the leading components — size
  and girth — roughly agree);
* BVH skeletal motion capture (``retarget.inputs.bvh``: skeleton families, units, up axis, body fit);
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

import pickle
import re
from pathlib import Path

import numpy as np

from otr_gym.rotations import quat_from_rotvec, quat_mul, quat_normalize, quat_to_matrix, xyzw_to_wxyz
from retarget.inputs.demonstration import (
    Demonstration,
    DemonstrationFileNotFoundError,
    DemoObject,
    InvalidDemonstrationError,
    check_finite,
    check_shape,
    check_unit,
    fail,
    from_arrays,
    ground_shift,
    read_npz,
)
from retarget.inputs.meshes import InvalidMeshError, load_mesh

# ------------------------------------------------------------------ dispatch


def load_demonstration(path: str | Path, object_mesh: str | Path | None = None, *,
                       ground: bool = True, bvh=None) -> Demonstration:
    """Read any supported demonstration file (see the module docstring) into a validated Demonstration.

    ``object_mesh`` overrides the mesh lookup of OMOMO clips; ``ground`` puts the human's feet on
    z = 0 (module docstring); ``bvh`` (``retarget.inputs.bvh.BvhOptions``) says how to read ``.bvh``
    files (skeleton map, units, up axis). Any problem raises InvalidDemonstrationError naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise DemonstrationFileNotFoundError(f"{path}: no such demonstration file")
    if path.suffix.lower() == ".bvh":
        from retarget.inputs.bvh import read_bvh

        demo = read_bvh(path, bvh, ground)
    elif path.suffix == ".pt":
        demo = _read_omomo(path, None if object_mesh is None else Path(object_mesh), ground)
    elif path.suffix == ".npz":
        data = read_npz(path)
        if "format" in data and "part_pos_w" in data:
            demo = from_arrays(data, str(path))
        elif "poses" in data or "pose_body" in data:
            demo = _read_amass(path, data, ground)
        else:
            fail(str(path), f"unknown .npz layout (keys {sorted(data)}): neither our demonstration format "
                             "nor AMASS parameters (poses / root_orient+pose_body)")
    else:
        fail(str(path), f"unknown demonstration format {path.suffix!r} (expected .npz, .pt or .bvh)")
    demo.validate(str(path))
    return demo


# ------------------------------------------------------------------ AMASS


def _first_key(origin: str, data: dict, keys: tuple[str, ...], what: str) -> np.ndarray:
    for key in keys:
        if key in data:
            return data[key]
    fail(origin, f"missing {what} (one of keys {list(keys)})")


def _amass_rows(origin: str, data: dict) -> tuple[np.ndarray, np.ndarray, str]:
    """(root_orient (T, 3), pose_body (T, 21, 3), body model) from either AMASS key layout."""
    if "poses" in data:
        poses = np.asarray(data["poses"], np.float64)
        widths = {165: "smplx", 156: "smplh"}
        if poses.ndim != 2 or poses.shape[1] not in widths:
            fail(origin, f"poses must be (T, 165) for SMPL-X or (T, 156) for SMPL-H, got {poses.shape}")
        return poses[:, :3], poses[:, 3:66].reshape(-1, 21, 3), widths[poses.shape[1]]
    if "root_orient" not in data:
        fail(origin, "pose_body present but root_orient missing")
    root, body = np.asarray(data["root_orient"], np.float64), np.asarray(data["pose_body"], np.float64)
    check_shape(origin, "root_orient", root, (None, 3))
    check_shape(origin, "pose_body", body, (len(root), 63))
    model = str(data["surface_model_type"]) if "surface_model_type" in data else (
        "smplx" if "pose_jaw" in data else "smplh")
    return root, body.reshape(-1, 21, 3), model


#: The pelvis joint of SMPL's template (model frame, y-up, m): J₀ of the mean shape, which
#: SMPL-H shares. AMASS SMPL-H ``trans`` places this joint (plus its shape offset).
SMPL_TEMPLATE_PELVIS = np.array([-0.00179506, -0.22333345, 0.02821913])


def _read_amass(path: Path, data: dict, ground: bool) -> Demonstration:
    from retarget.inputs.human import PART_NAMES, PART_PARENTS, HumanModel  # human.py builds on the types above

    origin = str(path)
    root, body, body_model = _amass_rows(origin, data)
    frames = len(root)
    trans = np.asarray(_first_key(origin, data, ("trans",), "root translation"), np.float64)
    check_shape(origin, "trans", trans, (frames, 3))
    betas = np.asarray(_first_key(origin, data, ("betas",), "shape coefficients"), np.float64).ravel()
    if betas.size < 10:
        fail(origin, f"betas has {betas.size} values, needs at least 10")
    rate = np.asarray(_first_key(origin, data, ("mocap_frame_rate", "mocap_framerate"), "frame rate"), np.float64)
    if rate.size != 1 or not np.isfinite(rate).all() or rate.item() <= 0:
        fail(origin, f"frame rate must be one positive number, got {rate.tolist()}")
    fps = rate.item()
    for key, arr in (("root orientation", root), ("body pose", body), ("trans", trans), ("betas", betas)):
        check_finite(origin, key, arr)
    if frames < 1:
        fail(origin, "no frames")
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
    shift = ground_shift(model.surface, part_pos, part_quat) if ground else 0.0
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
        fail(str(path), "cannot infer the object name from the file name (expected sub<N>_<object>_<take>); "
                         "pass object_mesh")
    # The clip's folder and its parent: OMOMO_new/<clip>.pt beside OMOMO_new/objects/, or a data root holding
    # omomo/ and objects/. For a relative path in the working folder both are "." (one candidate, listed once).
    candidates = list(dict.fromkeys(folder / "objects" / f"{object_name}.obj" for folder in (path.parent,
                                                                                            path.parent.parent)))
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    looked = " or ".join(str(c) for c in candidates)
    raise DemonstrationFileNotFoundError(
        f"{path}: object mesh for {object_name!r} not found (looked for {looked}); pass the mesh: "
        f"load_demonstration(..., object_mesh='{object_name}.obj') or otr retarget ... --object {object_name}.obj")


def _read_tensor(path: Path, origin: str) -> np.ndarray:
    """The one tensor of a ``torch.save`` file, without importing torch when the file is the
    plain layout (``retarget.inputs.torch_file``: ~2 s of a run's start), else by ``torch.load``."""
    from retarget.inputs.torch_file import read_tensor

    x = read_tensor(path)
    if x is not None:
        return x
    import torch  # slow to import: only for files the plain reader does not take

    try:
        tensor = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt or foreign files
        raise InvalidDemonstrationError(f"{origin}: not a readable torch tensor file ({type(exc).__name__}: {exc})") \
            from exc
    if not isinstance(tensor, torch.Tensor):
        fail(origin, f"expected one tensor (T, {OMOMO_COLUMNS}), got {type(tensor).__name__}")
    return tensor.detach().cpu().numpy()


def _read_omomo(path: Path, object_mesh: Path | None, ground: bool) -> Demonstration:
    from retarget.inputs.human import PART_NAMES, PART_PARENTS, SMPLX_REST_QUAT_W, HumanModel, fit_shape

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

    x = _read_tensor(path, origin).astype(np.float64)
    if x.ndim != 2 or x.shape[1] != OMOMO_COLUMNS or len(x) < 2:
        fail(origin, f"expected an InterMimic tensor (T ≥ 2, {OMOMO_COLUMNS}), got {x.shape}")
    check_finite(origin, "tensor", x)
    frames = len(x)
    columns = [INTERMIMIC_JOINTS.index(n) for n in INTERMIMIC_OF_PART]
    body_quat = xyzw_to_wxyz(x[:, 383:591].reshape(frames, 52, 4))[:, columns]
    check_unit(origin, "body quaternions (columns 383:591)", body_quat)
    part_quat = quat_mul(quat_normalize(body_quat), SMPLX_REST_QUAT_W)
    joints = x[:, 162:318].reshape(frames, 52, 3)[:, columns]
    fit = fit_shape(joints, part_quat)
    model = HumanModel(fit.shape)
    part_pos = model.forward_kinematics(part_quat, fit.pelvis_pos_w)
    shift = ground_shift(model.surface, part_pos, part_quat) if ground else 0.0
    part_pos[..., 2] += shift
    object_quat = xyzw_to_wxyz(x[:, 321:325])
    check_unit(origin, "object quaternion (columns 321:325)", object_quat)
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
