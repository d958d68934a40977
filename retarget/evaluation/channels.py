"""Object channels of a comparison: which demonstrated object each reference track is.

Every demonstrated object is a channel. Its retargeted pose is the reference's track of the
same name; when the demonstration and the reference hold exactly one object each, they are
the same object whatever their names (OmniRetarget calls the OMOMO box 'largebox_link').
Static furniture (a table) that the reference does not carry stays where the demonstration
has it; a manipulated object the reference lacks is an error: its interactions cannot be
scored. The retargeted surface is the reference's own mesh when it carries one (object
substitution), else the demonstrated mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from otr_gym.reference import InvalidReferenceError, Reference
from retarget.inputs.demonstration import Demonstration
from retarget.inputs.meshes import TriMesh, object_mesh


@dataclass(frozen=True)
class ObjectChannel:
    """One object at the reference's frame times: demonstrated (mapped into the reference's
    world, see ``scale``) and retargeted. Poses are world (m, wxyz), meshes in the object frame (m).
    """

    name: str
    demo_mesh: TriMesh
    demo_pos_w: np.ndarray  # (T, 3)
    demo_quat_w: np.ndarray  # (T, 4)
    ref_mesh: TriMesh
    ref_pos_w: np.ndarray  # (T, 3)
    ref_quat_w: np.ndarray  # (T, 4)
    tracked: bool  # the reference carries this object's track (False: static, demo pose reused)
    static: bool

    def drift_m(self) -> np.ndarray:
        """(T,) distance between the retargeted and demonstrated object positions (m)."""
        return np.linalg.norm(self.ref_pos_w - self.demo_pos_w, axis=-1)


def reference_tracks(ref: Reference, demo: Demonstration) -> list:
    """The reference's ObjectTrack for each demonstrated object, or None (see module docstring)."""
    by_name = {o.name: o for o in ref.objects}
    if len(demo.objects) == 1 and len(ref.objects) == 1:
        return [ref.objects[0]]
    out = []
    for o in demo.objects:
        track = by_name.get(o.name)
        if track is None and not o.static:
            raise InvalidReferenceError(
                f"{ref.source}: has no track for object '{o.name}' that the demonstration "
                f"{demo.source.get('path', demo.name)} manipulates (reference objects: {sorted(by_name) or 'none'})")
        out.append(track)
    return out


def object_channels(ref: Reference, demo_scaled: Demonstration, tracks: list) -> list[ObjectChannel]:
    """Channels from the demonstration (already at the reference's times and scale) and the
    matched reference tracks (``reference_tracks``)."""
    out = []
    for o, track in zip(demo_scaled.objects, tracks):
        demo_mesh = object_mesh(o.vertices, o.faces, o.mesh_path or f"object '{o.name}' of {demo_scaled.name}")
        if track is None:
            out.append(ObjectChannel(o.name, demo_mesh, o.pos_w, o.quat_w, demo_mesh, o.pos_w, o.quat_w,
                                     tracked=False, static=o.static))
            continue
        ref_mesh = demo_mesh
        if track.mesh_vertices is not None and track.mesh_faces is not None:
            ref_mesh = object_mesh(track.mesh_vertices, track.mesh_faces, f"{ref.source}: mesh of '{track.name}'")
        out.append(ObjectChannel(o.name, demo_mesh, o.pos_w, o.quat_w, ref_mesh, track.pos_w, track.quat_w,
                                 tracked=True, static=o.static))
    return out
