"""Shared fixtures. Real data lives in ../shared/data (not part of the project): tests that
need it skip with a reason when it is absent; the core suite uses generated data only."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

SHARED_DATA = Path(os.environ.get("OTR_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
REPO_ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = REPO_ROOT / "benchmarks"

# Headless rendering in tests: EGL unless the caller chose a GL backend (must precede `import mujoco`).
if sys.platform.startswith("linux"):
    os.environ.setdefault("MUJOCO_GL", "egl")


def benchmark_sets(name: str) -> dict:
    """The nested overrides of a ``benchmarks/NAME`` sets file, split and parsed as the shell
    recipes pass it (``SETS="$(cat FILE)"``, one ``--set`` per word)."""
    from agents.train import parse_sets

    return parse_sets((BENCHMARKS / name).read_text().split())


def lowest_collision_reach(qpos, bodies=None) -> tuple[float, str]:
    """(z in m, body) of the lowest reach of the G1's collision geometry (of ``bodies`` only, if
    given) at MuJoCo qpos (36,), by MuJoCo's kinematics: an independent check of the Pinocchio
    frames that feasibility and clear-ground put on ``collision_points``."""
    import mujoco

    from otr_gym import robot
    from otr_gym.robot_geometry import collision_points

    model = mujoco.MjModel.from_xml_path(str(robot.G1_MJCF))
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    reach = []
    for p in collision_points():
        if bodies is None or p.body in bodies:
            b = model.body(p.body).id
            reach.append(((data.xpos[b] + data.xmat[b].reshape(3, 3) @ p.point)[2] - p.radius, p.body))
    z, body = min(reach)
    return float(z), body


def env_checker_messages(env) -> list[str]:
    """Gymnasium's ``check_env`` on ``env.unwrapped``: the warnings it raises about the env (its
    own, or about a Box space), as text."""
    import warnings

    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    return [str(w.message) for w in caught if "gymnasium" in str(w.filename) or "Box" in str(w.message)]


def load_benchmark(name: str):
    """The module of the script ``benchmarks/NAME.py`` (the folder is not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while the script runs
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not (SHARED_DATA / "README.md").is_file():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (set OTR_SHARED_DATA to use it)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def largebox_reference(shared_data, tmp_path_factory) -> Path:
    """Our reference of OMOMO sub3_largebox_003 (native scale, box free), retargeted once per
    session (~30 s on one core) by this commit's code."""
    from retarget.clip import retarget_demonstration
    from retarget.config import RetargetConfig
    from retarget.inputs.readers import load_demonstration

    demo = load_demonstration(shared_data / "omomo" / "sub3_largebox_003.pt", shared_data / "objects" / "largebox.obj")
    return retarget_demonstration(demo, RetargetConfig()).save(
        tmp_path_factory.mktemp("refs") / "sub3_largebox_003.npz")


@pytest.fixture(scope="session")
def largebox_reference_per_frame(shared_data, tmp_path_factory) -> Path:
    """The same without the grasp pass (``grasp.enabled: false``): the person's grip, the hands
    under the box's bottom edges, as the per-frame solve makes it, with the solver of 53a180a
    (no contact-state pricing, no person's COM target, no refusal of deeper steps; the same
    reference bit for bit): the test that uses it judges the hands' collision boxes on one
    fixed grip, not the solver of the day."""
    from dataclasses import replace

    from retarget.clip import retarget_demonstration
    from retarget.config import RetargetConfig
    from retarget.inputs.readers import load_demonstration

    demo = load_demonstration(shared_data / "omomo" / "sub3_largebox_003.pt", shared_data / "objects" / "largebox.obj")
    cfg = RetargetConfig()
    cfg = replace(cfg, grasp=replace(cfg.grasp, enabled=False), balance=replace(cfg.balance, person_com_weight=0.0),
                  solver=replace(cfg.solver, price_contact_state=False, step_penetration_m=float("inf")))
    return retarget_demonstration(demo, cfg).save(tmp_path_factory.mktemp("refs") / "sub3_largebox_003.npz")


# ------------------------------------------------------------------ generated G1 references
@pytest.fixture(scope="session")
def standing_reference(tmp_path_factory) -> Path:
    """A 4 s standing clip (default pose, Reference.from_qpos) saved as our npz."""
    from agents.procedural import standing_reference as stand

    return stand(duration_s=4.0).save(tmp_path_factory.mktemp("refs") / "stand.npz")


@pytest.fixture(scope="session")
def walking_reference(tmp_path_factory) -> Path:
    """A 3 s procedural walk (4 footsteps) at 30 fps, so that loading resamples it to 50 fps."""
    from agents.procedural import WalkSpec
    from agents.procedural import walking_reference as walk

    return walk(WalkSpec(steps=4, fps=30.0)).save(tmp_path_factory.mktemp("refs") / "walk.npz")


# ------------------------------------------------------------------ a generated box reference
BOX_HALF_M = 0.1
TABLE_TOP_M = 0.75


def _box_clip(annotated: bool):
    """The G1 standing still (3 s at 50 fps) while a 20 cm box moves through known contact
    windows (frame ranges):

    - [0, 40): on the floor 0.6 m ahead (box–ground window);
    - [60, 100): 1 cm to the left of the left hand's collision capsule (left hand window);
    - [110, 151): on a static table (box–table window);
    - in between it glides through the air, away from everything.

    With ``annotated``, the file carries contact annotations whose hand windows differ from the
    geometry on purpose: left hand [60, 100), right hand [70, 90).
    """
    import numpy as np
    import trimesh

    from otr_gym import robot
    from otr_gym.reference import ContactAnnotations, ObjectTrack, Reference
    from otr_gym.rotations import linear_velocity_from_positions, quat_apply

    fps, frames = 50.0, 151
    qpos = np.tile(robot.default_qpos(), (frames, 1))
    ref = Reference.from_qpos(qpos, fps)
    left = ref.body_index(["left_wrist_yaw_link"])[0]
    hand = ref.body_pos_w[0, left] + quat_apply(ref.body_quat_w[0, left], np.array([0.11, 0.0, 0.0]))
    floor = np.array([0.6, 0.0, BOX_HALF_M])
    beside = hand + np.array([0.0, 0.035 + 0.01 + BOX_HALF_M, 0.0])
    table_xy = np.array([1.3, 0.0])
    on_table = np.array([table_xy[0], table_xy[1], TABLE_TOP_M + BOX_HALF_M])
    air = np.array([0.9, 0.6, 1.2])
    keys = [(0, floor), (39, floor), (49, air), (60, beside), (99, beside), (104, air), (110, on_table),
            (150, on_table)]
    t = np.arange(frames)
    pos = np.stack([np.interp(t, [k for k, _ in keys], [p[i] for _, p in keys]) for i in range(3)], axis=1)
    ident = np.tile([1.0, 0.0, 0.0, 0.0], (frames, 1))
    box = trimesh.creation.box(extents=(2 * BOX_HALF_M,) * 3)
    pieces = [trimesh.creation.box(extents=(0.6, 0.6, 0.04),
                                   transform=trimesh.transformations.translation_matrix((0, 0, TABLE_TOP_M - 0.02)))]
    for sx in (-1, 1):
        for sy in (-1, 1):
            pieces.append(trimesh.creation.box(extents=(0.04, 0.04, TABLE_TOP_M - 0.04),
                                               transform=trimesh.transformations.translation_matrix(
                                                   (sx * 0.26, sy * 0.26, 0.5 * (TABLE_TOP_M - 0.04)))))
    table = trimesh.util.concatenate(pieces)
    objects = [
        ObjectTrack("box", pos, ident.copy(), linear_velocity_from_positions(pos, 1 / fps), np.zeros((frames, 3)),
                    np.asarray(box.vertices), np.asarray(box.faces)),
        ObjectTrack("table", np.tile([*table_xy, 0.0], (frames, 1)), ident.copy(), np.zeros((frames, 3)),
                    np.zeros((frames, 3)), np.asarray(table.vertices), np.asarray(table.faces)),
    ]
    contacts = None
    if annotated:
        distance = np.full((frames, 2, 3), 0.3)
        distance[60:100, 0, 1] = 0.01
        distance[70:90, 1, 1] = 0.01
        contacts = ContactAnnotations(("left_wrist_yaw_link", "right_wrist_yaw_link"), ("ground", "box", "table"),
                                      distance)
    return Reference.from_qpos(qpos, fps, objects=objects, contacts=contacts, metadata={"source": "test box clip"})


@pytest.fixture(scope="session")
def box_reference(tmp_path_factory) -> Path:
    """The generated box clip with contact annotations (see ``_box_clip``)."""
    return _box_clip(annotated=True).save(tmp_path_factory.mktemp("refs") / "box_annotated.npz")


@pytest.fixture(scope="session")
def box_reference_geometry(tmp_path_factory) -> Path:
    """The same clip without annotations: windows come from the reference geometry."""
    return _box_clip(annotated=False).save(tmp_path_factory.mktemp("refs") / "box_plain.npz")
