"""The demonstrator's body: mannequin-x parts with SMPL-X kinematics, and the human <-> G1 tables.

Parts are the 22 SMPL-X body joints (``PART_NAMES``). A part is a rigid frame at its joint whose
axes are those of the SMPL-X rest pose (x: the subject's left, y: up, z: forward); its surface
is the set of mannequin-x LOD-0 convex hulls attached to that joint, in that frame. The figure
comes from mannequin-x (Apache-2.0), which reproduces SMPL-X skeleton lengths and floor for the
first ten SMPL-X shape coefficients without the licence-restricted SMPL-X model files.

Simplifications (ours, documented once here):

* Hands are rigid. The 30 finger hulls are merged into the wrist part in SMPL-X's fixed relaxed
  mean hand pose; finger articulation of the data is dropped.
* A part's surface is the concatenation of closed convex hulls that overlap near the joints, not
  one manifold skin: some hull faces lie inside a neighbouring hull.

Global rotation: ``HumanModel.pose`` follows mannequin-x / body-models, where the global rotation
turns the body about the SMPL-X origin (pelvis = R_g J₀ + transl). SMPL-X files fitted by MoSh++
(AMASS) instead turn it about the pelvis joint (pelvis = J₀ + transl); the AMASS reader converts.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from mannequin import Mannequin
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from otr_gym import robot
from otr_gym.robot import indices_by_name
from otr_gym.rotations import matrix_to_quat, quat_conj, quat_from_rotvec, quat_mul, quat_to_matrix
from retarget.inputs.human_surface import HumanSurface

PART_NAMES: tuple[str, ...] = (
    "Pelvis", "L_Hip", "R_Hip", "Spine1", "L_Knee", "R_Knee", "Spine2", "L_Ankle", "R_Ankle",
    "Spine3", "L_Foot", "R_Foot", "Neck", "L_Collar", "R_Collar", "Head", "L_Shoulder",
    "R_Shoulder", "L_Elbow", "R_Elbow", "L_Wrist", "R_Wrist",
)
PART_PARENTS: tuple[int, ...] = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)
NUM_PARTS = len(PART_NAMES)
NUM_SHAPE = 10
NUM_BODY_POSE = NUM_PARTS - 1  # SMPL-X body_pose rows: every part but the pelvis

#: World orientation of every part frame in the rest T-pose when the subject stands in our
#: z-up world facing +x like the G1: SMPL-X (left, up, forward) -> world (y, z, x), i.e. a
#: 120° turn about (1, 1, 1). Also the fixed right factor between InterMimic body frames and
#: SMPL-X part frames (their humanoid's rest pose is the identity in the z-up world).
SMPLX_REST_QUAT_W = quat_from_rotvec(np.full(3, 2.0 * np.pi / 3.0 / np.sqrt(3.0)))

# ------------------------------------------------------------------ human part <-> G1 link

#: The one human-part <-> G1-link table. For every G1 body with a visual mesh, the human parts
#: whose surface its probes take their targets from (OT correspondences,
#: docs/method.md "Correspondences (optimal transport)"). Small motor
#: housings (hip pitch, shoulder pitch, waist yaw/roll, ankle pitch, wrist roll/pitch) take the
#: human part most of their vertices are nearest to when both stand in the T-pose at the same
#: height; the torso carries the G1 head, so it takes the upper trunk, neck, head and collars.
G1_LINK_PARTS: dict[str, tuple[str, ...]] = {
    "pelvis": ("Pelvis",),
    "left_hip_pitch_link": ("L_Hip",),
    "left_hip_roll_link": ("L_Hip",),
    "left_hip_yaw_link": ("L_Hip",),
    "left_knee_link": ("L_Knee",),
    "left_ankle_pitch_link": ("L_Ankle",),
    "left_ankle_roll_link": ("L_Ankle", "L_Foot"),
    "right_hip_pitch_link": ("R_Hip",),
    "right_hip_roll_link": ("R_Hip",),
    "right_hip_yaw_link": ("R_Hip",),
    "right_knee_link": ("R_Knee",),
    "right_ankle_pitch_link": ("R_Ankle",),
    "right_ankle_roll_link": ("R_Ankle", "R_Foot"),
    "waist_yaw_link": ("Spine1",),
    "waist_roll_link": ("Spine1",),
    "torso_link": ("Spine2", "Spine3", "Neck", "Head", "L_Collar", "R_Collar"),
    "left_shoulder_pitch_link": ("L_Collar",),
    "left_shoulder_roll_link": ("L_Shoulder",),
    "left_shoulder_yaw_link": ("L_Shoulder",),
    "left_elbow_link": ("L_Elbow",),
    "left_wrist_roll_link": ("L_Elbow",),
    "left_wrist_pitch_link": ("L_Wrist",),
    "left_wrist_yaw_link": ("L_Wrist",),
    "right_shoulder_pitch_link": ("R_Collar",),
    "right_shoulder_roll_link": ("R_Shoulder",),
    "right_shoulder_yaw_link": ("R_Shoulder",),
    "right_elbow_link": ("R_Elbow",),
    "right_wrist_roll_link": ("R_Elbow",),
    "right_wrist_pitch_link": ("R_Wrist",),
    "right_wrist_yaw_link": ("R_Wrist",),
}

#: Groupings of G1 links that ``retarget.solver.transport.link_correspondences`` matches with their
#: shared human parts as one target cloud (``RetargetConfig.links_together``); every other link
#: is matched alone. "none" (default): each link alone, so a small housing spreads its targets
#: over the whole part it shares. "hand": the wrist pitch housing and the hand together, so the
#: housing takes the hand's near (wrist) end. "shared_parts": every set of links that take the
#: same parts (hip, waist, shoulder housings; elbow and wrist roll; wrist pitch and hand). The
#: evaluation's body units (``retarget.evaluation.units.group_units``) are the wider, connected
#: form (links sharing *any* part: also torso with the shoulder pitch housings, both ankle links);
#: a grouping here needs the same parts for all its links, as one plan transports from one cloud.
LINK_GROUPINGS: dict[str, tuple[tuple[str, ...], ...]] = {
    "none": (),
    "hand": tuple((f"{side}_wrist_pitch_link", f"{side}_wrist_yaw_link") for side in ("left", "right")),
    "shared_parts": tuple(group for group in (
        tuple(link for link in G1_LINK_PARTS if G1_LINK_PARTS[link] == parts)
        for parts in dict.fromkeys(G1_LINK_PARTS.values())) if len(group) > 1),
}


def link_grouping(name: str) -> tuple[tuple[str, ...], ...]:
    """The groups of ``LINK_GROUPINGS[name]``; an unknown name raises ValueError naming the choices."""
    if name not in LINK_GROUPINGS:
        raise ValueError(f"unknown links_together '{name}' (choose from {sorted(LINK_GROUPINGS)})")
    return LINK_GROUPINGS[name]


#: G1 link -> human part h(ℓ) for the style targets R̂_ℓ = R_h(ℓ) O_ℓ (paper Sec. III-D). The
#: links are those whose orientation a human segment fixes: the yaw links carry the thigh and
#: upper-arm twist, the ankle roll link is the foot, the wrist yaw link is the hand.
STYLE_LINKS: dict[str, str] = {
    "pelvis": "Pelvis",
    "left_hip_yaw_link": "L_Hip",
    "left_knee_link": "L_Knee",
    "left_ankle_roll_link": "L_Ankle",
    "right_hip_yaw_link": "R_Hip",
    "right_knee_link": "R_Knee",
    "right_ankle_roll_link": "R_Ankle",
    "torso_link": "Spine3",
    "left_shoulder_yaw_link": "L_Shoulder",
    "left_elbow_link": "L_Elbow",
    "left_wrist_yaw_link": "L_Wrist",
    "right_shoulder_yaw_link": "R_Shoulder",
    "right_elbow_link": "R_Elbow",
    "right_wrist_yaw_link": "R_Wrist",
}


def part_index(names) -> np.ndarray:
    """Indices of part ``names`` in PART_NAMES; unknown names raise with the list of them."""
    return indices_by_name(names, PART_NAMES, "human part")


# ------------------------------------------------------------------ skeleton


def _ancestor_matrix() -> np.ndarray:
    """A[k, i] = 1 when bone i (part i's offset from its parent) lies on the chain pelvis -> k."""
    a = np.zeros((NUM_PARTS, NUM_PARTS))
    for k in range(NUM_PARTS):
        i = k
        while i > 0:
            a[k, i] = 1.0
            i = PART_PARENTS[i]
    return a


_ANCESTORS = _ancestor_matrix()
_PARENT_OR_SELF = np.array([max(p, 0) for p in PART_PARENTS])


def _shape_vector(shape, what: str = "shape") -> np.ndarray:
    s = np.zeros(NUM_SHAPE) if shape is None else np.asarray(shape, dtype=np.float64)
    if s.shape != (NUM_SHAPE,):
        raise ValueError(f"{what} must have shape ({NUM_SHAPE},), got {s.shape}")
    if not np.isfinite(s).all():
        raise ValueError(f"{what} contains NaN/inf: {s}")
    return s


@dataclass(frozen=True)
class ShapeBasis:
    """Rest joints (SMPL-X rest frame, y-up, m) are affine in the shape coefficients β.

    J(β) = rest_joints + joint_dirs @ β, read off mannequin-x's calibrated skeleton.
    """

    rest_joints: np.ndarray  # (22, 3)
    joint_dirs: np.ndarray  # (22, 3, 10)

    def joints(self, shape) -> np.ndarray:
        return self.rest_joints + self.joint_dirs @ _shape_vector(shape)

    def bone_offsets(self) -> tuple[np.ndarray, np.ndarray]:
        """Per part, its offset from the parent joint: constant (22, 3) and shape part (22, 3, 10)."""
        o = self.rest_joints - self.rest_joints[_PARENT_OR_SELF]
        d = self.joint_dirs - self.joint_dirs[_PARENT_OR_SELF]
        return o, d


def _rest_joints(figure: Mannequin, shape: np.ndarray) -> np.ndarray:
    zeros = np.zeros
    transforms = figure.forward_skeleton(zeros((NUM_BODY_POSE, 3)), zeros((3, 3)), zeros((30, 3)), shape=shape)
    return transforms[:NUM_PARTS, :3, 3].astype(np.float64)


@lru_cache(maxsize=1)
def shape_basis() -> ShapeBasis:
    """The affine map β -> rest joints, from mannequin-x's public skeleton (exact: it is linear)."""
    figure = Mannequin("convex", lod=0)
    rest = _rest_joints(figure, np.zeros(NUM_SHAPE))
    dirs = np.stack([_rest_joints(figure, np.eye(NUM_SHAPE)[i]) - rest for i in range(NUM_SHAPE)], axis=-1)
    return ShapeBasis(rest, dirs)


def forward_kinematics(part_quat_w: np.ndarray, pelvis_pos_w: np.ndarray, rest_joints: np.ndarray) -> np.ndarray:
    """World part positions (…, 22, 3) from world part orientations (…, 22, 4 wxyz) and the pelvis.

    p_k = p_pelvis + Σ_{bones i on the chain to k} R_parent(i) (J_i − J_parent(i)), with the rest
    joints J (22, 3) of one shape in the SMPL-X rest frame.
    """
    offsets = rest_joints - rest_joints[_PARENT_OR_SELF]
    rot_parent = quat_to_matrix(np.asarray(part_quat_w, np.float64))[..., _PARENT_OR_SELF, :, :]
    bones_w = np.einsum("...iab,ib->...ia", rot_parent, offsets)
    return np.asarray(pelvis_pos_w)[..., None, :] + np.einsum("ki,...ia->...ka", _ANCESTORS, bones_w)


@dataclass(frozen=True)
class ShapeFit:
    """Least-squares shape of a subject from world joint positions and part orientations."""

    shape: np.ndarray  # (10,) mannequin-x / SMPL-X shape coefficients
    pelvis_pos_w: np.ndarray  # (T, 3) m, the per-frame translation that best aligns the skeleton
    joint_error_m: np.ndarray  # (T, 22) distance of the fitted joints to the given ones


def fit_shape(joint_pos_w: np.ndarray, part_quat_w: np.ndarray, *, ridge_m2: float = 1e-6) -> ShapeFit:
    """Fit the 10 shape coefficients and a per-frame translation to joint positions.

    With the part orientations known, the joints are affine in (β, translation), so the fit is
    one linear least-squares solve: the translation is eliminated by centring each frame over
    its joints. ``ridge_m2`` (m² of mean squared joint error per unit coefficient²) pulls the
    coefficients the joints barely constrain towards the mean shape: 1e-6 trades about 1 mm of
    RMS error per unit of β.

    joint_pos_w: (T, 22, 3) m, world; part_quat_w: (T, 22, 4) wxyz, world, SMPL-X part frames.
    """
    joints = np.asarray(joint_pos_w, np.float64)
    quats = np.asarray(part_quat_w, np.float64)
    if joints.ndim != 3 or joints.shape[1:] != (NUM_PARTS, 3) or quats.shape != (*joints.shape[:2], 4):
        raise ValueError(f"fit_shape needs joint_pos_w (T, {NUM_PARTS}, 3) and part_quat_w (T, {NUM_PARTS}, 4), "
                         f"got {joints.shape} and {quats.shape}")
    if not (np.isfinite(joints).all() and np.isfinite(quats).all()):
        raise ValueError("fit_shape: joint positions or orientations contain NaN/inf")
    offsets, offset_dirs = shape_basis().bone_offsets()
    rot_parent = quat_to_matrix(quats)[:, _PARENT_OR_SELF]
    constant = np.einsum("ki,tiab,ib->tka", _ANCESTORS, rot_parent, offsets)  # (T, 22, 3), pelvis-relative
    linear = np.einsum("ki,tiab,ibc->tkac", _ANCESTORS, rot_parent, offset_dirs)  # (T, 22, 3, 10)
    target = joints - constant
    a = (linear - linear.mean(axis=1, keepdims=True)).reshape(-1, NUM_SHAPE)
    b = (target - target.mean(axis=1, keepdims=True)).reshape(-1)
    n = len(b) / 3.0  # joint samples: the ridge is per mean squared joint error
    shape = np.linalg.solve(a.T @ a / n + ridge_m2 * np.eye(NUM_SHAPE), a.T @ b / n)
    relative = constant + linear @ shape
    pelvis = (joints - relative).mean(axis=1)
    error = np.linalg.norm(pelvis[:, None] + relative - joints, axis=-1)
    return ShapeFit(shape, pelvis, error)


# ------------------------------------------------------------------ the body


def _link_owners(figure: Mannequin) -> np.ndarray:
    """Joint index owning each mannequin link, matched through the public transforms of a random pose."""
    rng = np.random.default_rng(0)
    pose = figure.rest_pose(dtype=np.float64)
    pose["body_pose"] = rng.normal(scale=0.5, size=(NUM_BODY_POSE, 3))
    pose["hand_pose"] = rng.normal(scale=0.5, size=(30, 3))
    joints = figure.joint_transforms(pose)
    links = figure.link_transforms(pose)
    same = np.all(np.isclose(links[:, None], joints[None], atol=1e-9), axis=(-1, -2))
    if not same.any(axis=1).all():
        raise RuntimeError("mannequin-x: a link transform matches no joint transform; unsupported version")
    return np.argmax(same, axis=1)  # L_Hand coincides with L_Wrist; the first (the wrist) wins


def _link_vertex_ranges(figure: Mannequin) -> np.ndarray:
    """Link of every rest vertex: each link is one closed hull, stored contiguously in link order."""
    faces = figure.faces
    n = figure.num_vertices
    edges = coo_matrix((np.ones(faces.size), (faces.ravel(), np.roll(faces, 1, axis=1).ravel())), shape=(n, n))
    count, label = connected_components(edges, directed=False)
    if count != len(figure.link_names) or np.any(np.diff(label) < 0):
        raise RuntimeError(f"mannequin-x: expected {len(figure.link_names)} contiguous hulls, found {count}")
    return label


def _body_part_of_joint(figure: Mannequin) -> np.ndarray:
    """Body part (0..21) of every mannequin joint: itself, or for finger joints the wrist they hang from."""
    parents = figure.parents
    out = np.arange(len(parents))
    for j in range(NUM_PARTS, len(parents)):
        k = j
        while k >= NUM_PARTS:
            k = parents[k]
        out[j] = k
    return out


def _build_surface(figure: Mannequin) -> HumanSurface:
    if figure.joint_names[:NUM_PARTS] != PART_NAMES:
        raise RuntimeError(f"mannequin-x joint order {figure.joint_names[:NUM_PARTS]} differs from PART_NAMES")
    rest = figure.rest_pose(dtype=np.float64)
    vertices_rest = np.asarray(figure.vertices(rest), np.float64)  # body parts: identity rotations
    joints_rest = figure.joint_transforms(rest)[:NUM_PARTS, :3, 3].astype(np.float64)
    vertex_link = _link_vertex_ranges(figure)
    vertex_part = _body_part_of_joint(figure)[_link_owners(figure)][vertex_link]
    face_part = vertex_part[figure.faces[:, 0]]
    vertices, faces = [], []
    for k in range(NUM_PARTS):
        keep = np.flatnonzero(vertex_part == k)
        remap = np.full(figure.num_vertices, -1)
        remap[keep] = np.arange(len(keep))
        vertices.append(vertices_rest[keep] - joints_rest[k])
        faces.append(remap[figure.faces[face_part == k]])
    return HumanSurface(part_names=PART_NAMES, vertices=vertices, faces=faces)


class HumanModel:
    """The mannequin-x body of one shape: SMPL-X kinematics of the 22 parts and their hulls."""

    def __init__(self, shape=None) -> None:
        self.shape = _shape_vector(shape)
        self._figure = Mannequin("convex", lod=0, shape=self.shape.astype(np.float32))
        self.rest_joints = shape_basis().joints(self.shape)  # (22, 3) SMPL-X rest frame, m

    def pose(self, global_orient_aa, transl, body_pose_aa) -> tuple[np.ndarray, np.ndarray]:
        """World part poses from SMPL-X parameters (global rotation about the SMPL-X origin).

        global_orient_aa (T, 3) and body_pose_aa (T, 21, 3) are axis-angle (rad), transl (T, 3) m.
        Returns part_pos_w (T, 22, 3) m and part_quat_w (T, 22, 4) wxyz.
        """
        g = np.asarray(global_orient_aa, np.float64)
        t = np.asarray(transl, np.float64)
        b = np.asarray(body_pose_aa, np.float64)
        if g.ndim != 2 or g.shape[1] != 3 or t.shape != g.shape or b.shape != (len(g), NUM_BODY_POSE, 3):
            raise ValueError(f"pose needs global_orient_aa (T, 3), transl (T, 3), body_pose_aa (T, 21, 3); "
                             f"got {g.shape}, {t.shape}, {b.shape}")
        for name, arr in (("global_orient_aa", g), ("transl", t), ("body_pose_aa", b)):
            if not np.isfinite(arr).all():
                raise ValueError(f"pose: {name} contains NaN/inf")
        frames = len(g)
        transforms = self._figure.forward_skeleton(
            b, np.zeros((frames, 3, 3)), np.zeros((frames, 30, 3)), global_rotation=g, global_translation=t,
            joint_indices=list(range(NUM_PARTS)))
        return transforms[..., :3, 3], matrix_to_quat(transforms[..., :3, :3])

    def forward_kinematics(self, part_quat_w: np.ndarray, pelvis_pos_w: np.ndarray) -> np.ndarray:
        """World part positions (T, 22, 3) of this shape for world orientations (T, 22, 4) and pelvis (T, 3)."""
        return forward_kinematics(part_quat_w, pelvis_pos_w, self.rest_joints)

    @cached_property
    def surface(self) -> HumanSurface:
        """Per-part hulls in the part frames (fingers merged into the wrists, relaxed mean hand)."""
        return _build_surface(self._figure)

    @cached_property
    def stature_m(self) -> float:
        """Height of the rest mesh (top of the head to the soles), m."""
        y = np.concatenate([v[:, 1] + j[1] for v, j in zip(self.surface.vertices, self.rest_joints, strict=True)])
        return float(y.max() - y.min())

    def posed_vertices(self, part_pos_w: np.ndarray, part_quat_w: np.ndarray) -> np.ndarray:
        """World surface vertices (T, V, 3), parts concatenated in PART_NAMES order."""
        return self.surface.posed_vertices(part_pos_w, part_quat_w)


# ------------------------------------------------------------------ T-poses and alignment


def human_tpose(model: HumanModel | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Part poses (22, 3) m / (22, 4) wxyz of the rest T-pose in the z-up world, facing +x.

    The pelvis stands above the origin and the lowest surface point touches z = 0.
    """
    model = HumanModel() if model is None else model
    quat = np.broadcast_to(SMPLX_REST_QUAT_W, (NUM_PARTS, 4)).copy()
    joints_w = quat_to_matrix(SMPLX_REST_QUAT_W) @ (model.rest_joints - model.rest_joints[0]).T
    pos = joints_w.T
    lowest = model.posed_vertices(pos[None], quat[None])[0, :, 2].min()
    return pos - np.array([0.0, 0.0, lowest]), quat


#: G1 joint angles of the T-pose (rad): arms straight out sideways, everything else straight.
#: The G1 elbow is bent 90° at zero, so a straight arm needs elbow = π/2.
_G1_TPOSE_JOINTS = {
    "left_shoulder_roll_joint": np.pi / 2,
    "right_shoulder_roll_joint": -np.pi / 2,
    "left_elbow_joint": np.pi / 2,
    "right_elbow_joint": np.pi / 2,
}


@lru_cache(maxsize=1)
def _g1_tpose() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(qpos (36,), body_pos_w (30, 3), body_quat_w (30, 4)) with the soles on z = 0."""
    import mujoco

    from otr_gym.robot_geometry import posed_vertices, visual_meshes
    from otr_gym.scene import robot_model

    model = robot_model(visual=False)
    data = mujoco.MjData(model)
    qpos = np.zeros(7 + robot.NUM_JOINTS)
    qpos[3] = 1.0
    qpos[7 + robot.joint_indices(list(_G1_TPOSE_JOINTS))] = list(_G1_TPOSE_JOINTS.values())
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    ids = [model.body(n).id for n in robot.BODY_NAMES]
    pos, quat = data.xpos[ids].copy(), data.xquat[ids].copy()
    meshes = visual_meshes()
    lowest = min(posed_vertices(meshes[b], pos[i], quat[i])[:, 2].min()
                 for i, b in enumerate(robot.BODY_NAMES) if b in meshes)
    qpos[2] -= lowest
    pos[:, 2] -= lowest
    return qpos, pos, quat


def g1_tpose_qpos() -> np.ndarray:
    """G1 qpos [xyz, quat wxyz, 29 joints] of the T-pose, facing +x, soles on z = 0."""
    return _g1_tpose()[0].copy()


def g1_tpose_body_poses() -> tuple[np.ndarray, np.ndarray]:
    """World poses of the G1 bodies (BODY_NAMES order) in the T-pose: (30, 3) m, (30, 4) wxyz."""
    _, pos, quat = _g1_tpose()
    return pos.copy(), quat.copy()


def alignment_offsets() -> dict[str, np.ndarray]:
    """O_ℓ = R_h(ℓ)ᵀ R_ℓ (wxyz) at the T-pose for every STYLE_LINKS entry (paper: R̂_ℓ = R_h(ℓ) O_ℓ)."""
    _, g1_quat = g1_tpose_body_poses()
    g1 = dict(zip(robot.BODY_NAMES, g1_quat, strict=True))
    # every human part frame has the same T-pose orientation (human_tpose), whatever the shape
    return {link: quat_mul(quat_conj(SMPLX_REST_QUAT_W), g1[link]) for link in STYLE_LINKS}
