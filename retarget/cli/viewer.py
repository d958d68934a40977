"""``otr view``: a web viewer (viser) for references and demonstrations.

    otr view FILE… [--demo DEMO] [--port 8080] [--host 127.0.0.1] [--object MESH]

FILEs are references (ours, Holosoma, BeyondMimic, mjlab ``.npz``) of one demonstration —
switchable in the side panel, e.g. ours against Holosoma's — or demonstrations shown alone
(AMASS, OMOMO, BVH, ours). The page shows:

* the G1 (its visual meshes posed by forward kinematics of the reference's qpos) with the
  reference's objects, and the person (mannequin-x parts, posed rigidly per part) beside it or
  overlaid on it, with the demonstration's objects;
* a timeline slider (frames of the reference), play/pause and a speed factor; the person
  follows at the same time (nearest demonstration frame);
* contacts per channel from the reference's ``contact_distance`` annotations: a link within
  ε = 20 mm of a channel takes that channel's colour (ground: orange, objects: magenta, cyan,
  green, …) and so does the object; the person's parts within 20 mm of the floor turn orange;
* the metrics of ``otr score`` for the reference shown (computed in the background when a
  demonstration is given).

Everything the page shows is driven from this process: ``ReferenceViewer.show(frame)`` sets the
poses and colours, the GUI callbacks and the play loop call it.
"""

from __future__ import annotations

import argparse
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from otr_gym.reference_summary import CONTACT_EPS_M

GROUND_COLOUR = (255, 120, 0)
OBJECT_COLOURS = ((230, 40, 200), (0, 200, 230), (90, 220, 60), (250, 220, 0))
ROBOT_COLOUR = (185, 190, 200)
HUMAN_COLOUR = (215, 170, 130)
OBJECT_COLOUR = (110, 140, 200)
#: The person beside the robot: this offset (m, world) unless overlaid.
BESIDE_OFFSET_M = (0.0, 1.0, 0.0)
SPEEDS = ("0.25", "0.5", "1", "2", "4")
#: Chromium flags for headless use on a machine without a network or a GPU (tests, benchmarks).
CHROMIUM_ARGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run", "--enable-unsafe-swiftshader")


@dataclass
class RobotTrack:
    """One reference prepared for display: G1 link poses and objects per frame, contacts."""

    name: str
    fps: float
    link_names: tuple[str, ...]
    link_pos: np.ndarray  # (T, L, 3) world
    link_quat: np.ndarray  # (T, L, 4) wxyz
    objects: list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]  # name, V, F, pos (T,3), quat (T,4)
    channel_names: tuple[str, ...] = ()
    contact_links: np.ndarray | None = None  # (T, L, C) bool, links in link_names order
    metrics: dict | None = None
    metrics_note: str = ""

    @property
    def num_frames(self) -> int:
        return int(self.link_pos.shape[0])


def robot_track(name: str, ref, demo=None) -> RobotTrack:
    """Link poses by MuJoCo forward kinematics of the reference's qpos (any layout that loads),
    objects with their embedded meshes (else the demonstration's mesh of that name)."""
    import mujoco

    from otr_gym import robot
    from otr_gym.robot_geometry import visual_meshes
    from otr_gym.scene import robot_model

    meshes = visual_meshes()
    model = robot_model(visual=False)
    data = mujoco.MjData(model)
    links = tuple(b for b in robot.BODY_NAMES if b in meshes)
    ids = [model.body(b).id for b in links]
    qpos = ref.qpos()
    pos, quat = np.empty((len(qpos), len(ids), 3)), np.empty((len(qpos), len(ids), 4))
    for t, q in enumerate(qpos):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        pos[t], quat[t] = data.xpos[ids], data.xquat[ids]
    demo_meshes = {o.name: o for o in (demo.objects if demo is not None else [])}
    objects = []
    for o in ref.objects:
        if o.mesh_vertices is not None:
            objects.append((o.name, o.mesh_vertices, o.mesh_faces, o.pos_w, o.quat_w))
        elif o.name in demo_meshes:
            objects.append((o.name, demo_meshes[o.name].vertices, demo_meshes[o.name].faces, o.pos_w, o.quat_w))
    contacts, channels = None, ()
    if ref.contacts is not None:
        c = ref.contacts
        index = {b: i for i, b in enumerate(c.body_names)}
        touching = c.in_contact(CONTACT_EPS_M)
        contacts = np.zeros((ref.num_frames, len(links), len(c.channel_names)), dtype=bool)
        for j, link in enumerate(links):
            if link in index:
                contacts[:, j] = touching[:, index[link]]
        channels = tuple(c.channel_names)
    return RobotTrack(name, float(ref.fps), links, pos, quat, objects, channels, contacts)


