"""Demonstration readers (ours, AMASS, OMOMO) and the .npz round trip; real data from ../shared/data."""

from __future__ import annotations

import os
import pickle
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from otr_gym.rotations import quat_apply_inverse, quat_from_rotvec, quat_mul, quat_to_matrix, quat_to_rotvec
from retarget.inputs.demonstration import Demonstration, DemonstrationFileNotFoundError, InvalidDemonstrationError
from retarget.inputs.human import PART_NAMES, SMPLX_REST_QUAT_W, STYLE_LINKS, HumanModel, alignment_offsets, part_index
from retarget.inputs.meshes import load_mesh, signed_distance
from retarget.inputs.readers import INTERMIMIC_JOINTS, INTERMIMIC_OF_PART, load_demonstration
from retarget.inputs.synthetic import generate

OMOMO_CLIP = "omomo/sub3_largebox_003.pt"


@pytest.fixture(scope="module")
def carry() -> Demonstration:
    return generate("box_carry", seed=0)


@pytest.fixture(scope="module")
def largebox(shared_data: Path) -> Demonstration:
    return load_demonstration(shared_data / OMOMO_CLIP)


def _rewrite(path: Path, **changes) -> Path:
    """Copy of our .npz at ``path`` with arrays replaced (None deletes the key)."""
    with np.load(path) as npz:
        data = {k: npz[k] for k in npz.files}
    for key, value in changes.items():
        if value is None:
            del data[key]
        else:
            data[key] = value
    out = path.with_name(f"bad_{path.name}")
    np.savez(out, **data)
    return out


def _amass_file(path: Path, frames: int = 40, **overrides) -> Path:
    """A small AMASS-style SMPL-X parameter file: standing, turning about the vertical."""
    poses = np.zeros((frames, 165))
    yaw = np.linspace(0.0, 1.5, frames)
    root = quat_mul(quat_from_rotvec(yaw[:, None] * np.array([0.0, 0.0, 1.0])), SMPLX_REST_QUAT_W)
    poses[:, :3] = quat_to_rotvec(root)
    data = {"poses": poses, "trans": np.tile([0.3, -0.2, 0.9], (frames, 1)), "betas": np.zeros(16),
            "gender": np.array("neutral"), "mocap_framerate": np.array(120.0)}
    data.update(overrides)
    np.savez(path, **{k: v for k, v in data.items() if v is not None})
    return path


def _box_obj(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=(0.4, 0.4, 0.4)).export(path)
    return path


# ------------------------------------------------------------------ our format


