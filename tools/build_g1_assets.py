"""Rebuild ``otr_gym/assets/g1`` from Unitree's G1 model as shipped in the mjlab wheel.

    pip install pymeshlab          # the decimator (build time only)
    python tools/build_g1_assets.py [--wheel mjlab-1.6.0-py3-none-any.whl] [--tolerance-mm 0.8]

Steps: fetch the mjlab 1.6.0 wheel from PyPI (or use ``--wheel``), take
``mjlab/asset_zoo/robots/unitree_g1/xmls/g1.xml`` and its STL meshes, and decimate every visual
mesh with a bounded error: each connected piece separately (so no piece merges or falls
apart), by quadric edge collapse (MeshLab, topology and boundaries preserved), with the
largest reduction whose two-sided distance to the original piece (vertices and area samples,
both ways) stays within ``--tolerance-mm``. Then add what the RL spec needs: position
actuators (kp, kd, effort from ``otr_gym.robot``), joint armature, the 200 Hz physics options
and the "knees_bent" keyframe. Prints the per-link error table (``otr_gym.true_surface``:
outer-surface p99/max, surface error, hull volume change, pieces) and writes it to
``mesh_error.json``, whose surface error is the margin the solver and ``retarget.checks.verify`` add
to keep their checks conservative. The model stays under Unitree's BSD-3-Clause licence
(``otr_gym/assets/g1/LICENSE``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import igl
import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from otr_gym import robot  # noqa: E402
from otr_gym.true_surface import (  # noqa: E402
    ORIGINAL_STEM,
    fetch_wheel,
    mesh_error,
    read_wheel,
    write_error_table,
)

#: Pieces with fewer triangles are kept as they are.
MIN_FACES = 64
#: Bisection steps on the reduction ratio (the last accepted ratio is within 1 % of the best).
BISECTION_STEPS = 7


def _two_sided_distance_m(a: trimesh.Trimesh, b: trimesh.Trimesh, samples: int = 3000) -> float:
    """Largest distance of a's vertices and area samples to b, and of b's to a (m)."""
    worst = 0.0
    for src, dst in ((a, b), (b, a)):
        pts = np.concatenate([src.vertices, trimesh.sample.sample_surface(src, samples, seed=0)[0]])
        d2, _, _ = igl.point_mesh_squared_distance(pts, np.asarray(dst.vertices, np.float64),
                                                   np.asarray(dst.faces, np.int64))
        worst = max(worst, float(np.sqrt(d2.max())))
    return worst


def _stl_round_trip(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh as it loads back from the shipped STL file (float32 vertices, merged)."""
    return trimesh.load(trimesh.util.wrap_as_stream(mesh.export(file_type="stl")), file_type="stl", process=True)


def _collapse(piece: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(piece.vertices, np.float64), np.asarray(piece.faces, np.int32)))
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(faces), preservetopology=True,
                                                preserveboundary=True, boundaryweight=2.0, optimalplacement=True,
                                                planarquadric=True, qualitythr=0.3, autoclean=True)
    out = ms.current_mesh()
    return _stl_round_trip(trimesh.Trimesh(out.vertex_matrix(), out.face_matrix(), process=True))


def decimate_piece(piece: trimesh.Trimesh, tolerance_m: float) -> trimesh.Trimesh:
    """The coarsest decimation of one connected piece that stays one piece (as the STL file
    loads back) within the tolerance."""
    if len(piece.faces) < MIN_FACES:
        return piece
    lo, hi, best = 0.0, 0.98, piece
    for _ in range(BISECTION_STEPS):
        ratio = 0.5 * (lo + hi)
        candidate = _collapse(piece, len(piece.faces) * (1.0 - ratio))
        ok = (len(candidate.faces) >= 4 and len(candidate.split(only_watertight=False)) == 1
              and _two_sided_distance_m(piece, candidate) <= tolerance_m)
        lo, hi, best = (ratio, hi, candidate) if ok else (lo, ratio, best)
    return best


def decimate(data: bytes, tolerance_m: float) -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """(original, decimated) of an STL file's bytes."""
    mesh = trimesh.load(trimesh.util.wrap_as_stream(data), file_type="stl", process=True)
    pieces = mesh.split(only_watertight=False)
    return mesh, trimesh.util.concatenate([decimate_piece(p, tolerance_m) for p in pieces])


