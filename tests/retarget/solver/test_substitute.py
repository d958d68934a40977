"""Object substitution and resizing (paper Sec. III-E, IV-D), two-object scenes, ``otr variants``.

Generated data only: short clips of the synthetic squat–lift–place (box + table, ``clips``)."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
import trimesh

from otr_gym.rotations import quat_from_rotvec
from retarget.checks.verify import check_reference, object_in_robot_depth
from retarget.clip import retarget_demonstration
from retarget.config import RetargetConfig
from retarget.evaluation import evaluate_sequence
from retarget.geometry.channels import GeometryConfig, sample_surface
from retarget.inputs.meshes import InvalidMeshError, as_trimesh, signed_distance
from retarget.inputs.shapes import (
    LIBRARY,
    ShapeSpec,
    UnknownShapeError,
    canonical_mesh,
    load_shape_mesh,
    parse_scales,
    parse_shapes,
    substitute_mesh,
)
from retarget.solver.problem import build_problem, resample_demonstration
from retarget.solver.substitute import (
    SubstitutionConfig,
    free_objects,
    substitute,
    surface_maps,
)
from retarget.solver.targets import frame_targets

from clips import clip

EPS_COL = 3e-4
#: The paper's dimensions (m) along the canonical x, y, z (z up).
PAPER_EXTENTS = {"ball": (0.34, 0.34, 0.34), "drum": (0.34, 0.34, 0.36), "capsule": (0.23, 0.23, 0.36),
                 "rugby": (0.43, 0.31, 0.28), "torus": (0.36, 0.36, 0.12), "cube": (0.26, 0.26, 0.26),
                 "board": (0.38, 0.30, 0.12), "beam": (0.46, 0.19, 0.19)}


def _box(extents=(0.35, 0.40, 0.30), name="box"):
    m = trimesh.creation.box(extents=extents)
    return as_trimesh(m.vertices, m.faces, name)


def _unsigned_distance(mesh, points) -> np.ndarray:
    return np.abs(signed_distance(mesh, points)[0])


@pytest.fixture(scope="module")
def lift():
    """Reach, grasp and lift of the synthetic box carry at 50 fps (hands on the box sides)."""
    return resample_demonstration(clip("box_carry", 150, 175), 50.0)


# ------------------------------------------------------------------ shape library


def test_library_holds_the_papers_eight_shapes_at_their_dimensions():
    assert sorted(LIBRARY) == sorted(PAPER_EXTENTS)
    for name, extents in PAPER_EXTENTS.items():
        mesh = canonical_mesh(name)
        assert np.allclose(np.ptp(mesh.vertices, axis=0), extents, atol=1e-3), name
        assert np.allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-9), name
        assert trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).is_watertight, name


def test_shapes_stand_as_the_demonstrated_object_stood_and_sit_at_its_centre():
    # the captured object's frame is upside down in the world (as the OMOMO box's is) and off-centre
    box = as_trimesh(_box((0.47, 0.30, 0.41)).vertices + [0.02, -0.01, 0.03], _box().faces, "box")
    upside_down = np.tile(quat_from_rotvec(np.array([np.pi, 0.0, 0.0])), (10, 1))
    drum = substitute_mesh(ShapeSpec("drum"), box, upside_down)
    assert np.allclose(np.ptp(drum.vertices, axis=0), (0.34, 0.34, 0.36), atol=1e-3)  # axis along the box's z
    assert np.allclose(drum.bounds.mean(axis=0), box.bounds.mean(axis=0), atol=1e-9)
    board = substitute_mesh(ShapeSpec("board"), box, upside_down)  # 0.38 along the box's longer side (x)
    assert np.allclose(np.ptp(board.vertices, axis=0), (0.38, 0.30, 0.12), atol=1e-9)


def test_resizing_is_uniform_or_per_axis_about_the_centre():
    box = _box((0.4, 0.3, 0.2))
    upright = np.tile([1.0, 0.0, 0.0, 0.0], (5, 1))
    big = substitute_mesh(ShapeSpec("original", 1.5), box, upright)
    assert np.allclose(big.vertices, 1.5 * box.vertices)
    tall = substitute_mesh(ShapeSpec("original", (1.0, 1.0, 2.0)), box, upright)
    assert np.allclose(np.ptp(tall.vertices, axis=0), (0.4, 0.3, 0.4))
    assert parse_scales("0.7:1.6:0.1") == [(s, s, s) for s in (0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6)]
    assert parse_scales("1,1x1x1.5") == [(1.0, 1.0, 1.0), (1.0, 1.0, 1.5)]


def test_unknown_shape_bad_scale_and_unreadable_mesh_are_named(tmp_path):
    with pytest.raises(UnknownShapeError, match="unknown shape 'pyramid'"):
        parse_shapes("ball,pyramid")
    for bad in ("0", "-0.5", "0.7:1.6:0", "1x0x1", "big"):
        with pytest.raises(ValueError, match=f"scale '{bad}'"):
            parse_scales(bad)
    with pytest.raises(ValueError, match="'ball'.*> 0"):
        ShapeSpec("ball", 0.0)
    corrupt = tmp_path / "broken.obj"
    corrupt.write_text("v 0 0 0\nf 1 2 3\nthis is not a mesh\n")
    with pytest.raises(InvalidMeshError, match="broken.obj"):
        load_shape_mesh(corrupt)
    with pytest.raises(InvalidMeshError, match="missing.stl.*not found"):
        load_shape_mesh(tmp_path / "missing.stl")


# ------------------------------------------------------------------ transport of witnesses


def test_an_identical_surface_maps_every_point_onto_itself():
    box = _box()
    to_sub, to_demo = surface_maps(box, box, SubstitutionConfig(samples=600))
    points = sample_surface(box, 2000.0, seed=3).points
    assert np.abs(to_sub(points) - points).max() < 1e-9
    assert np.abs(to_demo(points) - points).max() < 1e-9


def test_a_resized_surface_maps_points_to_their_scaled_places():
    box = _box()
    to_sub, _ = surface_maps(box, as_trimesh(1.5 * box.vertices, box.faces, "big"), SubstitutionConfig(samples=600))
    points = sample_surface(box, 2000.0, seed=3).points
    error = np.linalg.norm(to_sub(points) - 1.5 * points, axis=1)
    assert np.median(error) < 0.008 and np.quantile(error, 0.9) < 0.015  # 600 samples: 5 cm apart on the big box


@pytest.mark.parametrize("shape", ["ball", "torus", "cube", "board"])
def test_mapped_witnesses_lie_on_the_substitute_surface(shape):
    box = _box()
    upright = np.tile([1.0, 0.0, 0.0, 0.0], (2, 1))
    sub = substitute_mesh(ShapeSpec(shape), box, upright)
    to_sub, to_demo = surface_maps(box, sub, SubstitutionConfig(samples=600))
    witnesses = sample_surface(box, 2000.0, seed=5).points
    assert _unsigned_distance(sub, to_sub(witnesses)).max() <= 1e-3
    assert _unsigned_distance(box, to_demo(sample_surface(sub, 2000.0, seed=5).points)).max() <= 1e-3


def test_targets_on_a_substitute_keep_metric_distances_and_land_on_its_surface(lift):
    native = build_problem(lift)
    swapped = build_problem(substitute(lift, ShapeSpec("original", 0.8)))
    sub_mesh, box_mesh = swapped.channels[1].channel.mesh, native.channels[1].channel.mesh
    t = lift.num_frames - 5  # lifting, both hands on the box
    a, b = frame_targets(native, t), frame_targets(swapped, t)
    active = a.robot_active[1]
    assert active.sum() > 100 and np.array_equal(active, b.robot_active[1])
    np.testing.assert_allclose(b.robot[1].d[active], a.robot[1].d[active], atol=1e-12)  # d̂ in metres, not rescaled
    assert _unsigned_distance(sub_mesh, b.robot[1].w[active]).max() <= 1e-3
    # each probe of the substitute takes the demonstrated triples of a point of the captured box
    assert _unsigned_distance(box_mesh, swapped.objects[0].demonstrated_probes).max() <= 1e-3
    assert swapped.objects[0].probes.shape == (len(swapped.channels[1].channel.surface), 3)


# ------------------------------------------------------------------ retargeting substitutes


def test_a_substitute_equal_to_the_original_gives_the_original_reference():
    demo = resample_demonstration(clip("box_carry", 164, 172), 50.0)  # hands closing on the box
    native = retarget_demonstration(demo, RetargetConfig())
    same = retarget_demonstration(substitute(demo, ShapeSpec("original")), RetargetConfig())
    np.testing.assert_allclose(same.joint_pos, native.joint_pos, atol=1e-6)
    np.testing.assert_allclose(same.objects[0].pos_w, native.objects[0].pos_w, atol=1e-6)
    np.testing.assert_allclose(same.contacts.distance, native.contacts.distance, atol=1e-6)


def test_a_resized_box_keeps_hand_contact_without_penetration(lift):
    ref = retarget_demonstration(substitute(lift, ShapeSpec("original", 0.8)), RetargetConfig())
    assert np.ptp(ref.objects[0].mesh_vertices, axis=0) == pytest.approx(0.8 * np.array([0.35, 0.40, 0.30]), abs=1e-6)
    checks = check_reference(ref, lift)  # robot against the reference's (resized) box, hands of the demonstration
    assert checks.hand_contact_frames > 30 and checks.hand_hold >= 0.85
    assert checks.object_penetration_mesh_m <= EPS_COL and checks.ground_penetration_mesh_m <= EPS_COL
    assert object_in_robot_depth(ref) <= 1e-3
    # the smaller box rests on the floor until lifted: it sank with its size, not through the floor
    assert checks.object_min_height_m >= -EPS_COL


# ------------------------------------------------------------------ two objects: box and table


@pytest.fixture(scope="module")
def place():
    """The box is put on the table and let go (it rests from frame ~12 of 30 at 30 fps)."""
    return resample_demonstration(clip("box_carry", 376, 406), 50.0)


@pytest.mark.parametrize("free_table", [False, True])
def test_the_box_rests_on_the_table_and_the_robot_never_touches_it(place, free_table):
    demo = free_objects(place, ["table"]) if free_table else place
    ref = retarget_demonstration(demo, RetargetConfig())
    assert ref.metadata["free_objects"] == (["box", "table"] if free_table else ["box"])
    ref.source = "place"
    result = evaluate_sequence(ref, place)
    pair = result.details["object_pairs"]["box|table"]
    assert pair["n_h"] > 30  # the demonstrated box rests on the table in most frames
    assert pair["recall"] >= 0.95 and pair["dd_m"] <= 0.006  # measured 2.0–5.1 mm
    assert result.metrics["pair_recall"] == pair["recall"]
    table = result.details["object_channels"]["table"]
    assert table["n_h"] == 0  # the person never touches the table
    c = list(result.channels).index("table")
    touching = (np.maximum(result.d_m[:, :, c], 0.0) < 0.02).any(axis=1)
    if not free_table:
        # no robot–table contact once the cold start of this clip (cut mid-carry: 50 SQP
        # iterations from a default pose) has settled; measured: a hand 18.7 mm from the table
        # on frames 0–2. (With the table free the cold start pushes it 7–8 cm towards the placed
        # box and the left hand, still on the box, ends within 2 cm of the table top: a known limit.)
        assert not touching[5:].any()
    assert result.details["object_channels"]["box"]["recall"] >= 0.9
    from retarget.evaluation.report import format_object_notes

    notes = format_object_notes([result.as_dict()])  # what `otr score` prints under its table
    assert "robot–table" in notes and f"box–table R {100 * pair['recall']:.0f} %" in notes
    moved = np.linalg.norm(ref.objects[1].pos_w - place.objects[1].pos_w, axis=1)
    # free: pushed off by the cold start (frames 0-2; measured 7.1 cm, 8.2 cm since the contact
    # rows judge a unit by its whole surface: the robot then stays 18-29 mm off the table there
    # where it came within 5 mm), then back in place (measured ≤ 0.5 cm)
    assert moved[:3].max() <= (0.09 if free_table else 0.0)
    assert moved[3:].max() <= (0.01 if free_table else 0.0)


# ------------------------------------------------------------------ otr variants


def _variant_args(*argv: str) -> argparse.Namespace:
    from retarget.cli.variants import configure_parser

    parser = argparse.ArgumentParser()
    configure_parser(parser)
    return parser.parse_args(list(argv))


@pytest.fixture(scope="module")
def grasp_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("demos") / "grasp.npz"
    clip("box_carry", 166, 172).save(path)  # hands on the box sides
    return path


def test_variants_batch_reports_a_failure_goes_on_then_resumes(grasp_file, tmp_path, monkeypatch, capsys):
    import retarget.clip
    from retarget.cli.variants import main

    real = retarget.clip.retarget_timed

    def fail_on_small_box(demo, cfg, progress=None):
        if demo.source.get("substitution", {}).get("scale") == [0.8, 0.8, 0.8]:
            raise RuntimeError("solver exploded")
        return real(demo, cfg, progress)

    out = tmp_path / "variants"
    monkeypatch.setattr(retarget.clip, "retarget_timed", fail_on_small_box)
    assert main(_variant_args(str(grasp_file), "--scales", "0.8,1", "--out", str(out))) == 1
    captured = capsys.readouterr()
    assert "original_x0.80" in captured.err and "solver exploded" in captured.err
    assert (out / "grasp__original_x1.00.npz").is_file() and not (out / "grasp__original_x0.80.npz").exists()

    monkeypatch.setattr(retarget.clip, "retarget_timed", real)
    assert main(_variant_args(str(grasp_file), "--scales", "0.8,1", "--out", str(out))) == 0
    captured = capsys.readouterr()
    assert "1 of 2 variants already done" in captured.out
    summary = json.loads((out / "variants.json").read_text())
    rows = {r["variant"]: r for r in summary["variants"]}
    assert sorted(rows) == ["original_x0.80", "original_x1.00"]
    for r in rows.values():
        assert 0.0 <= r["metrics"]["object_recall"] <= 1.0 and r["timing"]["solve_s"] > 0
        assert r["metrics"]["grip_recall"] >= 0.8  # the hands hold either box
        # the robot's visual-mesh vertices never enter the box (the solver's ε_col, checked exactly)
        assert (r["checks"]["object_penetration_mesh_m"] <= EPS_COL
                and r["checks"]["ground_penetration_mesh_m"] <= EPS_COL)
        assert r["checks"]["object_in_robot_m"] >= 0.0
    table = (out / "variants.md").read_text()
    assert "| box ×1.0 (native) |" in table and "| box ×0.8 |" in table and "drift cm" in table
    assert (out / "recall_precision_vs_scale.png").read_bytes()[:4] == b"\x89PNG"


def test_variants_cli_names_an_unknown_shape_a_bad_scale_and_an_unreadable_mesh(grasp_file, tmp_path, capsys):
    from retarget.cli.variants import main

    corrupt = tmp_path / "junk.ply"
    corrupt.write_bytes(b"ply\nformat nonsense\n")
    for argv, named in ((["--shapes", "ball,pyramid"], "pyramid"), (["--scales", "1,0"], "scale '0'"),
                        (["--shapes", str(corrupt)], "junk.ply")):
        assert main(_variant_args(str(grasp_file), *argv, "--out", str(tmp_path / "o"))) == 2
        assert named in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_substitute_too_big_to_hold_finishes_with_a_warning_and_its_recall(grasp_file, tmp_path):
    from retarget.cli.variants import VariantJob, run_variant

    # six times as wide: the sides are 1.4 m from the centre, beyond the G1's reach even with the
    # box moved by its full 0.35 m of freedom (b_cor); at four times one hand reaches a side
    job = VariantJob(grasp_file, None, ShapeSpec("original", (1.0, 6.0, 1.0)), tmp_path / "grasp__wide.npz")
    cfg = RetargetConfig(geometry=GeometryConfig(grid_resolution_m=0.02))  # a coarse grid: the batch logic is tested
    status, message = run_variant(job, cfg, SubstitutionConfig(samples=500), min_recall=0.5)
    assert status == "warning" and "too big" in message
    record = json.loads(job.record.read_text())
    assert record["metrics"]["grip_recall"] < 0.5 and record["warnings"]
    assert job.output.is_file()


def test_a_substituted_demonstration_refuses_to_be_saved_as_captured(tmp_path):
    from retarget.inputs.demonstration import InvalidDemonstrationError

    demo = clip("box_carry", 166, 168)
    with pytest.raises(InvalidDemonstrationError, match=r"\['box'\].*substitutes"):
        substitute(demo, ShapeSpec("ball")).save(tmp_path / "ball.npz")
    assert not (tmp_path / "ball.npz").exists()
