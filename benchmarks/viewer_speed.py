"""``otr view`` in headless Chromium: page load time and frames per second while playing a
500-frame reference.

    python benchmarks/viewer_speed.py [--frames 500] [--seconds 8]

The reference is the procedural walk (``agents.procedural``) at 50 fps with its ground contacts
annotated on every frame where a sole is down (so the colours change while it plays). Chromium
is Debian's (``/usr/bin/chromium``, software WebGL: no GPU), driven by Playwright.

- load: from ``page.goto`` until the canvas and the frame counter are on the page and the
  robot's meshes have arrived (the first frame drawn with them);
- render fps: ``requestAnimationFrame`` callbacks per second while playing;
- reference frames/s: distinct frame numbers the page displayed per second while playing at
  speed 1 (the reference's own rate is 50).
"""

from __future__ import annotations

import argparse
import os
import platform
import socket
import sys
import time

import numpy as np

from retarget.cli.viewer import CHROMIUM_ARGS, open_viewer


def walk_reference(frames: int):
    from agents.procedural import WalkSpec, walking_reference
    from otr_gym import robot
    from otr_gym.reference import ContactAnnotations

    spec = WalkSpec(steps=max(2, int((frames / 50.0 - 1.0) / 0.5)), fps=50.0)
    ref = walking_reference(spec)
    keep = slice(0, min(frames, ref.num_frames))
    ref = type(ref).from_qpos(ref.qpos()[keep], ref.fps)
    feet = [robot.BODY_NAMES.index(n) for n in ("left_ankle_roll_link", "right_ankle_roll_link")]
    distance = np.full((ref.num_frames, len(robot.BODY_NAMES), 1), 0.5)
    distance[:, feet, 0] = ref.body_pos_w[:, feet, 2] - ref.body_pos_w[:, feet, 2].min(axis=0)
    ref.contacts = ContactAnnotations(robot.BODY_NAMES, ("ground",), distance)
    return ref


def main() -> int:
    from playwright.sync_api import sync_playwright

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=500)
    parser.add_argument("--seconds", type=float, default=8.0, help="how long to play (s)")
    parser.add_argument("--no-shadows", action="store_true", help="the viewer's --no-shadows")
    parser.add_argument("--viewport", default="1280x800", help="browser window, WIDTHxHEIGHT pixels")
    args = parser.parse_args()
    ref = walk_reference(args.frames)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    viewer = open_viewer({"walk": ref}, port=port, shadows=not args.no_shadows)
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=list(CHROMIUM_ARGS))
            width, height = (int(v) for v in args.viewport.split("x"))
            page = browser.new_page(viewport={"width": width, "height": height})
            start = time.perf_counter()
            page.goto(f"http://127.0.0.1:{port}")
            page.wait_for_selector("canvas")
            page.get_by_text("frame 0 /").wait_for()
            page.evaluate("() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
            load_s = time.perf_counter() - start
            page.evaluate("""() => {
                window.__frames = 0; window.__shown = [];
                const tick = () => { window.__frames++; requestAnimationFrame(tick); }; requestAnimationFrame(tick);
                const box = document.querySelector('input.mantine-NumberInput-input');
                setInterval(() => { const v = box.value; const s = window.__shown;
                                    if (!s.length || s[s.length - 1] !== v) s.push(v); }, 5);
            }""")
            page.get_by_role("button", name="play").click()
            time.sleep(1.0)  # playing
            page.evaluate("() => { window.__frames = 0; window.__shown = []; }")
            time.sleep(args.seconds)
            raf, shown = page.evaluate("() => [window.__frames, window.__shown.length]")
            browser.close()
    finally:
        viewer.close()
    print(f"{ref.num_frames}-frame reference at {ref.fps:g} fps; {platform.node()}, {os.cpu_count()} cores, "
          f"{time.strftime('%Y-%m-%d')}; Debian chromium, software WebGL; "
          f"shadows {not args.no_shadows}, {args.viewport} window")
    print(f"page load {load_s:.2f} s; while playing: {raf / args.seconds:.1f} render fps, "
          f"{shown / args.seconds:.1f} reference frames/s shown")
    return 0


if __name__ == "__main__":
    sys.exit(main())