def print_table(table: dict) -> None:
    print(f"{'link':26s} {'faces':>13s} {'p99 mm':>7s} {'max mm':>7s} {'surf mm':>8s} {'hull %':>7s} {'pieces':>7s}")
    for name, e in sorted(table.items()):
        print(f"{name:26s} {e.faces[0]:6d}>{e.faces[1]:6d} {e.p99_mm:7.2f} {e.max_mm:7.2f} {e.surface_error_mm:8.2f} "
              f"{e.hull_volume_change_pct:+7.2f} {e.components[0]:3d}>{e.components[1]:<3d}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--wheel", type=Path, help="mjlab wheel (downloaded from PyPI when omitted)")
    ap.add_argument("--tolerance-mm", type=float, default=0.8,
                    help="largest two-sided distance between a decimated piece and its original (mm)")
    ap.add_argument("--out", type=Path, default=ROOT / "otr_gym" / "assets" / "g1")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        xml_text, meshes = read_wheel(args.wheel or fetch_wheel(Path(tmp)))

    tree = ET.ElementTree(ET.fromstring(xml_text))
    root = tree.getroot()
    root.find("compiler").set("meshdir", "meshes")
    mesh_dir = args.out / "meshes"
    mesh_dir.mkdir(parents=True, exist_ok=True)
    for old in mesh_dir.glob("*.stl"):
        old.unlink()
    table = {}
    stem_to_name = {v: k for k, v in ORIGINAL_STEM.items()}
    for mesh in root.find("asset").iter("mesh"):
        src = mesh.get("file")
        dst = f"{mesh.get('name')}.stl"
        original, shipped = decimate(meshes[src], args.tolerance_mm * 1e-3)
        shipped.export(mesh_dir / dst)
        table[stem_to_name.get(Path(src).stem, mesh.get("name"))] = mesh_error(original, _stl_round_trip(shipped))
        mesh.set("file", dst)

    # Physics options of the RL spec (§1): 200 Hz, Newton, 10 iterations, 20 line-search iterations.
    option = ET.Element("option", timestep="0.005", iterations="10", ls_iterations="20")
    root.insert(1, option)

    names = list(robot.JOINT_NAMES)
    for joint in root.iter("joint"):
        if joint.get("name") in names:
            i = names.index(joint.get("name"))
            joint.set("armature", f"{robot.ARMATURE[i]:.8g}")
            joint.set("actuatorfrcrange", f"{-robot.EFFORT_LIMIT[i]:.6g} {robot.EFFORT_LIMIT[i]:.6g}")

    actuator = ET.SubElement(root, "actuator")
    for i, name in enumerate(names):
        ET.SubElement(actuator, "position", name=name.removesuffix("_joint"), joint=name,
                      kp=f"{robot.KP[i]:.8g}", kv=f"{robot.KD[i]:.8g}",
                      forcerange=f"{-robot.EFFORT_LIMIT[i]:.6g} {robot.EFFORT_LIMIT[i]:.6g}")

    keyframe = ET.SubElement(root, "keyframe")
    qpos = robot.default_qpos()
    ET.SubElement(keyframe, "key", name="knees_bent", qpos=" ".join(f"{x:.6g}" for x in qpos),
                  ctrl=" ".join(f"{x:.6g}" for x in robot.DEFAULT_JOINT_POS))

    ET.indent(tree, space="  ")
    header = ("<!-- Unitree G1 29-DoF (BSD-3-Clause, see LICENSE), from the mjlab 1.6.0 wheel;\n"
              "     generated by tools/build_g1_assets.py: error-bounded decimated meshes, actuators, keyframe. -->\n")
    (args.out / "g1.xml").write_text(header + ET.tostring(root, encoding="unicode") + "\n")
    write_error_table(table, args.out / "mesh_error.json")
    print_table(table)
    total = sum(p.stat().st_size for p in args.out.rglob("*") if p.is_file())
    print(f"wrote {args.out} ({total / 1e6:.2f} MB, {len(meshes)} meshes)")


if __name__ == "__main__":
    main()