@dataclass
class PersonTrack:
    """A demonstration prepared for display: part poses, surface pieces, floor contacts."""

    name: str
    fps: float
    part_pos: np.ndarray  # (T, P, 3)
    part_quat: np.ndarray  # (T, P, 4)
    vertices: list[np.ndarray]
    faces: list[np.ndarray]
    on_floor: np.ndarray  # (T, P) bool: the part's lowest point within ε of z = 0
    objects: list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)

    @property
    def num_frames(self) -> int:
        return int(self.part_pos.shape[0])


def person_track(demo) -> PersonTrack:
    from otr_gym.rotations import quat_to_matrix

    rot_z = quat_to_matrix(demo.part_quat_w)[..., 2, :]  # (T, P, 3)
    lowest = np.stack([(rot_z[:, k] @ v.T).min(axis=-1) + demo.part_pos_w[:, k, 2]
                       for k, v in enumerate(demo.surface.vertices)], axis=-1)
    objects = [(o.name, o.vertices, o.faces, o.pos_w, o.quat_w) for o in demo.objects]
    return PersonTrack(demo.name, float(demo.fps), demo.part_pos_w, demo.part_quat_w, demo.surface.vertices,
                       demo.surface.faces, lowest < CONTACT_EPS_M, objects)


def metrics_markdown(metrics: dict | None, note: str = "") -> str:
    """The ``otr score`` metrics of one reference as a markdown table (paper units)."""
    from retarget.evaluation.sequence import TABLE_COLUMNS

    if metrics is None:
        return f"**otr score**  \n{note or 'no demonstration given (--demo)'}"
    rows = ["| metric | value |", "|---|---|"]
    groups = {"dd": "ground ", "R": "ground ", "P": "ground ", "J": "ground "}
    for key, label, unit, factor, digits in TABLE_COLUMNS:
        value = metrics.get(key)
        prefix = "object " if key.startswith("object") else groups.get(label, "")
        text = "–" if value is None or not np.isfinite(value) else f"{value * factor:.{digits}f} {unit}".strip()
        rows.append(f"| {prefix}{label} | {text} |")
    return "**otr score**\n\n" + "\n".join(rows)