def test_save_then_load_gives_back_every_field(carry, tmp_path):
    path = carry.save(tmp_path / "carry.npz")
    back = Demonstration.load(path)
    assert (back.name, back.fps, back.part_names, back.part_parents) == (
        carry.name, carry.fps, carry.part_names, carry.part_parents)
    np.testing.assert_array_equal(back.part_pos_w, carry.part_pos_w)
    np.testing.assert_array_equal(back.part_quat_w, carry.part_quat_w)
    np.testing.assert_array_equal(back.shape, carry.shape)
    assert back.stature_m == carry.stature_m and back.source == carry.source
    pieces = zip(back.surface.vertices + back.surface.faces, carry.surface.vertices + carry.surface.faces, strict=True)
    for a, b in pieces:
        np.testing.assert_array_equal(a, b)
    assert [(o.name, o.static, o.mesh_path) for o in back.objects] == [
        (o.name, o.static, o.mesh_path) for o in carry.objects]
    for a, b in zip(back.objects, carry.objects, strict=True):
        for key in ("vertices", "faces", "pos_w", "quat_w"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    assert back.annotations.keys() == carry.annotations.keys()
    for key, value in carry.annotations.items():
        np.testing.assert_array_equal(back.annotations[key], value)


def test_load_dispatches_our_format(carry, tmp_path):
    back = load_demonstration(carry.save(tmp_path / "carry.npz"))
    np.testing.assert_array_equal(back.part_pos_w, carry.part_pos_w)


def test_save_is_atomic_when_writing_fails(carry, tmp_path, monkeypatch):
    path = carry.save(tmp_path / "carry.npz")
    before = path.read_bytes()

    def broken(*_, **__):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", broken)  # the data is written, then the disk fails
    with pytest.raises(OSError, match="disk full"):
        carry.save(path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["carry.npz"]


def test_save_refuses_an_invalid_demonstration(carry, tmp_path):
    bad = replace(carry, fps=0.0)
    with pytest.raises(InvalidDemonstrationError, match="fps"):
        bad.save(tmp_path / "bad.npz")
    assert not (tmp_path / "bad.npz").exists()


@pytest.mark.parametrize("key, value, message", [
    ("part_pos_w", None, "missing keys"),
    ("part_quat_w", np.zeros((3, 22, 4)), "part_quat_w must have shape"),
    ("fps", np.array(-30.0), "fps must be a positive"),
    ("stature_m", np.array(7.0), "not a human stature"),
    ("format", np.array("something-else"), "format tag"),
    ("surface_vertex_counts", np.array([1, 2, 3]), "do not add up"),
    ("source_json", np.array("{not json"), "not valid JSON"),
])
def test_load_rejects_a_broken_file_naming_it(carry, tmp_path, key, value, message):
    bad = _rewrite(carry.save(tmp_path / "carry.npz"), **{key: value})
    with pytest.raises(InvalidDemonstrationError, match=message) as info:
        Demonstration.load(bad)
    assert str(bad) in str(info.value)


def test_load_rejects_nan_and_non_unit_quaternions(carry, tmp_path):
    path = carry.save(tmp_path / "carry.npz")
    pos = carry.part_pos_w.copy()
    pos[5, 3, 1] = np.nan
    with pytest.raises(InvalidDemonstrationError, match=r"part_pos_w contains NaN.*\(5, 3, 1\)"):
        Demonstration.load(_rewrite(path, part_pos_w=pos))
    quat = carry.part_quat_w.copy()
    quat[2, 7] *= 1.1
    with pytest.raises(InvalidDemonstrationError, match="not unit-norm"):
        Demonstration.load(_rewrite(path, part_quat_w=quat))
    box_quat = carry.objects[0].quat_w * 2.0
    with pytest.raises(InvalidDemonstrationError, match="object 'box' quat_w is not unit-norm"):
        Demonstration.load(_rewrite(path, object0_quat_w=box_quat))


def test_missing_file_raises_file_not_found_naming_it(tmp_path):
    missing = tmp_path / "nowhere.npz"
    for reader in (load_demonstration, Demonstration.load):
        with pytest.raises(FileNotFoundError, match="nowhere.npz"):
            reader(missing)


def test_unknown_formats_and_corrupt_files_are_rejected(tmp_path):
    (tmp_path / "clip.fbx").write_text("Kaydara FBX Binary")
    with pytest.raises(InvalidDemonstrationError, match=r"clip.fbx.*unknown demonstration format"):
        load_demonstration(tmp_path / "clip.fbx")
    (tmp_path / "clip.bvh").write_text("HIERARCHY")
    with pytest.raises(InvalidDemonstrationError, match=r"clip.bvh:1: file ends where ROOT was expected"):
        load_demonstration(tmp_path / "clip.bvh")
    np.savez(tmp_path / "other.npz", weights=np.zeros(3))
    with pytest.raises(InvalidDemonstrationError, match=r"other.npz.*unknown .npz layout"):
        load_demonstration(tmp_path / "other.npz")
    (tmp_path / "corrupt.npz").write_bytes(b"PK\x03\x04 definitely not a zip")
    with pytest.raises(InvalidDemonstrationError, match=r"corrupt.npz: not a NumPy .npz archive \(truncated"):
        load_demonstration(tmp_path / "corrupt.npz")


# ------------------------------------------------------------------ AMASS (generated files)


def test_amass_root_rotation_turns_the_body_about_its_pelvis(tmp_path):
    demo = load_demonstration(_amass_file(tmp_path / "turn_stageii.npz"), ground=False)
    pelvis = demo.part_pos_w[:, 0]
    np.testing.assert_allclose(pelvis, np.broadcast_to(pelvis[0], pelvis.shape), atol=1e-6)
    np.testing.assert_allclose(pelvis[0], [0.3, -0.2, 0.9] + HumanModel().rest_joints[0], atol=1e-6)
    assert demo.source["format"] == "amass-smplx" and demo.fps == 120.0


def test_amass_grounding_puts_the_median_lowest_point_on_the_floor(tmp_path):
    demo = load_demonstration(_amass_file(tmp_path / "turn_stageii.npz"))
    lowest = demo.surface.lowest_z(demo.part_pos_w, demo.part_quat_w)
    assert np.median(lowest) == pytest.approx(0.0, abs=1e-9)
    assert demo.source["ground_shift_m"] != 0.0


def test_amass_split_keys_layout_reads_like_poses(tmp_path):
    packed = load_demonstration(_amass_file(tmp_path / "a.npz"))
    poses = np.load(tmp_path / "a.npz")["poses"]
    split = _amass_file(tmp_path / "b.npz", poses=None, root_orient=poses[:, :3], pose_body=poses[:, 3:66],
                        pose_jaw=np.zeros((len(poses), 3)), mocap_framerate=None, mocap_frame_rate=np.array(120.0))
    np.testing.assert_allclose(load_demonstration(split).part_pos_w, packed.part_pos_w)


@pytest.mark.parametrize("overrides, message", [
    ({"poses": np.zeros((40, 100))}, r"\(T, 165\).*\(T, 156\)"),
    ({"trans": np.zeros((39, 3))}, "trans must have shape"),
    ({"trans": None}, "root translation"),
    ({"betas": np.zeros(4)}, "betas has 4 values"),
    ({"mocap_framerate": np.array(0.0)}, "frame rate must be one positive number"),
    ({"poses": np.full((40, 165), np.nan)}, "NaN"),
])
def test_amass_bad_input_raises_naming_the_file(tmp_path, overrides, message):
    path = _amass_file(tmp_path / "bad_stageii.npz", **overrides)
    with pytest.raises(InvalidDemonstrationError, match=message) as info:
        load_demonstration(path)
    assert "bad_stageii.npz" in str(info.value)


# ------------------------------------------------------------------ OMOMO (generated files)


@pytest.mark.parametrize("tensor, message", [
    (torch.zeros(10, 100), r"expected an InterMimic tensor"),
    ({"motion": torch.zeros(10, 591)}, "expected one tensor"),
    (torch.full((10, 591), float("nan")), "NaN"),
])
def test_omomo_bad_tensor_raises_naming_the_file(tmp_path, tensor, message):
    _box_obj(tmp_path / "objects" / "largebox.obj")
    path = tmp_path / "sub1_largebox_000.pt"
    torch.save(tensor, path)
    with pytest.raises(InvalidDemonstrationError, match=message) as info:
        load_demonstration(path)
    assert str(path) in str(info.value)


def _minimal_omomo_tensor(frames: int = 12) -> torch.Tensor:
    """An InterMimic-layout tensor that reads: identity orientations, distinct joint positions."""
    x = torch.zeros(frames, 591)
    x[:, 383:591] = torch.tensor([0.0, 0.0, 0.0, 1.0]).repeat(52)  # identity body orientations (xyzw)
    x[:, 321:325] = torch.tensor([0.0, 0.0, 0.0, 1.0])
    x[:, 162:318] = torch.arange(156, dtype=torch.float32) * 1e-3
    return x


@pytest.mark.parametrize("tensor", [
    torch.arange(12, dtype=torch.float64).reshape(3, 4).T,  # strided
    torch.arange(10, dtype=torch.float32)[3:],  # offset into its storage
    torch.zeros(0, 5), torch.tensor(3.0), torch.arange(6)[::2],
    torch.ones(4, 591, requires_grad=True),  # as OMOMO's files are saved
])
def test_a_saved_tensor_reads_without_torch_as_torch_reads_it(tmp_path, tensor):
    from retarget.inputs.torch_file import read_tensor

    path = tmp_path / "x.pt"
    torch.save(tensor, path)
    x = read_tensor(path)
    expected = tensor.detach().numpy()
    assert x.dtype == expected.dtype and x.shape == expected.shape and np.array_equal(x, expected)


@pytest.mark.parametrize("content", [{"motion": torch.zeros(2)}, [torch.zeros(2)],
                                     torch.zeros(2, dtype=torch.bfloat16)])
def test_anything_but_one_plain_tensor_is_left_to_torch(tmp_path, content):
    from retarget.inputs.torch_file import read_tensor

    torch.save(content, tmp_path / "x.pt")
    assert read_tensor(tmp_path / "x.pt") is None
    torch.save(torch.zeros(2), tmp_path / "legacy.pt", _use_new_zipfile_serialization=False)
    assert read_tensor(tmp_path / "legacy.pt") is None
    (tmp_path / "garbage.pt").write_bytes(b"\x00garbage")
    assert read_tensor(tmp_path / "garbage.pt") is None


def test_omomo_clips_read_without_torch_as_torch_reads_them(shared_data):
    from retarget.inputs.torch_file import read_tensor

    for path in sorted((shared_data / "omomo").glob("*.pt")):
        expected = torch.load(path, weights_only=True).detach().numpy()
        assert np.array_equal(read_tensor(path), expected), path.name


def test_omomo_corrupt_file_and_missing_mesh_are_reported(tmp_path):
    corrupt = tmp_path / "sub1_largebox_000.pt"
    corrupt.write_bytes(b"\x00garbage")
    with pytest.raises(InvalidDemonstrationError, match="not a readable torch tensor file"):
        load_demonstration(corrupt, object_mesh=_box_obj(tmp_path / "box.obj"))
    clip = tmp_path / "sub1_largebox_001.pt"
    torch.save(_minimal_omomo_tensor(), clip)
    with pytest.raises(DemonstrationFileNotFoundError, match=r"object mesh for 'largebox' not found"):
        load_demonstration(clip)
    with pytest.raises(DemonstrationFileNotFoundError, match="no_such.obj"):
        load_demonstration(clip, object_mesh=tmp_path / "no_such.obj")


def test_omomo_missing_mesh_beside_a_relative_clip_lists_its_one_candidate_once_and_says_how_to_pass_it(
        tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # "sub1_largebox_001.pt": the clip's folder and its parent are both "."
    torch.save(_minimal_omomo_tensor(), tmp_path / "sub1_largebox_001.pt")
    with pytest.raises(DemonstrationFileNotFoundError) as error:
        load_demonstration("sub1_largebox_001.pt")
    message = str(error.value)
    assert message.count("objects/largebox.obj") == 1, message
    assert "object_mesh=" in message and "--object" in message


def test_omomo_unusable_object_mesh_is_reported_with_both_files(tmp_path):
    torch.save(torch.zeros(12, 591), tmp_path / "sub1_largebox_002.pt")
    (tmp_path / "empty.obj").write_text("# no triangles here\n")
    with pytest.raises(InvalidDemonstrationError, match=r"sub1_largebox_002.pt: object mesh unusable: .*empty.obj"):
        load_demonstration(tmp_path / "sub1_largebox_002.pt", object_mesh=tmp_path / "empty.obj")


def test_subject_heights_loader_refuses_code_in_the_pickle(tmp_path):
    pt = tmp_path / "sub3_largebox_003.pt"
    torch.save(_minimal_omomo_tensor(), pt)
    (tmp_path / "subject_heights.pkl").write_bytes(pickle.dumps({"sub3": os.system}))
    with pytest.raises(InvalidDemonstrationError, match=r"subject_heights.pkl.*refusing to load"):
        load_demonstration(pt, object_mesh=_box_obj(tmp_path / "box.obj"))


# ------------------------------------------------------------------ OMOMO (real clip)


def test_omomo_posed_joints_reproduce_the_files_joints(shared_data):
    """Measured: mean 8.1 mm, max 21.5 mm over 196 frames × 22 joints."""
    demo = load_demonstration(shared_data / OMOMO_CLIP, ground=False)
    x = torch.load(shared_data / OMOMO_CLIP, weights_only=True).detach().numpy().astype(np.float64)
    columns = [INTERMIMIC_JOINTS.index(n) for n in INTERMIMIC_OF_PART]
    error = np.linalg.norm(demo.part_pos_w - x[:, 162:318].reshape(-1, 52, 3)[:, columns], axis=-1)
    assert error.mean() < 0.010
    assert error.max() < 0.030
    assert demo.source["joint_fit_mean_m"] == pytest.approx(error.mean(), abs=1e-9)


def test_omomo_largebox_sits_between_the_hands_while_carried(largebox):
    box = largebox.objects[0]
    mesh = load_mesh(box.mesh_path)
    carried = box.pos_w[:, 2] > box.pos_w[0, 2] + 0.05
    assert carried.sum() > 100 and largebox.annotations["object_contact"][carried].all()
    vertices = largebox.human_vertices_w(carried)
    wrists = {}
    for side in ("L", "R"):
        k = PART_NAMES.index(f"{side}_Wrist")
        wrists[side] = quat_apply_inverse(box.quat_w[carried], largebox.part_pos_w[carried, k] - box.pos_w[carried])
        wrist_d, _, _ = signed_distance(mesh, wrists[side])
        assert np.all((wrist_d > 0.005) & (wrist_d < 0.08)), side  # the wrist is just outside the box
        hand = quat_apply_inverse(box.quat_w[carried][:, None],
                                  vertices[:, largebox.surface.vertex_part == k] - box.pos_w[carried][:, None])
        hand_d, _, _ = signed_distance(mesh, hand.reshape(-1, 3))
        nearest = hand_d.reshape(len(hand), -1).min(axis=1)
        # the rigid relaxed hand touches; its curled fingers sink up to 6 cm (the file's own fingertips: 4 cm)
        assert np.all((nearest < 0.02) & (nearest > -0.07)), side
    centre = mesh.vertices.mean(axis=0)
    a, b = wrists["L"] - centre, wrists["R"] - centre
    cosine = np.sum(a * b, axis=-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    assert np.all(cosine < -0.5)  # on opposite sides of the box


def test_omomo_stature_comes_from_subject_heights_and_the_fit_agrees(largebox):
    assert largebox.stature_m == pytest.approx(1.9411, abs=1e-4)
    assert largebox.source["stature_source"] == "subject_heights.pkl"
    assert abs(largebox.source["model_stature_m"] - largebox.stature_m) < 0.03


def test_omomo_subject_is_grounded_and_the_box_starts_on_the_floor(largebox):
    lowest = largebox.surface.lowest_z(largebox.part_pos_w, largebox.part_quat_w)
    assert np.median(lowest) == pytest.approx(0.0, abs=1e-9)
    assert np.all(np.abs(lowest) < 0.02)
    assert largebox.source["ground_shift_m"] == pytest.approx(-0.048, abs=0.005)
    box = largebox.objects[0]
    assert abs(box.posed_vertices([0])[0, :, 2].min()) < 0.01


def test_omomo_upright_trunk_gives_upright_g1_pelvis_and_torso_targets(largebox):
    """Frames where the joints put the neck above the pelvis (within 10°); the targets come from the
    quaternions, so this cross-checks the frame change. Measured: pelvis ≤ 15°, torso ≤ 27°."""
    trunk = largebox.part_pos_w[:, PART_NAMES.index("Neck")] - largebox.part_pos_w[:, 0]
    upright = np.degrees(np.arccos(trunk[:, 2] / np.linalg.norm(trunk, axis=-1))) < 10.0
    assert upright.sum() > 40
    offsets = alignment_offsets()
    for link in ("pelvis", "torso_link"):
        part = part_index([STYLE_LINKS[link]])[0]
        target = quat_mul(largebox.part_quat_w[upright, part], offsets[link])
        tilt = np.degrees(np.arccos(quat_to_matrix(target)[:, 2, 2]))
        assert np.median(tilt) < 20.0 and tilt.max() < 30.0, link


# ------------------------------------------------------------------ AMASS (real clips)


def test_amass_smplx_squat_pelvis_goes_from_0p79_to_0p40_m(shared_data):
    demo = load_demonstration(shared_data / "amass/smplx_steps_deep_squat.npz", ground=False)
    pelvis_z = demo.part_pos_w[:, 0, 2]
    assert pelvis_z[0] == pytest.approx(0.80, abs=0.02)
    assert pelvis_z.min() == pytest.approx(0.40, abs=0.02)
    assert 1.55 < demo.stature_m < 1.80 and demo.fps == 120.0


def test_amass_planted_feet_do_not_slide_in_the_squat_clip(shared_data):
    """With the root turned about the origin instead of the pelvis they slide at ~0.27 m/s."""
    demo = load_demonstration(shared_data / "amass/smplx_steps_deep_squat.npz")
    speeds = []
    for side in ("L", "R"):
        ankle = demo.part_pos_w[:, PART_NAMES.index(f"{side}_Ankle")]
        speed = np.linalg.norm(np.diff(ankle[:, :2], axis=0), axis=-1) * demo.fps
        low = ankle[1:, 2] < np.percentile(ankle[:, 2], 30)
        speeds.append(np.median(speed[low]))
    assert max(speeds) < 0.10


def test_amass_smplh_walk_has_a_plausible_body_on_the_floor(shared_data):
    demo = load_demonstration(shared_data / "amass/smplh_walk_jog_turn.npz")
    assert demo.source["format"] == "amass-smplh"
    assert 1.55 < demo.stature_m < 1.85
    assert 0.80 < demo.part_pos_w[0, 0, 2] < 1.0  # standing pelvis height
    lowest = demo.surface.lowest_z(demo.part_pos_w, demo.part_quat_w)
    assert np.median(lowest) == pytest.approx(0.0, abs=1e-9)
    assert np.percentile(lowest, 5) > -0.03
    travelled = np.linalg.norm(demo.part_pos_w[-1, 0, :2] - demo.part_pos_w[0, 0, :2])
    assert travelled > 1.5
