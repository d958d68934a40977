"""BVH reader: parsing and forward kinematics against hand-computed positions, skeleton families,
units and up-axis detection, the body fit, and a clear error for every kind of bad file."""

from __future__ import annotations

import re

import numpy as np
import pytest

from otr_gym.rotations import quat_error_angle, quat_to_matrix
from retarget.inputs.bvh import BvhError, BvhOptions, detect_units, read_bvh
from retarget.inputs.bvh_file import parse_bvh, world_transforms
from retarget.inputs.human import PART_NAMES, PART_PARENTS, SMPLX_REST_QUAT_W
from retarget.inputs.readers import load_demonstration
from retarget.inputs.skeletons import FAMILIES, match_family

# A stick figure in centimetres, y up, facing +z, T-pose: SMPL-X part -> offset from its parent.
STICK_CM = {
    "Pelvis": (0.0, 0.0, 0.0), "L_Hip": (9.0, -8.0, 0.0), "R_Hip": (-9.0, -8.0, 0.0), "Spine1": (0.0, 10.0, 0.0),
    "L_Knee": (0.0, -40.0, 0.0), "R_Knee": (0.0, -40.0, 0.0), "Spine2": (0.0, 13.0, 0.0),
    "L_Ankle": (0.0, -42.0, 0.0), "R_Ankle": (0.0, -42.0, 0.0), "Spine3": (0.0, 6.0, 0.0),
    "L_Foot": (0.0, -6.0, 12.0), "R_Foot": (0.0, -6.0, 12.0), "Neck": (0.0, 17.0, 0.0),
    "L_Collar": (4.0, 8.0, 0.0), "R_Collar": (-4.0, 8.0, 0.0), "Head": (0.0, 15.0, 0.0),
    "L_Shoulder": (12.0, 4.0, 0.0), "R_Shoulder": (-12.0, 4.0, 0.0), "L_Elbow": (26.0, 0.0, 0.0),
    "R_Elbow": (-26.0, 0.0, 0.0), "L_Wrist": (25.0, 0.0, 0.0), "R_Wrist": (-25.0, 0.0, 0.0),
}
END_SITES_CM = {"L_Foot": (0.0, 0.0, 5.0), "R_Foot": (0.0, 0.0, 5.0), "Head": (0.0, 15.0, 0.0),
                "L_Wrist": (8.0, 0.0, 0.0), "R_Wrist": (-8.0, 0.0, 0.0)}
ROOT_CM = (10.0, 95.0, -5.0)


def family_names(family: str) -> dict[str, str]:
    """Part -> joint name of a family (its first candidate; parts it may lack are left out)."""
    names = {}
    for part, candidates in FAMILIES[family].items():
        first = candidates[0]
        if first != "?" and "/" not in first:
            names[part] = ("mixamorig:" + first) if family == "Mixamo" else first
    return names


