"""Score one reference against its demonstration (paper Sec. IV-A), then a dataset's medians.

Pipeline of ``evaluate_sequence``: align the demonstration to the reference's frame times
(``alignment``), recover or take the reference's world scale and map the demonstration into
that world (``scale``; the demonstrated contacts stay in the captured world unless
``EvalConfig.contacts_world`` says otherwise), match objects (``channels``), then per frame and
body unit (``units``)
measure the exact distance and witness of the demonstrated and the robot unit to the ground
and to every object (``proximity``) and compare them (``contact``), pooled over the objects and
per object channel (details); score the objects' own contacts, object–object (the box on the
table: the ``pair_*`` metrics) and object–ground (details) (``object_pairs``); add the style
error (``orientation``), self-penetration (``self_collision``), foot sliding and clearance
(``feet``) and object drift. Nothing here reads the solver's grids, probes or annotations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from otr_gym import robot
from otr_gym.flags import true_intervals
from otr_gym.reference import Reference
from otr_gym.robot_geometry import visual_meshes
from retarget.evaluation.alignment import check_durations, demo_at_times
from retarget.evaluation.channels import object_channels, reference_tracks
from retarget.evaluation.config import EvalConfig
from retarget.evaluation.contact import contact_scores, interaction_set
from retarget.evaluation.feet import skate_and_clear
from retarget.evaluation.object_pairs import object_pair_samples, pooled_scores
from retarget.evaluation.orientation import orientation_error_deg
from retarget.evaluation.proximity import BoundedMesh, ground_proximity, mesh_proximity
from retarget.evaluation.scale import ScaleFit, recover_scale, scale_demonstration
from retarget.evaluation.self_collision import g1_self_model, self_penetration
from retarget.evaluation.units import BodyUnit, Piece, PosedUnit, default_units
from retarget.inputs.demonstration import Demonstration

#: Frames of one batch of mesh queries: bounds the memory of posed vertices near objects
#: (a few MB per unit at worst) while keeping libigl's per-call set-up (~0.1 s) rare.
CHUNK_FRAMES = 256

#: The metrics of the paper's Tables I–III, in their column order: key, header, unit, factor
#: from the stored value (SI or fraction) to the displayed one, digits.
TABLE_COLUMNS: tuple[tuple[str, str, str, float, int], ...] = (
    ("sc", "sc", "", 1.0, 2),
    ("rot_deg", "rot", "°", 1.0, 1),
    ("self_m", "self", "mm", 1e3, 1),
    ("ground_dd_m", "dd", "mm", 1e3, 1),
    ("ground_recall", "R", "%", 100.0, 0),
    ("ground_precision", "P", "%", 100.0, 0),
    ("ground_jaccard", "J", "%", 100.0, 0),
    ("skate_m_s", "skate", "cm/s", 100.0, 1),
    ("clear_m", "clear", "mm", 1e3, 1),
    ("object_dd_m", "dd", "mm", 1e3, 1),
    ("object_dw_m", "dw", "mm", 1e3, 0),
    ("object_recall", "R", "%", 100.0, 0),
    ("object_precision", "P", "%", 100.0, 0),
    ("object_jaccard", "J", "%", 100.0, 0),
    ("drift_m", "drift", "cm", 100.0, 1),
)


@dataclass
class SequenceResult:
    """Per-sequence metrics (SI units, ratios as fractions) and the per-frame samples behind them."""

    name: str
    reference: str
    demonstration: str
    scale: ScaleFit
    metrics: dict[str, float]
    times_s: np.ndarray  # (T,) the reference's frame times
    units: tuple[str, ...]  # G1 links, U
    channels: tuple[str, ...]  # 'ground', then objects, C
    d_hat_m: np.ndarray  # (T, U, C) demonstrated signed distances
    d_m: np.ndarray  # (T, U, C) retargeted signed distances
    self_depth_m: np.ndarray  # (T,) deepest self-penetration per frame
    eps_m: float
    details: dict = field(default_factory=dict)

    def timeline(self) -> dict:
        """Per channel and unit, the frame intervals [start, stop) of H and of R (reference frames)."""
        h = interaction_set(self.d_hat_m, self.eps_m)
        r = interaction_set(self.d_m, self.eps_m)
        return {c_name: {u_name: {"H": _intervals(h[:, u, c]), "R": _intervals(r[:, u, c])}
                         for u, u_name in enumerate(self.units) if h[:, u, c].any() or r[:, u, c].any()}
                for c, c_name in enumerate(self.channels)}

    def as_dict(self) -> dict:
        """JSON-ready record: every per-sequence value and the contact timeline (NaN -> None)."""
        return json_safe({"name": self.name, "reference": self.reference, "demonstration": self.demonstration,
                           "frames": len(self.times_s),
                           "fps": float(1.0 / (self.times_s[1] - self.times_s[0])) if len(self.times_s) > 1 else None,
                           "metrics": self.metrics, "scale": self.scale.as_dict(), "units": list(self.units),
                           "channels": list(self.channels), "details": self.details, "timeline": self.timeline()})


def _intervals(mask: np.ndarray) -> list[list[int]]:
    return [[a, b] for a, b in true_intervals(mask)]  # JSON: [start, stop) as lists


def json_safe(x):
    """``x`` with NaN/inf as None and NumPy scalars as Python numbers (strict JSON)."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    return x