class ReferenceViewer:
    """The viser page for several references of one demonstration, or a demonstration alone."""

    def __init__(self, tracks: list[RobotTrack], person: PersonTrack | None, *, host: str = "127.0.0.1",
                 port: int = 8080, demo=None, references: dict | None = None, shadows: bool = True) -> None:
        """``demo`` and ``references`` (name -> Reference, the tracks' sources) enable the metrics;
        ``shadows=False`` halves the drawing work (browsers without a GPU)."""
        import viser

        if not tracks and person is None:
            raise ValueError("nothing to show: give references and/or a demonstration")
        self.tracks = {t.name: t for t in tracks}
        self.person = person
        self._demo = demo
        self._references = references or {}
        self._shading = {} if shadows else {"cast_shadow": False, "receive_shadow": False}
        self.server = viser.ViserServer(host=host, port=port, label="OTR-Gym", verbose=False)
        self.server.scene.set_up_direction("+z")
        self.server.scene.add_grid("/floor", width=20.0, height=20.0, cell_size=0.5, plane="xy")
        self.current = tracks[0].name if tracks else None
        self.frame = 0
        self.colours: dict[str, tuple[int, int, int]] = {}
        self._lock = threading.RLock()
        self._link_handles: dict[str, object] = {}
        self._object_handles: dict[str, object] = {}
        self._part_handles: list = []
        self._person_object_handles: dict[str, object] = {}
        self._build_scene()
        self._aim_camera()
        self._build_gui()
        self._playing = False
        self._stop = threading.Event()
        self._player = threading.Thread(target=self._play_loop, daemon=True)
        self._player.start()
        if demo is not None and self._references:
            threading.Thread(target=self._compute_metrics, daemon=True).start()
        self.show(0)

    # ------------------------------------------------------------ scene

    @property
    def track(self) -> RobotTrack | None:
        return self.tracks.get(self.current) if self.current else None

    @property
    def num_frames(self) -> int:
        return self.track.num_frames if self.track else self.person.num_frames

    @property
    def fps(self) -> float:
        return self.track.fps if self.track else self.person.fps

    def _build_scene(self) -> None:
        from otr_gym.robot_geometry import visual_meshes

        scene = self.server.scene
        if self.tracks:
            meshes = visual_meshes()
            for link in next(iter(self.tracks.values())).link_names:
                m = meshes[link]
                self._link_handles[link] = scene.add_mesh_simple(f"/robot/{link}", m.vertices, m.faces,
                                                                 color=ROBOT_COLOUR, **self._shading)
            self._add_objects()
        if self.person is not None:
            for k, (v, f) in enumerate(zip(self.person.vertices, self.person.faces, strict=True)):
                self._part_handles.append(scene.add_mesh_simple(f"/person/part{k}", v, f, color=HUMAN_COLOUR,
                                                                **self._shading))
            for name, v, f, _, _ in self.person.objects:
                self._person_object_handles[name] = scene.add_mesh_simple(f"/person_objects/{name}", v, f,
                                                                          color=OBJECT_COLOUR, opacity=0.7,
                                                                          **self._shading)

    def _aim_camera(self) -> None:
        """Look at the middle of the motion from the front-left, at a distance that fits it."""
        if self.track is not None:
            path = self.track.link_pos[:, 0]
        else:
            path = self.person.part_pos[:, 0]
        centre = 0.5 * (path.min(axis=0) + path.max(axis=0))
        centre[2] = 0.7
        if self.person is not None and self.track is not None:
            centre += 0.5 * np.array(BESIDE_OFFSET_M)
        reach = max(2.5, 1.2 * float(np.ptp(path[:, :2], axis=0).max()))
        self.server.initial_camera.look_at = tuple(centre)
        self.server.initial_camera.position = tuple(centre + np.array([0.8 * reach, -0.9 * reach, 0.35 * reach]))

    def _add_objects(self) -> None:
        for handle in self._object_handles.values():
            handle.remove()
        self._object_handles = {}
        for name, v, f, _, _ in self.track.objects if self.track else []:
            self._object_handles[name] = self.server.scene.add_mesh_simple(f"/objects/{name}", v, f,
                                                                          color=OBJECT_COLOUR, **self._shading)

    # ------------------------------------------------------------ GUI

    def _build_gui(self) -> None:
        gui = self.server.gui
        if len(self.tracks) > 1:
            self.reference_choice = gui.add_dropdown("reference", tuple(self.tracks), initial_value=self.current)
            self.reference_choice.on_update(lambda _: self.select(self.reference_choice.value))
        self.slider = gui.add_slider("frame", min=0, max=max(self.num_frames - 1, 1), step=1, initial_value=0)
        self.slider.on_update(self._on_slider)
        self.play_button = gui.add_button("play")
        self.play_button.on_click(lambda _: self.toggle_play())
        self.speed = gui.add_dropdown("speed", SPEEDS, initial_value="1")
        if self.person is not None and self.tracks:
            self.layout = gui.add_dropdown("person", ("beside", "overlaid", "hidden"), initial_value="beside")
            self.layout.on_update(lambda _: self.show(self.frame))
        self.status = gui.add_markdown("")
        self.legend = gui.add_markdown(self._legend())
        self.metrics_panel = gui.add_markdown(metrics_markdown(None, "computing…" if self._demo is not None
                                                               else "no demonstration given (--demo)")
                                              if self.tracks else "")

    def _on_slider(self, _event) -> None:
        # show() moves the slider itself: that echo (the frame shown) must not redraw everything again
        if int(self.slider.value) != self.frame:
            self.show(int(self.slider.value))

    def _legend(self) -> str:
        if not self.track or not self.track.channel_names:
            return "contacts: no annotations in this reference" if self.track else "contacts: person on the floor"
        items = [f"<span style='color:rgb{self._channel_colour(c)}'>■</span> {name}"
                 for c, name in enumerate(self.track.channel_names)]
        return "contacts (ε 20 mm): " + " ".join(items)

    def _channel_colour(self, channel: int) -> tuple[int, int, int]:
        name = self.track.channel_names[channel]
        if name == "ground":
            return GROUND_COLOUR
        objects = [n for n in self.track.channel_names if n != "ground"]
        return OBJECT_COLOURS[objects.index(name) % len(OBJECT_COLOURS)]

    # ------------------------------------------------------------ state

    def select(self, name: str) -> None:
        """Show reference ``name`` (keeps the time)."""
        with self._lock:
            seconds = self.frame / self.fps
            self.current = name
            self._add_objects()
            self.colours = {k: v for k, v in self.colours.items() if not k.startswith("object:")}
            self.slider.max = max(self.num_frames - 1, 1)
            self.legend.content = self._legend()
            self.metrics_panel.content = metrics_markdown(self.track.metrics, self.track.metrics_note or "computing…")
            self.show(min(int(round(seconds * self.fps)), self.num_frames - 1))

    def _set_colour(self, key: str, handle, colour: tuple[int, int, int]) -> None:
        if self.colours.get(key) != colour:
            handle.color = colour
            self.colours[key] = colour

    def show(self, frame: int) -> None:
        """Pose and colour everything at ``frame`` of the current reference (or demonstration)."""
        with self._lock:
            frame = int(np.clip(frame, 0, self.num_frames - 1))
            self.frame = frame
            with self.server.atomic():
                self._show_robot(frame)
                self._show_person(frame)
                if int(self.slider.value) != frame:
                    self.slider.value = frame
                self.status.content = self._status(frame)

    def _show_robot(self, t: int) -> None:
        track = self.track
        if track is None:
            return
        touching = track.contact_links[t] if track.contact_links is not None else None  # (L, C)
        object_channel = {name: c for c, name in enumerate(track.channel_names)}
        object_hit = set()
        for j, link in enumerate(track.link_names):
            handle = self._link_handles[link]
            handle.position, handle.wxyz = track.link_pos[t, j], track.link_quat[t, j]
            colour = ROBOT_COLOUR
            if touching is not None and touching[j].any():
                c = int(np.flatnonzero(touching[j])[0])
                colour = self._channel_colour(c)
                object_hit.update(track.channel_names[i] for i in np.flatnonzero(touching[j]))
            self._set_colour(f"link:{link}", handle, colour)
        for name, _, _, pos, quat in track.objects:
            handle = self._object_handles[name]
            handle.position, handle.wxyz = pos[t], quat[t]
            colour = self._channel_colour(object_channel[name]) if name in object_hit else OBJECT_COLOUR
            self._set_colour(f"object:{name}", handle, colour)

    def _person_frame(self, t: int) -> int:
        if self.track is None:
            return t
        return int(np.clip(round(t / self.track.fps * self.person.fps), 0, self.person.num_frames - 1))

    def _show_person(self, t: int) -> None:
        if self.person is None:
            return
        layout = self.layout.value if self.tracks else "overlaid"
        visible = layout != "hidden"
        offset = np.array(BESIDE_OFFSET_M) if layout == "beside" else np.zeros(3)
        k = self._person_frame(t)
        for part, handle in enumerate(self._part_handles):
            handle.visible = visible
            handle.position = self.person.part_pos[k, part] + offset
            handle.wxyz = self.person.part_quat[k, part]
            self._set_colour(f"part:{part}", handle, GROUND_COLOUR if self.person.on_floor[k, part] else HUMAN_COLOUR)
        for name, _, _, pos, quat in self.person.objects:
            handle = self._person_object_handles[name]
            handle.visible = visible
            handle.position, handle.wxyz = pos[k] + offset, quat[k]

    def _status(self, t: int) -> str:
        text = f"**{self.current or self.person.name}** · frame {t} / {self.num_frames - 1} · {t / self.fps:.2f} s"
        track = self.track
        if track is not None and track.contact_links is not None:
            names = sorted({f"{track.link_names[j]}–{track.channel_names[c]}"
                            for j, c in zip(*np.nonzero(track.contact_links[t]), strict=True)})
            text += f"  \ncontacts: {', '.join(names) if names else 'none'}"
        return text

    # ------------------------------------------------------------ playback

    def toggle_play(self) -> None:
        self._playing = not self._playing
        self.play_button.label = "pause" if self._playing else "play"

    def _play_loop(self) -> None:
        last, position = time.perf_counter(), 0.0
        while not self._stop.is_set():
            time.sleep(0.01)
            now = time.perf_counter()
            if not self._playing:
                last, position = now, float(self.frame)
                continue
            position += (now - last) * self.fps * float(self.speed.value)
            last = now
            if position >= self.num_frames:
                position = 0.0
            if int(position) != self.frame:
                self.show(int(position))

    def close(self) -> None:
        self._stop.set()
        self.server.stop()

    # ------------------------------------------------------------ metrics

    def _compute_metrics(self) -> None:
        from retarget.evaluation.sequence import evaluate_sequence

        for name, track in self.tracks.items():
            try:
                ref = self._references[name]
                track.metrics = evaluate_sequence(ref, self._demo).as_dict()["metrics"]
            except Exception as exc:  # the page stays usable without metrics
                track.metrics_note = f"could not score this reference: {type(exc).__name__}: {exc}"
            if name == self.current:
                self.metrics_panel.content = metrics_markdown(track.metrics, track.metrics_note)


