"""Reference datasets: Holosoma/BeyondMimic layout, our extras, validation, atomic save."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from otr_gym import robot
from otr_gym.reference import ContactAnnotations, InvalidReferenceError, ObjectTrack, Reference
from otr_gym.rotations import quat_from_rotvec


def squat_qpos(T: int = 60) -> np.ndarray:
    """A squat with a yaw turn and a sidestep: every joint and root coordinate moves."""
    t = np.linspace(0, 1, T)
    q = np.tile(robot.default_qpos(), (T, 1))
    q[:, 0] = 0.3 * t
    q[:, 1] = 0.1 * np.sin(2 * np.pi * t)
    q[:, 2] = 0.76 - 0.2 * np.sin(np.pi * t)
    q[:, 3:7] = quat_from_rotvec(np.stack([0.05 * t, 0.1 * np.sin(np.pi * t), 1.2 * t], axis=1))
    q[:, 7:] += 0.3 * np.sin(2 * np.pi * t)[:, None] * np.linspace(-1, 1, 29)
    return q


def box_track(T: int) -> ObjectTrack:
    t = np.linspace(0, 1, T)
    pos = np.stack([0.5 + 0.2 * t, 0 * t, 0.2 + 0.5 * t], axis=1)
    quat = quat_from_rotvec(np.stack([0 * t, 0 * t, 0.5 * t], axis=1))
    return ObjectTrack("box", pos, quat, np.zeros_like(pos), np.zeros_like(pos),
                       mesh_vertices=np.random.default_rng(0).normal(size=(8, 3)),
                       mesh_faces=np.arange(12).reshape(4, 3) % 8)


@pytest.fixture(scope="module")
def reference() -> Reference:
    T = 60
    contacts = ContactAnnotations(("left_ankle_roll_link", "left_wrist_yaw_link"), ("ground", "box"),
                                  np.random.default_rng(1).uniform(-0.001, 0.3, (T, 2, 2)),
                                  np.random.default_rng(2).normal(size=(T, 2, 2, 3)))
    return Reference.from_qpos(squat_qpos(T), fps=50, objects=[box_track(T)], contacts=contacts,
                               metadata={"mode": "native", "scale": 1.0, "source": "test"}).with_recomputed_velocities()


def test_body_poses_are_forward_kinematics_of_the_joint_configuration(reference):
    pelvis = reference.body_index(["pelvis"])[0]
    assert np.allclose(reference.body_pos_w[:, pelvis], reference.root_pos_w)
    assert np.allclose(reference.body_quat_w[:, pelvis], reference.root_quat_w, atol=1e-12)
    torso = reference.body_index(["torso_link"])[0]
    assert np.all(reference.body_pos_w[:, torso, 2] > reference.root_pos_w[:, 2])  # torso above pelvis


def test_velocities_are_finite_differences_of_poses(reference):
    dt = 1 / reference.fps
    # central difference of a smooth track: ω·dt ≈ log(q_{t+1} q_{t-1}^-1)/2
    fd = (reference.body_pos_w[2:] - reference.body_pos_w[:-2]) / (2 * dt)
    assert np.abs(fd - reference.body_lin_vel_w[1:-1]).max() < 1e-9
    assert max(reference.velocity_consistency().values()) < 1e-9
    yaw_rate = reference.joint_vel[1:-1, 5]  # root angular velocity, world z
    assert np.allclose(yaw_rate, 1.2 / ((reference.num_frames - 1) * dt), rtol=0.05)


def test_save_then_load_gives_equal_arrays(reference, tmp_path):
    path = reference.save(tmp_path / "clip.npz")
    back = Reference.load(path)
    for key, value in reference.to_arrays().items():
        other = back.to_arrays()[key]
        assert other.shape == value.shape, key
        assert np.array_equal(other, value), key
    assert back.metadata == {"mode": "native", "scale": 1.0, "source": "test"}
    assert back.objects[0].name == "box" and back.contacts.channel_names == ("ground", "box")
    assert not list(tmp_path.glob("*.tmp"))  # atomic: no temporary left behind


def test_our_files_use_the_holosoma_keys_and_conventions(reference, tmp_path):
    path = reference.save(tmp_path / "clip.npz")
    with np.load(path) as npz:
        assert npz["fps"].dtype.kind == "i" and npz["fps"].tolist() == [50]
        assert npz["joint_pos"].shape == (60, 36) and npz["joint_vel"].shape == (60, 35)
        assert list(npz["joint_names"]) == list(robot.JOINT_NAMES)
        assert np.allclose(np.linalg.norm(npz["body_quat_w"], axis=-1), 1.0)
        assert npz["object_pos_w"].shape == (60, 3) and npz["object_quat_w"].shape == (60, 4)
        assert json.loads(str(npz["otr_metadata"]))["mode"] == "native"


def test_holosoma_references_load_unchanged(shared_data):
    for name, bodies, has_object in (("sub3_largebox_003_mj_w_obj.npz", 52, True),
                                     ("motion_crawl_slope.npz", 51, False)):
        path = shared_data / "references" / "holosoma" / name
        ref = Reference.load(path)
        with np.load(path) as raw:
            assert np.array_equal(ref.joint_pos, raw["joint_pos"])
            assert np.array_equal(ref.body_quat_w, raw["body_quat_w"])
        assert len(ref.body_names) == bodies and ref.fps == 50
        assert bool(ref.objects) == has_object
        assert np.allclose(ref.qpos()[:, 7:], ref.dof_pos)
    box = Reference.load(shared_data / "references" / "holosoma" / "sub3_largebox_003_mj_w_obj.npz")
    assert box.objects[0].name == "largebox"


def test_mjlab_layout_without_names_is_read_with_the_root_from_the_first_body(reference):
    arrays = reference.to_arrays()
    mj = {k: arrays[k] for k in ("fps", "body_pos_w", "body_quat_w", "body_lin_vel_w", "body_ang_vel_w")}
    mj["joint_pos"], mj["joint_vel"] = reference.dof_pos, reference.dof_vel
    back = Reference.from_arrays(mj, source="mjlab.npz")
    assert np.allclose(back.joint_pos, reference.joint_pos)


def test_resampling_to_50_fps_keeps_the_motion(reference):
    slow = reference.resampled(30.0)
    assert slow.num_frames == int(np.floor(reference.duration_s * 30 + 1e-9)) + 1
    back = slow.resampled(50.0)
    assert np.abs(back.root_pos_w - reference.root_pos_w[: back.num_frames]).max() < 5e-3


def test_a_subclip_holds_the_frames_of_every_series_and_saves_valid(reference, tmp_path):
    cut = reference.subclip(10, 40)
    assert cut.num_frames == 30 and cut.fps == reference.fps
    whole, part = reference.to_arrays(), cut.to_arrays()
    for key, value in whole.items():
        if value.ndim and value.shape[0] == reference.num_frames:  # time series: frames 10..39
            assert np.array_equal(part[key], value[10:40]), key
    assert np.array_equal(cut.objects[0].mesh_vertices, reference.objects[0].mesh_vertices)
    assert cut.contacts.witness_c.shape[0] == 30 and cut.metadata["subclip"] == [10, 40]
    assert cut.source == reference.source  # terrain and clip-list options keep applying
    back = Reference.load(cut.save(tmp_path / "cut.npz"))  # validates: every series 30 frames
    assert np.array_equal(back.root_pos_w, reference.root_pos_w[10:40])
    assert reference.subclip(55).num_frames == 5  # to the end
    for start, stop in ((-1, None), (59, None), (30, 30), (10, 61)):
        with pytest.raises(InvalidReferenceError, match=f"frames {start}:.*of its 60 frames"):
            reference.subclip(start, stop)


def _write(tmp_path: Path, arrays: dict, name: str = "bad.npz") -> Path:
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


MALFORMED = {
    "missing_keys": (lambda a: a.pop("body_quat_w"), "missing keys \\['body_quat_w'\\]"),
    "wrong_shape": (lambda a: a.__setitem__("joint_vel", a["joint_vel"][:, :30]), "joint_vel has shape"),
    "nan": (lambda a: a["joint_pos"].__setitem__((3, 9), np.nan), "joint_pos contains NaN"),
    "inf": (lambda a: a["body_pos_w"].__setitem__((5, 2, 1), np.inf), "body_pos_w contains NaN/inf"),
    "non_unit_quaternion": (lambda a: a["body_quat_w"].__setitem__((0, 3), [2.0, 0, 0, 0]), "not unit-norm"),
    "unknown_joint": (lambda a: a["joint_names"].__setitem__(4, "left_ankle_pitch_jnt"), "unknown joint names"),
    "zero_fps": (lambda a: a.__setitem__("fps", np.array([0])), "fps must be > 0"),
    "negative_fps": (lambda a: a.__setitem__("fps", np.array([-50])), "fps must be > 0"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_file_raises_an_error_naming_the_file_and_the_problem(case, reference, tmp_path):
    arrays = {k: np.array(v, copy=True) for k, v in reference.to_arrays().items()}
    arrays["joint_names"] = arrays["joint_names"].astype("<U32")
    mutate, message = MALFORMED[case]
    mutate(arrays)
    path = _write(tmp_path, arrays, f"{case}.npz")
    with pytest.raises(InvalidReferenceError, match=f"{case}.npz.*{message}"):
        Reference.load(path)


def test_missing_and_corrupt_files_are_named(tmp_path):
    with pytest.raises(InvalidReferenceError, match="nowhere.npz: no such reference file"):
        Reference.load(tmp_path / "nowhere.npz")
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"PK\x03\x04 definitely not a zip")
    with pytest.raises(InvalidReferenceError, match="corrupt.npz: not a NumPy .npz archive"):
        Reference.load(corrupt)


def test_a_failed_save_leaves_the_previous_file_intact(reference, tmp_path):
    path = reference.save(tmp_path / "clip.npz")
    before = path.read_bytes()
    broken = Reference.from_arrays(reference.to_arrays())
    broken.joint_pos = broken.joint_pos.copy()
    broken.joint_pos[0, 0] = np.nan
    with pytest.raises(InvalidReferenceError):
        broken.save(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.npz"]
