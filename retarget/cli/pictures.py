"""Pictures of demonstrations and their retargeted references, side by side in time.

Row 1: the human (mannequin-x surface, one rigid track per part) with the demonstration's
objects; row 2: the G1 reference with its objects (and the demonstration's static furniture).
Columns are the same instants, so contacts can be compared by eye.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from otr_gym.reference import Reference
from otr_gym.render import HUMAN_RGBA, RigidTrack, SceneRenderer, grid, reference_tracks, save_png
from retarget.inputs.demonstration import Demonstration

TABLE_RGBA = (0.55, 0.4, 0.25, 1.0)


def demonstration_tracks(demo: Demonstration, humans: bool = True) -> list[RigidTrack]:
    """Human parts (optional) and objects of a demonstration as renderable tracks."""
    tracks = []
    if humans:
        for k, name in enumerate(demo.part_names):
            tracks.append(RigidTrack(name, demo.surface.vertices[k], demo.surface.faces[k],
                                     demo.part_pos_w[:, k], demo.part_quat_w[:, k], HUMAN_RGBA))
    for o in demo.objects:
        tracks.append(RigidTrack(o.name, o.vertices, o.faces, o.pos_w, o.quat_w,
                                 TABLE_RGBA if o.static else (0.8, 0.55, 0.3, 1.0)))
    return tracks


def _resample_track(track: RigidTrack, frames: np.ndarray) -> RigidTrack:
    return RigidTrack(track.name, track.vertices, track.faces, track.pos_w[frames], track.quat_w[frames], track.rgba)


def save_comparison(demo: Demonstration, ref: Reference | None, path: str | Path, count: int = 6,
                    width: int = 300, height: int = 380) -> Path:
    """A grid PNG: the demonstration (top) and, when given, the reference (bottom) at ``count``
    evenly spaced instants of the demonstration's duration."""
    times = np.linspace(0.0, demo.duration_s, count)
    demo_frames = np.clip(np.rint(times * demo.fps).astype(int), 0, demo.num_frames - 1)
    pelvis = demo.part_pos_w[:, 0]
    rows = [SceneRenderer(demonstration_tracks(demo), robot=False, width=width, height=height)
            .render(demo_frames, follow=pelvis)]
    if ref is not None:
        ref_frames = np.clip(np.rint(times * ref.fps).astype(int), 0, ref.num_frames - 1)
        # the reference's own objects, plus the demonstration's static furniture at the same instants
        furniture = [_resample_track(t, demo_frames) for t in demonstration_tracks(demo, humans=False)
                     if t.name not in {o.name for o in ref.objects}]
        ref_tracks = [_resample_track(t, ref_frames) for t in reference_tracks(ref)]
        renderer = SceneRenderer(ref_tracks + furniture, robot=True, width=width, height=height)
        qpos = ref.qpos()[ref_frames]
        rows.append(renderer.render(range(count), robot_qpos=qpos, follow=pelvis[demo_frames]))
    return save_png(grid(rows), path)