def open_viewer(references: dict, demo=None, *, host: str = "127.0.0.1", port: int = 8080,
                shadows: bool = True) -> ReferenceViewer:
    """A viewer for ``references`` (name -> Reference) of ``demo`` (or ``demo`` alone)."""
    tracks = [robot_track(name, ref, demo) for name, ref in references.items()]
    person = person_track(demo) if demo is not None else None
    return ReferenceViewer(tracks, person, host=host, port=port, demo=demo, references=dict(references),
                           shadows=shadows)


# ------------------------------------------------------------------ the command


def configure_parser(p: argparse.ArgumentParser) -> None:
    from retarget.inputs.bvh import add_arguments

    p.add_argument("files", nargs="+", type=Path, metavar="FILE",
                   help="references (.npz) of one demonstration, switchable on the page, or demonstrations alone")
    p.add_argument("--demo", type=Path, default=None, help="the demonstration the references were made from")
    p.add_argument("--object", type=Path, default=None, metavar="MESH", help="object mesh of the demonstration (OMOMO)")
    p.add_argument("--port", type=int, default=8080, help="port of the web page (default 8080)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1; 0.0.0.0 for all)")
    p.add_argument("--no-shadows", action="store_true", help="draw without shadows (faster in browsers without a GPU)")
    add_arguments(p)


