"""Pictures of the 3D pages (contactpose.view), taken in headless Chromium.

``python -m contactpose.harness.pages [DIR]`` writes, DIR defaulting to results/demo:

* DIR/view_banana.png: ``contactpose localize banana --contacts examples/banana_contacts.json
  --html PAGE``;
* DIR/view_ycb.png: the YCB banana (``ycb:011_banana``, its model from the model cache)
  touched by four fingertips of 8 mm (sim.fingertip.approach, sensor noise 0.5 mm and 1°, the
  object at the paper's pose), localized with ``--finger-radius``.

The pages are made by the command line, as a user makes them, in a temporary folder (each
holds plotly's 4.6 MB bundle). Without a GPU, Chromium draws WebGL with SwiftShader, its
software renderer (CHROMIUM_ARGS).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from contactpose.contacts import Contacts
from contactpose.geometry.sampling import perturb_normals
from contactpose.io import jsonfiles
from contactpose.sim import fingertip, ycb
from contactpose.sim.grasps import paper_pose

#: Debian's Chromium, and its flags: no sandbox (containers), WebGL by SwiftShader, nothing
#: fetched in the background.
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ("--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--no-first-run", "--disable-quic")
#: Browser window of a picture (CSS pixels).
VIEWPORT = {"width": 1200, "height": 800}
#: The YCB picture's grasp: object, fingertip radius (m), sensor noise (m, degrees), seed.
YCB_NAME = "ycb:011_banana"
YCB_FINGER_RADIUS = 0.008
YCB_NOISE = (0.0005, 1.0)
YCB_SEED = 6
EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "banana_contacts.json"


@contextmanager
def chromium(executable=CHROMIUM):
    """A headless Chromium (playwright's sync API) for the block; closed after it."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=executable, args=list(CHROMIUM_ARGS))
        try:
            yield browser
        finally:
            browser.close()


def shoot(browser, page_path, png_path=None, timeout_ms=20_000, on_request=None):
    """Open the page ``page_path`` (a file), wait until its graph's WebGL canvas has drawn, take
    a screenshot (saved to ``png_path`` when given); ``on_request`` is called with the URL of
    every request the page makes. -> (the PNG's bytes, [console errors and page errors])"""
    page = browser.new_page(viewport=VIEWPORT)
    errors = []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    if on_request is not None:
        page.on("request", lambda r: on_request(r.url))
    try:
        page.goto(Path(page_path).resolve().as_uri())
        page.wait_for_selector(".js-plotly-plot .gl-container canvas", state="attached", timeout=timeout_ms)
        page.wait_for_function("() => document.querySelector('.js-plotly-plot')._fullLayout !== undefined",
                               timeout=timeout_ms)
        page.evaluate("() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
        return page.screenshot(path=None if png_path is None else str(png_path)), errors
    finally:
        page.close()


def cli_page(model, contacts_path, page_path, *options):
    """``contactpose localize MODEL --contacts C --html PAGE [options]`` in a child process. -> PAGE"""
    subprocess.run([sys.executable, "-m", "contactpose", "localize", model, "--contacts", str(contacts_path),
                    "--html", str(page_path), *options], check=True, stdout=subprocess.DEVNULL)
    return page_path


def ycb_contacts(path):
    """Write CONTACTS.json of the YCB picture's grasp (see the module's notes) to ``path``."""
    rng = np.random.default_rng(YCB_SEED)
    mesh = ycb.load(YCB_NAME)
    touch = fingertip.approach(np.asarray(mesh.vertices), np.asarray(mesh.faces), rng, 4, YCB_FINGER_RADIUS)
    sigma_x, sigma_deg = YCB_NOISE
    pose = paper_pose()
    points = touch.points @ pose[:3, :3].T + pose[:3, 3] + sigma_x * rng.normal(size=touch.points.shape)
    normals = perturb_normals(touch.normals @ pose[:3, :3].T, np.radians(sigma_deg), rng)
    jsonfiles.write_json(path, Contacts(points, object_normals=normals).to_dict())
    return path


def pictures(out_dir="results/demo"):
    """Write out_dir/view_banana.png and out_dir/view_ycb.png. -> [paths]"""
    os.makedirs(out_dir, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        pages = {"banana": cli_page("banana", EXAMPLE, folder / "banana.html"),
                 "ycb": cli_page(YCB_NAME, ycb_contacts(folder / "ycb.json"), folder / "ycb.html",
                                 "--finger-radius", str(YCB_FINGER_RADIUS), "--position-noise", str(YCB_NOISE[0]),
                                 "--normal-noise-deg", str(YCB_NOISE[1]))}
        written = []
        with chromium() as browser:
            for name, page in pages.items():
                png = os.path.join(out_dir, f"view_{name}.png")
                _, errors = shoot(browser, page, png)
                if errors:
                    raise RuntimeError(f"{page}: the browser reported {errors}")
                written.append(png)
    return written


if __name__ == "__main__":
    for picture in pictures(*sys.argv[1:2]):
        print(picture)