def _metadata_scale(ref: Reference) -> float | None:
    value = ref.metadata.get("scale") if isinstance(ref.metadata, dict) else None
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) and value > 0 else None


def evaluate_sequence(ref: Reference, demo: Demonstration, cfg: EvalConfig | None = None, *,
                      units: tuple[BodyUnit, ...] | None = None, progress: bool = False,
                      demo_source: str | None = None) -> SequenceResult:
    """All metrics of one reference against its demonstration, compared at the reference's
    frame times in the reference's world (see the module docstrings for each definition).

    ``demo_source`` names the demonstration in messages and records (default: the path its
    reader recorded, else its name).
    """
    from retarget.inputs.human import STYLE_LINKS, alignment_offsets

    cfg = EvalConfig() if cfg is None else cfg
    demo_name = demo_source or str(demo.source.get("path", demo.name))
    check_durations(ref.duration_s, demo.duration_s, cfg.duration_tolerance_s, ref.source, demo_name)
    T = ref.num_frames
    times = np.arange(T) / ref.fps
    demo_t = demo_at_times(demo, times)
    tracks = reference_tracks(ref, demo)

    # ---- world scale
    root = demo.part_parents.index(-1)
    pelvis = ref.body_index([robot.ROOT_BODY])[0]
    ref_tracks = [ref.body_pos_w[:, pelvis, :2]] + [t.pos_w for t in tracks if t is not None]
    demo_tracks = [demo_t.part_pos_w[:, root, :2]] + [o.pos_w for o, t in zip(demo_t.objects, tracks) if t is not None]
    scale = recover_scale(ref_tracks, demo_tracks, demo.stature_m, given=cfg.scale,
                          metadata_scale=_metadata_scale(ref), min_excursion_m=cfg.scale_min_excursion_m,
                          snap_rel=cfg.scale_snap_rel)
    demo_s = scale_demonstration(demo_t, scale.sc)
    channels = object_channels(ref, demo_s, tracks)

    # ---- proximity samples
    units = default_units() if units is None else units
    part_of = {n: i for i, n in enumerate(demo.part_names)}
    missing = sorted({p for u in units for p in u.parts if p not in part_of})
    if missing:
        raise ValueError(f"{demo_name}: human parts {missing} of the unit table are not in the demonstration")
    eps = cfg.eps_eval_m
    native = cfg.contacts_world == "native"
    robot_u = _robot_units(ref, units)
    d_hat, w_hat, d, w = _proximity_samples(demo_t if native else demo_s, ref, units, robot_u, channels, eps,
                                            progress)
    if native:  # ground witnesses of the captured world into the reference's world
        w_hat[:, :, 0, :2] *= scale.sc
    ground = contact_scores(d_hat[..., 0], w_hat[..., 0, :], d[..., 0], w[..., 0, :], eps)
    objects = contact_scores(d_hat[..., 1:], w_hat[..., 1:, :], d[..., 1:], w[..., 1:, :], eps)
    per_object = {c.name: contact_scores(d_hat[..., k], w_hat[..., k, :], d[..., k], w[..., k, :], eps)
                  for k, c in enumerate(channels, start=1)}
    # the objects' own contacts: object–object (box–table) pooled into the pair metrics, object–ground in details
    pairs = object_pair_samples(channels, eps)
    between = pooled_scores([p for p in pairs if p.b != "ground"], eps)

    # ---- style: R̂_ℓ = R_h(ℓ) O_ℓ
    offsets = alignment_offsets()
    style_links = [lk for lk in STYLE_LINKS if lk in ref.body_names]
    rot = orientation_error_deg(ref.body_quat_w[:, ref.body_index(style_links)],
                                demo_t.part_quat_w[:, [part_of[STYLE_LINKS[lk]] for lk in style_links]],
                                np.stack([offsets[lk] for lk in style_links]))

    # ---- self-penetration of the visual meshes
    model = g1_self_model()
    body = ref.body_index(model.links)
    pen = self_penetration(list(model.meshes), ref.body_pos_w[:, body], ref.body_quat_w[:, body], model.pairs)

    # ---- feet: stance from the demonstration
    unit_of = {lk: i for i, u in enumerate(units) for lk in u.links}
    feet = [f for f in robot.FEET if f in unit_of]
    stance = interaction_set(d_hat[:, [unit_of[f] for f in feet], 0], eps)
    feet_w = [robot_u[unit_of[f]].vertices() for f in feet]
    skate, clear = skate_and_clear(feet_w, stance, ref.fps)

    # ---- object drift (tracked, manipulated objects)
    drifts = {c.name: float(c.drift_m().mean()) for c in channels if c.tracked and not c.static}

    metrics = {
        "sc": scale.sc, "rot_deg": float(rot.mean()), "self_m": pen.percentile_m(cfg.self_percentile),
        "ground_dd_m": ground.dd_m, "ground_dw_m": ground.dw_m, "ground_recall": ground.recall,
        "ground_precision": ground.precision, "ground_jaccard": ground.jaccard,
        "skate_m_s": skate, "clear_m": clear,
        "object_dd_m": objects.dd_m, "object_dw_m": objects.dw_m, "object_recall": objects.recall,
        "object_precision": objects.precision, "object_jaccard": objects.jaccard,
        "drift_m": float(np.mean(list(drifts.values()))) if drifts else float("nan"),
        "pair_dd_m": between.dd_m, "pair_recall": between.recall, "pair_precision": between.precision,
        "pair_jaccard": between.jaccard,
    }
    worst = int(np.argmax(pen.depth_m))
    # the file's body poses are what is scored; say how far they are from our G1's own kinematics
    fk = Reference.from_qpos(ref.qpos(), ref.fps)
    fk_gap = np.linalg.norm(fk.body_pos_w - ref.body_pos_w[:, ref.body_index(fk.body_names)], axis=-1)
    details = {
        "ground_counts": {"H": ground.n_h, "R": ground.n_r, "H∩R": ground.n_both},
        "object_counts": {"H": objects.n_h, "R": objects.n_r, "H∩R": objects.n_both},
        "object_channels": {name: sc.as_dict() for name, sc in per_object.items()},
        "object_pairs": {p.name: p.scores(eps).as_dict() for p in pairs},
        "stance_frames": {f: int(stance[:, i].sum()) for i, f in enumerate(feet)},
        "drift_m_per_object": drifts,
        "objects": [{"name": c.name, "tracked": c.tracked, "static": c.static, "mesh": c.ref_mesh.name}
                    for c in channels],
        "self_max_m": float(pen.depth_m[worst]),
        "self_max_pair": [model.links[i] for i in pen.pair[worst]] if pen.depth_m[worst] > 0 else None,
        "rot_deg_per_link": dict(zip(style_links, rot.mean(axis=0).tolist())),
        "unit_links": {u.name: list(u.links) for u in units},
        "unit_parts": {u.name: list(u.parts) for u in units},
        "body_pos_vs_our_fk_max_m": float(fk_gap.max()),
        "contacts_world": cfg.contacts_world,
        "frame_times": "reference",
        "demo_fps": demo.fps, "reference_fps": ref.fps,
        "duration_gap_s": ref.duration_s - demo.duration_s,
    }
    return SequenceResult(
        name=ref.source.rsplit("/", 1)[-1].removesuffix(".npz"), reference=ref.source, demonstration=demo_name,
        scale=scale, metrics=metrics, times_s=times, units=tuple(u.name for u in units),
        channels=("ground",) + tuple(c.name for c in channels), d_hat_m=d_hat, d_m=d,
        self_depth_m=pen.depth_m, eps_m=eps, details=details)