def stick_bvh(family: str = "LAFAN1 / Ubisoft", frames=None, scale: float = 1.0, up: str = "y",
              order: str = "Zrotation Xrotation Yrotation", names: dict[str, str] | None = None) -> str:
    """BVH text of the stick figure in ``family``'s names. ``frames``: list of {part: (rz, rx, ry)}
    and optional "root": (x, y, z) in cm (y-up), default one T-pose frame. ``up="z"`` writes the
    same motion turned into a z-up file."""
    names = names or family_names(family)
    turn = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float) if up == "z" else np.eye(3)  # y -> z
    children = {p: [c for c in PART_NAMES if c in names and _mapped_parent(c, names) == p] for p in PART_NAMES}
    lines, order_parts = ["HIERARCHY"], []

    def offset(part: str) -> np.ndarray:
        total, k = np.array(STICK_CM[part]), PART_NAMES.index(part)
        parent = PART_PARENTS[k]
        while parent >= 0 and PART_NAMES[parent] not in names:  # a skipped part's bone joins its child's
            total = total + np.array(STICK_CM[PART_NAMES[parent]])
            parent = PART_PARENTS[parent]
        return turn @ total * scale

    def joint(part: str, depth: int) -> None:
        pad = "  " * depth
        kind = "ROOT" if part == "Pelvis" else "JOINT"
        lines.append(f"{pad}{kind} {names[part]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {' '.join(f'{v:g}' for v in offset(part))}")
        channels = f"Xposition Yposition Zposition {order}" if part == "Pelvis" else order
        lines.append(f"{pad}  CHANNELS {len(channels.split())} {channels}")
        order_parts.append(part)
        for child in children[part]:
            joint(child, depth + 1)
        if part in END_SITES_CM:
            lines.extend([f"{pad}  End Site", f"{pad}  {{",
                          f"{pad}    OFFSET {' '.join(f'{v:g}' for v in turn @ np.array(END_SITES_CM[part]) * scale)}",
                          f"{pad}  }}"])
        lines.append(f"{pad}}}")

    joint("Pelvis", 0)
    frames = frames or [{}]
    lines += ["MOTION", f"Frames: {len(frames)}", "Frame Time: 0.0333333"]
    for frame in frames:
        root = turn @ np.array(frame.get("root", ROOT_CM)) * scale
        values = list(root)
        for part in order_parts:
            angles = dict(zip(("Zrotation", "Xrotation", "Yrotation"), frame.get(part, (0.0, 0.0, 0.0)), strict=True))
            if up == "z" and part == "Pelvis":  # the z-up file's root turns about its own up axis
                angles = {"Zrotation": angles["Yrotation"], "Xrotation": angles["Xrotation"],
                          "Yrotation": -angles["Zrotation"]}
            values += [angles[c] for c in order.split()]
        lines.append(" ".join(f"{v:g}" for v in values))
    return "\n".join(lines) + "\n"


def _mapped_parent(part: str, names: dict[str, str]) -> str | None:
    parent = PART_PARENTS[PART_NAMES.index(part)]
    while parent >= 0 and PART_NAMES[parent] not in names:
        parent = PART_PARENTS[parent]
    return PART_NAMES[parent] if parent >= 0 else None


def write(tmp_path, text: str, name: str = "clip.bvh"):
    path = tmp_path / name
    path.write_text(text)
    return path


# ------------------------------------------------------------------ parsing and kinematics


