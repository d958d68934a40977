"""``otr view`` in a real browser: headless Chromium (Debian's ``chromium``) driven by Playwright.

The page is loaded, the frame slider is moved with the keyboard like a user would, and the
rendered canvas is checked: the robot's pose changed, and the foot whose ground contact is
annotated turns the ground colour (orange) only on the frames where it is annotated.
``OTR_VIEWER_SCREENSHOT=docs/img/viewer.png`` also saves the README picture (the person beside).
"""

from __future__ import annotations

import io
import os
import socket
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from otr_gym import robot
from otr_gym.reference import ContactAnnotations, Reference
from retarget.cli.viewer import CHROMIUM_ARGS, GROUND_COLOUR, open_viewer

CHROMIUM = Path("/usr/bin/chromium")
pytest.importorskip("viser", reason="viser is not installed (pip install 'otr-gym[viewer]')")
sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install playwright)")
if not CHROMIUM.is_file():
    pytest.skip(f"{CHROMIUM} is absent (Debian: apt-get install chromium)", allow_module_level=True)

CONTACT_LINK = "left_ankle_roll_link"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def annotated_walk(walking_reference) -> Reference:
    """The procedural walk with a ground contact annotated on the left foot in the second half only."""
    ref = Reference.load(walking_reference)
    distance = np.full((ref.num_frames, len(robot.BODY_NAMES), 1), 0.5)
    distance[ref.num_frames // 2:, robot.BODY_NAMES.index(CONTACT_LINK), 0] = 0.005
    ref.contacts = ContactAnnotations(robot.BODY_NAMES, ("ground",), distance)
    return ref


def _orange_pixels(png: bytes) -> int:
    """Pixels of the ground-contact colour (shaded): hue near orange, saturated, bright."""
    import imageio.v3 as iio

    rgb = iio.imread(io.BytesIO(png))[..., :3].astype(int)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    assert GROUND_COLOUR == (255, 120, 0)  # the test's colour window is made for this one
    return int(((r > 120) & (b < 0.45 * r) & (g > 0.25 * r) & (g < 0.75 * r)).sum())


@pytest.fixture(scope="module")
def browser():
    with sync_api.sync_playwright() as pw:
        chromium = pw.chromium.launch(executable_path=str(CHROMIUM), args=list(CHROMIUM_ARGS))
        yield chromium
        chromium.close()


@contextmanager
def _viewer_page(browser, viewer):
    """A page on ``viewer``, closed afterwards with the viewer: a software-WebGL page left open
    keeps rendering and starves the next test's page of the CPU (its canvas then never came)."""
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    try:
        page.goto(f"http://127.0.0.1:{viewer.server.get_port()}")
        page.wait_for_selector("canvas")
        page.get_by_text("frame 0 /").wait_for()
        # the client's notice that WebGL runs in software (no GPU here) would cover part of the scene
        page.add_style_tag(content=".mantine-Notification-root { display: none !important; }")
        page.wait_for_timeout(1000)  # meshes arrive and render
        yield page
    finally:
        page.close()
        viewer.close()


def _canvas(page) -> bytes:
    """The 3D view left of the side panel (a page screenshot: element shots of a software
    WebGL canvas take 10 s)."""
    return page.screenshot(clip={"x": 0, "y": 0, "width": 930, "height": 800})


def test_slider_moves_the_robot_and_an_annotated_contact_turns_the_foot_orange(browser, annotated_walk):
    viewer = open_viewer({"walk": annotated_walk}, port=_free_port())
    with _viewer_page(browser, viewer) as page:
        before = _canvas(page)
        assert _orange_pixels(before) < 20  # frame 0: nothing annotated
        last = annotated_walk.num_frames - 1
        page.locator("[role=slider]").first.focus()
        page.keyboard.press("End")
        page.get_by_text(f"frame {last} / {last}").wait_for()
        page.wait_for_timeout(1000)
        after = _canvas(page)
        assert viewer.frame == last  # the browser's slider drove the server
        assert page.get_by_text(f"contacts: {CONTACT_LINK}–ground").count() == 1
        import imageio.v3 as iio

        diff = np.abs(iio.imread(io.BytesIO(after)).astype(int) - iio.imread(io.BytesIO(before)).astype(int))
        assert (diff.max(axis=-1) > 40).sum() > 500  # the robot walked: its pixels moved
        assert _orange_pixels(after) > 60  # the annotated foot is drawn in the ground colour
        page.locator("[role=slider]").first.focus()
        page.keyboard.press("Home")
        page.get_by_text("frame 0 /").wait_for()
        page.wait_for_timeout(1000)
        assert _orange_pixels(_canvas(page)) < 20  # and back to its own colour without the contact


@pytest.fixture(scope="module")
def retargeted_walk():
    """Two seconds of the synthetic walk and its native-scale reference (a few seconds to solve)."""
    from retarget.clip import retarget_demonstration
    from retarget.config import load_config

    from clips import clip

    demo = clip("walk", 40, 100)
    return retarget_demonstration(demo, load_config()), demo


def test_the_person_beside_the_robot_with_the_eval_metrics_and_the_readme_picture(browser, retargeted_walk):
    reference, demo = retargeted_walk
    viewer = open_viewer({"ours": reference}, demo, port=_free_port())
    with _viewer_page(browser, viewer) as page:
        page.get_by_text("ground J").wait_for(timeout=60_000)  # otr score's table, computed in the background
        frame_box = page.locator("input.mantine-NumberInput-input").first  # the number beside the slider
        frame_box.fill("60")
        frame_box.press("Enter")
        page.get_by_text("frame 60 /").wait_for()
        page.wait_for_timeout(1500)
        png = page.screenshot()
        assert _orange_pixels(png) > 60  # feet on the floor: the person's and the robot's
        assert viewer.track.metrics["ground_jaccard"] > 0.5
        target = os.environ.get("OTR_VIEWER_SCREENSHOT")
        if target:
            Path(target).parent.mkdir(parents=True, exist_ok=True)
            Path(target).write_bytes(png)


def test_references_of_one_demonstration_are_switchable_on_the_page(browser, annotated_walk, standing_reference):
    stand = Reference.load(standing_reference)
    viewer = open_viewer({"walk": annotated_walk, "stand": stand}, port=_free_port())
    with _viewer_page(browser, viewer) as page:
        page.get_by_text(f"frame 0 / {annotated_walk.num_frames - 1}").wait_for()
        page.locator("input.mantine-Select-input[value='walk']").click()
        page.get_by_role("option", name="stand").click()
        page.get_by_text(f"stand · frame 0 / {stand.num_frames - 1}").wait_for()
        assert viewer.current == "stand" and viewer.track.contact_links is None
        assert page.get_by_text("contacts: no annotations in this reference").count() == 1


def test_a_demonstration_alone_is_shown_with_its_floor_contacts(browser):
    from clips import clip

    demo = clip("walk", 40, 70)
    viewer = open_viewer({}, demo, port=_free_port())
    with _viewer_page(browser, viewer) as page:
        page.get_by_text(f"frame 0 / {demo.num_frames - 1}").wait_for()
        assert viewer.track is None and _orange_pixels(_canvas(page)) > 30  # its soles on the floor