def main(args: argparse.Namespace) -> int:
    import sys

    from otr_gym.reference import InvalidReferenceError, Reference
    from otr_gym.reference_summary import is_reference_file
    from retarget.inputs.bvh import options_from_args
    from retarget.inputs.demonstration import InvalidDemonstrationError
    from retarget.inputs.readers import load_demonstration

    try:
        references, demos = {}, []
        for path in args.files:
            if is_reference_file(path):
                name = path.stem if path.stem not in references else str(path)
                references[name] = Reference.load(path)
            else:
                demos.append(path)
        if args.demo is not None:
            demos.insert(0, args.demo)
        if len(demos) > 1:
            raise ValueError(f"one demonstration at a time, got {[str(d) for d in demos]}")
        demo = load_demonstration(demos[0], args.object, bvh=options_from_args(args)) if demos else None
        viewer = open_viewer(references, demo, host=args.host, port=args.port, shadows=not args.no_shadows)
    except (InvalidReferenceError, InvalidDemonstrationError, FileNotFoundError, ValueError) as exc:
        print(f"otr view: error: {exc}", file=sys.stderr)
        return 2
    print(f"otr view: http://{'localhost' if args.host in ('127.0.0.1', '0.0.0.0') else args.host}:"
          f"{viewer.server.get_port()}  (Ctrl-C to stop)")
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        viewer.close()
    return 0