@pytest.mark.parametrize("family", list(FAMILIES))
def test_each_family_is_recognised_with_its_rest_pose_and_a_posed_frame(tmp_path, family):
    frames = [{}, {"root": (10.0, 90.0, -5.0), "Pelvis": (0.0, 0.0, 90.0), "L_Knee": (0.0, 90.0, 0.0)}]
    bvh = parse_bvh(write(tmp_path, stick_bvh(family, frames)))
    found, mapping = match_family(bvh)
    assert found == family
    names = family_names(family)
    at = {part: mapping[part].joint for part in names}
    rest, _ = world_transforms(bvh, rest=True)
    # rest pose: sums of offsets (root at its OFFSET, 0)
    np.testing.assert_allclose(rest[0, at["L_Knee"]], [9.0, -48.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(rest[0, at["L_Shoulder"]], [16.0, 41.0, 0.0], atol=1e-9)
    pos, _ = world_transforms(bvh)
    # frame 1 by hand: Ry(90°) takes (x, y, z) to (z, y, -x); the knee's Rx(90°) takes (0, -42, 0)
    # to (0, 0, -42), which the root turns to (-42, 0, 0)
    np.testing.assert_allclose(pos[1, at["L_Hip"]], [10.0, 82.0, -14.0], atol=1e-9)
    np.testing.assert_allclose(pos[1, at["L_Knee"]], [10.0, 42.0, -14.0], atol=1e-9)
    np.testing.assert_allclose(pos[1, at["L_Ankle"]], [-32.0, 42.0, -14.0], atol=1e-9)
    np.testing.assert_allclose(pos[1, at["L_Shoulder"]], [10.0, 131.0, -21.0], atol=1e-9)


def test_rotation_channels_compose_in_the_listed_order(tmp_path):
    text = ("HIERARCHY\nROOT a\n{\n OFFSET 0 0 0\n CHANNELS 3 Zrotation Xrotation Yrotation\n"
            " JOINT b\n {\n  OFFSET 0 1 0\n  CHANNELS 0\n  End Site\n  {\n   OFFSET 0 1 0\n  }\n }\n}\n"
            "MOTION\nFrames: 1\nFrame Time: 0.01\n90 90 0\n")
    pos, _ = world_transforms(parse_bvh(write(tmp_path, text)))
    # Rz(90) Rx(90) (0, 1, 0) = Rz(90) (0, 0, 1) = (0, 0, 1); the other order would give (-1, 0, 0)
    np.testing.assert_allclose(pos[0, 1], [0.0, 0.0, 1.0], atol=1e-12)


def test_position_channels_replace_the_offset(tmp_path):
    text = ("HIERARCHY\nROOT a\n{\n OFFSET 0 0 0\n CHANNELS 3 Xposition Yposition Zposition\n"
            " JOINT b\n {\n  OFFSET 5 5 5\n  CHANNELS 3 Xposition Yposition Zposition\n"
            "  End Site\n  {\n   OFFSET 0 1 0\n  }\n }\n}\nMOTION\nFrames: 1\nFrame Time: 0.01\n1 2 3 5 5 5\n")
    pos, _ = world_transforms(parse_bvh(write(tmp_path, text)))
    np.testing.assert_allclose(pos[0], [[1.0, 2.0, 3.0], [6.0, 7.0, 8.0]])


def test_a_brace_on_the_declaration_line_reads_as_on_its_own_line(tmp_path):
    """``ROOT Hips {``, ``JOINT X {``, ``JOINT X{`` and ``End Site {`` as some exporters write them."""
    frames = [{}, {"root": (10.0, 90.0, -5.0), "Pelvis": (0.0, 0.0, 90.0), "L_Knee": (0.0, 90.0, 0.0)}]
    own_line = stick_bvh(frames=frames)
    same_line = re.sub(r"^(\s*(?:ROOT|JOINT|End)\b[^\n]*)\n\s*\{$", r"\1 {", own_line, flags=re.M)
    same_line = same_line.replace("JOINT leftleg {", "JOINT leftleg{")
    assert "ROOT hips {" in same_line and "End Site {" in same_line and "JOINT leftleg{" in same_line
    a = parse_bvh(write(tmp_path, own_line, "own_line.bvh"))
    b = parse_bvh(write(tmp_path, same_line, "same_line.bvh"))
    assert b.joint_names == a.joint_names and b.parents == a.parents and b.channels == a.channels
    assert b.end_sites.keys() == a.end_sites.keys()
    np.testing.assert_array_equal(b.offsets, a.offsets)
    np.testing.assert_array_equal(b.motion, a.motion)


# ------------------------------------------------------------------ units and up axis


@pytest.mark.parametrize(("per_cm", "unit"), [(1.0, "centimetres"), (0.01, "metres"), (10.0, "millimetres"),
                                              (1 / 2.54, "inches"), (0.45 / 2.54, "CMU ASF units (1/0.45 inch)")])
def test_units_are_detected_from_the_body_size(tmp_path, per_cm, unit):
    demo = read_bvh(write(tmp_path, stick_bvh(scale=per_cm, frames=[{}, {}])), BvhOptions(quiet=True))
    info = demo.source["bvh"]
    assert info["units"] == unit
    assert info["metres_per_unit"] * per_cm == pytest.approx(0.01, rel=1e-9)


def test_a_body_of_no_plausible_size_is_scaled_to_a_typical_stature():
    name, scale = detect_units(17.0)  # 17 units tall: 1.7 m in dm would be 'decimetres'
    assert name == "decimetres" and scale == 0.1
    name, scale = detect_units(5000.0)  # 5000 units: 50 m in cm, 5 m in mm: nothing fits
    assert name.startswith("unknown") and 5000.0 * scale == pytest.approx(1.70)


@pytest.mark.parametrize("up", ["y", "z"])
def test_the_up_axis_is_detected_and_both_files_give_the_same_body(tmp_path, up):
    frames = [{}, {"Pelvis": (0.0, 0.0, 30.0), "L_Knee": (0.0, 40.0, 0.0), "L_Hip": (0.0, -30.0, 0.0)}]
    demo = read_bvh(write(tmp_path, stick_bvh(frames=frames, up=up)), BvhOptions(quiet=True))
    assert demo.source["bvh"]["up_axis"] == up
    reference = read_bvh(write(tmp_path, stick_bvh(frames=frames, up="y"), "y.bvh"), BvhOptions(quiet=True))
    # the same motion lands in the same z-up world up to a turn about z (y-up: +z -> +x)
    height = demo.part_pos_w[..., 2] - demo.part_pos_w[:, :1, 2]
    np.testing.assert_allclose(height, reference.part_pos_w[..., 2] - reference.part_pos_w[:, :1, 2], atol=1e-6)


def test_units_and_up_overrides_are_used_and_stated(tmp_path, capsys):
    demo = read_bvh(write(tmp_path, stick_bvh(frames=[{}, {}])), BvhOptions(units="cm", up="y"))
    statement = capsys.readouterr().err
    assert "units centimetres (given)" in statement and "up axis y (given)" in statement
    assert "skeleton LAFAN1 / Ubisoft" in statement and "stature" in statement and "joint error" in statement
    assert demo.source["bvh"]["statement"] in statement


# ------------------------------------------------------------------ the body


def test_a_tpose_frame_gives_smplx_tpose_orientations_and_feet_on_the_floor(tmp_path):
    bent = {"L_Knee": (0.0, 50.0, 0.0), "R_Knee": (0.0, 50.0, 0.0), "L_Hip": (0.0, -40.0, 0.0),
            "R_Hip": (0.0, -40.0, 0.0), "L_Elbow": (0.0, 0.0, -60.0), "R_Elbow": (0.0, 0.0, 60.0)}
    frames = [{}] * 6 + [bent] * 2
    demo = load_demonstration(write(tmp_path, stick_bvh(frames=frames)), bvh=BvhOptions(quiet=True))
    tpose = demo.part_quat_w[0]

    def angles(parts):
        k = [PART_NAMES.index(p) for p in parts]
        return dict(zip(parts, np.degrees(quat_error_angle(tpose[k], SMPLX_REST_QUAT_W)).round(1), strict=True))

    # facing +x like SMPLX_REST_QUAT_W, up to the angles between the stick's bones and SMPL-X's
    # (its arms are horizontal, SMPL-X's 16° lower; its thighs vertical, SMPL-X's 8° apart)
    legs_trunk = angles(("Pelvis", "L_Hip", "R_Hip", "L_Knee", "R_Knee", "Spine1", "Spine2", "Spine3", "Neck"))
    arms = angles(("L_Shoulder", "R_Shoulder", "L_Elbow", "R_Elbow"))
    assert max(legs_trunk.values()) < 12.0 and max(arms.values()) < 25.0, (legs_trunk, arms)
    # feet flat: the SMPL-X foot's up axis (y) points up (its heading follows the stick's toes)
    for foot in ("L_Ankle", "R_Ankle", "L_Foot", "R_Foot"):
        up = quat_to_matrix(tpose[PART_NAMES.index(foot)])[:, 1]
        assert np.degrees(np.arccos(min(up[2], 1.0))) < 3.0, foot
    lowest = demo.surface.lowest_z(demo.part_pos_w, demo.part_quat_w)
    assert np.median(lowest) == pytest.approx(0.0, abs=1e-9)
    assert 1.6 < demo.stature_m < 1.9  # the stick is 1.75 m from sole to crown
    assert demo.source["joint_fit_mean_m"] < 0.05


# ------------------------------------------------------------------ bad files


def test_a_truncated_motion_block_names_the_file_and_the_frame_count(tmp_path):
    lines = stick_bvh(frames=[{}] * 5).splitlines()
    path = write(tmp_path, "\n".join(lines[:-2]) + "\n")
    with pytest.raises(BvhError, match=rf"{path}:\d+: MOTION declares 5 frames but the file ends after 3"):
        parse_bvh(path)


def test_a_line_cut_short_is_a_channel_count_mismatch_on_that_line(tmp_path):
    text = stick_bvh(frames=[{}] * 3)
    lines = text.splitlines()
    lines[-1] = " ".join(lines[-1].split()[:20])
    path = write(tmp_path, "\n".join(lines))
    with pytest.raises(BvhError, match=rf"{path}:{len(lines)}: frame 2 has 20 values but the HIERARCHY declares "
                                       r"\d+ channels \(the file's last line: truncated\?\)"):
        parse_bvh(path)


def test_a_channels_line_whose_count_disagrees_names_the_joint_and_line(tmp_path):
    lines = stick_bvh().splitlines()
    k = next(i for i, line in enumerate(lines) if "CHANNELS 3" in line)
    joint = lines[k - 3].split()[-1]
    lines[k] = lines[k].replace("CHANNELS 3", "CHANNELS 4")
    path = write(tmp_path, "\n".join(lines))
    with pytest.raises(BvhError, match=rf"{path}:{k + 1}: joint {joint}: CHANNELS declares 4 channels but lists 3"):
        parse_bvh(path)


def test_a_non_finite_value_names_the_line_joint_and_channel(tmp_path):
    lines = stick_bvh(frames=[{}] * 3).splitlines()
    values = lines[-2].split()
    values[4] = "nan"  # root channels: X Y Z position, then Z X Y rotation -> column 5 is Xrotation
    lines[-2] = " ".join(values)
    path = write(tmp_path, "\n".join(lines))
    with pytest.raises(BvhError, match=rf"{path}:{len(lines) - 1}: frame 1, column 5 \(joint hips, Xrotation\): "
                                       r"non-finite value 'nan'"):
        parse_bvh(path)


def test_an_unknown_skeleton_asks_for_a_map_and_a_map_reads_it(tmp_path):
    names = {part: f"bone_{i}" for i, part in enumerate(PART_NAMES)}
    path = write(tmp_path, stick_bvh(names=names, frames=[{}, {}]))
    with pytest.raises(BvhError, match=rf"{path}: skeleton not recognised \(joints: bone_0, .*--skeleton-map"):
        load_demonstration(path, bvh=BvhOptions(quiet=True))
    skeleton_map = tmp_path / "map.yaml"
    skeleton_map.write_text("\n".join(f"{part}: {name}" for part, name in names.items()))
    demo = load_demonstration(path, bvh=BvhOptions(skeleton_map=str(skeleton_map), quiet=True))
    assert demo.source["bvh"]["family"] == f"map {skeleton_map}" and demo.num_frames == 2


def test_a_map_with_an_unknown_part_or_joint_names_both_files(tmp_path):
    path = write(tmp_path, stick_bvh(frames=[{}, {}]))
    bad_part = tmp_path / "parts.yaml"
    bad_part.write_text("LeftKnee: leftleg\n")
    with pytest.raises(BvhError, match=rf"{bad_part}: unknown SMPL-X part\(s\) \['LeftKnee'\]"):
        read_bvh(path, BvhOptions(skeleton_map=str(bad_part), quiet=True))
    bad_joint = tmp_path / "joints.yaml"
    bad_joint.write_text("Pelvis: pelvis_bone\n")
    with pytest.raises(BvhError, match=rf"{bad_joint}: joint 'pelvis_bone' \(for part Pelvis\) is not in {path}"):
        read_bvh(path, BvhOptions(skeleton_map=str(bad_joint), quiet=True))


def test_not_a_bvh_file_is_refused_with_its_first_line(tmp_path):
    path = write(tmp_path, "hello world\n")
    with pytest.raises(BvhError, match=rf"{path}:1: expected HIERARCHY, found 'hello'"):
        parse_bvh(path)


# ------------------------------------------------------------------ real captures


REAL = {"bandai1_walk_normal_001.bvh": ("Bandai Namco", "centimetres", 30.0),
        "ganimator_cmu_08_01_trimmed.bvh": ("Poser / CMU-Daz", "centimetres", 120.0),
        "xia_neutral_01_000.bvh": ("CMU / Motionbuilder", "CMU ASF units (1/0.45 inch)", 120.0)}


@pytest.mark.parametrize("name", sorted(REAL))
def test_the_shared_bvh_walks_are_read_with_their_family_units_and_up_axis(shared_data, name):
    family, unit, fps = REAL[name]
    demo = load_demonstration(shared_data / "bvh" / name, bvh=BvhOptions(quiet=True))
    info = demo.source["bvh"]
    assert (info["family"], info["units"], info["up_axis"], demo.fps) == (family, unit, "y", fps)
    assert 1.45 < demo.stature_m < 1.85 and info["joint_fit_mean_m"] < 0.05
    lowest = demo.surface.lowest_z(demo.part_pos_w, demo.part_quat_w)
    # no floor is level: ganimator's feet rise 8 cm over its 3.5 m, so its first steps sink 6 cm
    assert np.median(lowest) == pytest.approx(0.0, abs=1e-9) and lowest.min() > -0.08
    # walking: the pelvis travels and stays at walking height
    assert np.linalg.norm(demo.part_pos_w[-1, 0, :2] - demo.part_pos_w[0, 0, :2]) > 1.0
    assert 0.7 < np.median(demo.part_pos_w[:, 0, 2]) < 1.1


def test_bandais_walk_solves_with_the_defaults_its_legs_apart_and_the_robot_keeping_up(shared_data):
    """Bandai's left foot skims the floor (within 2 cm in 308 of 324 frames) at up to 3 m/s.
    Planted there, the G1 fell behind the person, one leg passed through the other and every
    QP after it failed (2.2 s per frame); as a sweeping foot (``StanceConfig.sweep_ratio``) it
    is held on the floor but free to move."""
    from dataclasses import replace

    from retarget.solver.problem import build_problem, resample_demonstration
    from retarget.solver.sqp import solve_sequence

    demo = resample_demonstration(load_demonstration(shared_data / "bvh" / "bandai1_walk_normal_001.bvh",
                                                     bvh=BvhOptions(quiet=True)), 50.0)
    n = 60
    demo = replace(demo, part_pos_w=demo.part_pos_w[:n], part_quat_w=demo.part_quat_w[:n],
                   annotations={k: v[:n] for k, v in demo.annotations.items()})
    problem = build_problem(demo)
    assert problem.sweep[:, 0].any() and not (problem.sweep & problem.stance).any()
    sol = solve_sequence(problem)
    assert sol.qp_failures == 0
    assert min(s.min_self_distance_m for s in sol.stats) > -3e-4
    # the robot's pelvis travels with the person's (1.4 m in these 1.2 s)
    travel = np.linalg.norm(demo.part_pos_w[-1, 0, :2] - demo.part_pos_w[0, 0, :2])
    moved = np.linalg.norm(sol.qpos[-1, :2] - sol.qpos[0, :2])
    assert travel > 1.0 and abs(moved - travel) < 0.15 * travel


# ------------------------------------------------------------------ commands


def test_otr_inspect_reads_a_bvh_with_the_overrides_and_states_them(tmp_path, capsys):
    from otr_gym.cli import main

    path = write(tmp_path, stick_bvh(frames=[{}, {}]))
    assert main(["inspect", str(path), "--units", "cm", "--up", "y"]) == 0
    out = capsys.readouterr()
    assert "demonstration (bvh)" in out.out and "2 @ 30 fps" in out.out
    assert "units centimetres (given); up axis y (given)" in out.err


def test_retarget_collects_bvh_files_from_folders(tmp_path):
    from retarget.cli.batch import collect_jobs

    (tmp_path / "clips" / "a").mkdir(parents=True)
    write(tmp_path / "clips" / "a", stick_bvh(), "walk.BVH")
    jobs = collect_jobs([tmp_path / "clips"], tmp_path / "out")
    assert [(j.source.name, j.output) for j in jobs] == [("walk.BVH", tmp_path / "out" / "a" / "walk.npz")]