def _robot_units(ref: Reference, units: tuple[BodyUnit, ...]) -> list[PosedUnit]:
    meshes = visual_meshes()
    out = []
    for u in units:
        i = ref.body_index(u.links)
        out.append(PosedUnit.from_poses([Piece.of(meshes[lk].vertices) for lk in u.links], ref.body_pos_w[:, i],
                                        ref.body_quat_w[:, i]))
    return out


def _proximity_samples(demo_c: Demonstration, ref: Reference, units: tuple[BodyUnit, ...],
                       robot_u: list[PosedUnit], channels: list, eps: float, progress: bool):
    """(d̂, ŵ, d, w) of every sample: (T, U, C) signed distances (m) and (T, U, C, 3) witnesses
    (channel frames); channel 0 is the ground, then the objects. The demonstrated side is
    ``demo_c`` (at the reference's times, in the world chosen for contacts)."""
    T, U, C = ref.num_frames, len(units), 1 + len(channels)
    part_of = {n: i for i, n in enumerate(demo_c.part_names)}
    pieces = [Piece.of(v) for v in demo_c.surface.vertices]
    human = []
    for unit in units:
        ps = [part_of[p] for p in unit.parts]
        human.append(PosedUnit.from_poses([pieces[k] for k in ps], demo_c.part_pos_w[:, ps], demo_c.part_quat_w[:, ps]))
    d_hat, d = np.empty((T, U, C)), np.empty((T, U, C))
    w_hat, w = np.empty((T, U, C, 3)), np.empty((T, U, C, 3))
    for u in range(U):
        d_hat[:, u, 0], w_hat[:, u, 0] = ground_proximity(human[u])
        d[:, u, 0], w[:, u, 0] = ground_proximity(robot_u[u])
    bounded = {}
    for chan in channels:
        for m in (chan.demo_mesh, chan.ref_mesh):
            if id(m) not in bounded:
                bounded[id(m)] = BoundedMesh.from_mesh(m)
    demo_objects = {o.name: o for o in demo_c.objects}
    starts = range(0, T, CHUNK_FRAMES)
    if progress:
        from tqdm import tqdm

        starts = tqdm(starts, desc=f"eval {ref.source.rsplit('/', 1)[-1]}", unit="chunk", leave=False)
    for s in starts:
        ch = slice(s, min(s + CHUNK_FRAMES, T))
        for c, chan in enumerate(channels, start=1):
            o = demo_objects[chan.name]
            d_hat[ch, :, c], w_hat[ch, :, c] = mesh_proximity(
                bounded[id(chan.demo_mesh)], [x.frames(ch).in_frame(o.pos_w[ch], o.quat_w[ch]) for x in human], eps)
            # the robot's distance is needed exactly wherever the demonstration interacts (dd, dw)
            need = np.where(interaction_set(d_hat[ch, :, c], eps), np.inf, eps)
            d[ch, :, c], w[ch, :, c] = mesh_proximity(
                bounded[id(chan.ref_mesh)],
                [x.frames(ch).in_frame(chan.ref_pos_w[ch], chan.ref_quat_w[ch]) for x in robot_u], need)
    return d_hat, w_hat, d, w


def dataset_medians(metrics: list[dict[str, float | None]]) -> dict[str, float]:
    """Median over sequences of every metric; undefined values (NaN or None) are skipped."""
    out = {}
    for k in (metrics[0] if metrics else {}):
        vals = np.array([np.nan if m.get(k) is None else m[k] for m in metrics], np.float64)
        vals = vals[np.isfinite(vals)]
        out[k] = float(np.median(vals)) if vals.size else float("nan")
    return out
