"""Body units: what a sample (t, u, c) pairs with a channel, on the human and on the robot.

Units come from the one human-part <-> G1-link table ``retarget.inputs.human.G1_LINK_PARTS``: a unit
is a connected group of that table, i.e. a set of G1 links (with visual meshes) and the set
of human parts they map to, closed under sharing — links that share a human part are one
unit, and so are parts that share a link. The robot unit is the union of its links' visual
meshes posed by the reference; the demonstrated unit is the **union of its human parts'
surface vertices** posed by the demonstration. Each link and each part belongs to exactly
one unit, so both bodies are partitioned the same way. With the current table the units are
pelvis, waist, trunk (torso link and shoulder pitch housings <-> spine, neck, head, collars),
and per side thigh (hip pitch/roll/yaw <-> hip), knee, foot (ankle pitch and roll <-> ankle,
foot), upper arm, forearm (elbow, wrist roll <-> elbow) and hand (wrist pitch and yaw <-> wrist).

Why groups and not single links: several small G1 housings take a part that they only cover
a piece of (the ankle pitch housing takes the whole human foot part). Scored alone, such a
housing would be asked to touch the floor wherever the foot does — something no robot can do —
and every method would lose recall on it for nothing.

A posed unit is kept as rigid pieces (vertices in the piece frame) and their poses over time,
never as a (T, V, 3) array of every vertex: the proximity queries first bound whole pieces
by their spheres and pose only the vertices of pieces that may be close.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from otr_gym.rotations import quat_to_matrix


@dataclass(frozen=True)
class BodyUnit:
    """G1 links and the human parts whose surface they stand for; named after the parts."""

    links: tuple[str, ...]
    parts: tuple[str, ...]

    @property
    def name(self) -> str:
        """The parts joined by '+', the middle elided beyond two ('Spine2+…+R_Collar')."""
        return "+".join(self.parts) if len(self.parts) <= 2 else f"{self.parts[0]}+…+{self.parts[-1]}"


def group_units(link_parts: dict[str, tuple[str, ...]]) -> tuple[BodyUnit, ...]:
    """Connected groups of a link -> parts table (see module docstring), in table order."""
    groups: list[tuple[list[str], list[str]]] = []
    for link, parts in link_parts.items():
        touching = [g for g in groups if set(g[1]) & set(parts)]
        merged = ([], [])
        for g in touching:
            merged[0].extend(g[0])
            merged[1].extend(p for p in g[1] if p not in merged[1])
            groups.remove(g)
        merged[0].append(link)
        merged[1].extend(p for p in parts if p not in merged[1])
        groups.append(merged)
    order = {link: i for i, link in enumerate(link_parts)}
    groups.sort(key=lambda g: min(order[lk] for lk in g[0]))
    return tuple(BodyUnit(tuple(sorted(g[0], key=order.get)), tuple(g[1])) for g in groups)


def default_units() -> tuple[BodyUnit, ...]:
    """Units of ``G1_LINK_PARTS`` restricted to the G1 links that have a visual mesh."""
    from otr_gym.robot_geometry import visual_meshes
    from retarget.inputs.human import G1_LINK_PARTS

    meshes = visual_meshes()
    return group_units({link: tuple(parts) for link, parts in G1_LINK_PARTS.items() if link in meshes})


@dataclass(frozen=True)
class Piece:
    """Rigid surface vertices (V, 3) in their own frame (m) and a bounding sphere."""

    vertices: np.ndarray
    centre: np.ndarray  # (3,)
    radius: float

    @classmethod
    def of(cls, vertices: np.ndarray) -> Piece:
        v = np.asarray(vertices, np.float64)
        centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
        return cls(v, centre, float(np.linalg.norm(v - centre, axis=1).max()))


@dataclass(frozen=True)
class PosedUnit:
    """A unit's rigid pieces and their poses over T frames in some frame (world or a channel's)."""

    pieces: tuple[Piece, ...]
    pos: np.ndarray  # (T, K, 3) m
    rot: np.ndarray  # (T, K, 3, 3)

    @classmethod
    def from_poses(cls, pieces, pos_w: np.ndarray, quat_w: np.ndarray) -> PosedUnit:
        """Pieces with world poses (T, K, 3) m / (T, K, 4) wxyz."""
        return cls(tuple(pieces), np.asarray(pos_w, np.float64), quat_to_matrix(np.asarray(quat_w, np.float64)))

    @property
    def num_frames(self) -> int:
        return self.pos.shape[0]

    def frames(self, index) -> PosedUnit:
        return PosedUnit(self.pieces, self.pos[index], self.rot[index])

    def in_frame(self, pos_w: np.ndarray, quat_w: np.ndarray) -> PosedUnit:
        """The same unit expressed in a moving frame with world poses (T, 3) / (T, 4) wxyz."""
        r_t = np.swapaxes(quat_to_matrix(np.asarray(quat_w, np.float64)), -1, -2)[:, None]  # (T, 1, 3, 3)
        return PosedUnit(self.pieces, np.einsum("tkij,tkj->tki", r_t, self.pos - pos_w[:, None]),
                         np.matmul(r_t, self.rot))

    def centres(self) -> np.ndarray:
        """(T, K, 3) sphere centres of the pieces."""
        c = np.stack([p.centre for p in self.pieces])
        return np.einsum("tkij,kj->tki", self.rot, c) + self.pos

    def radii(self) -> np.ndarray:
        return np.array([p.radius for p in self.pieces])

    def vertices(self, frames=slice(None)) -> np.ndarray:
        """Posed vertices (n, V, 3) at ``frames``, pieces concatenated in order."""
        rot, pos = self.rot[frames], self.pos[frames]
        return np.concatenate([np.matmul(p.vertices, np.swapaxes(rot[:, k], -1, -2)) + pos[:, k, None]
                               for k, p in enumerate(self.pieces)], axis=1)
