"""End to end: the real studio page in headless Chromium (Debian's, driven by Playwright), as a user
would use it. Screenshots land in artifacts/e2e/ (look at them: they are the review of the page)."""

import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from ..conftest import REPO, SAMPLES, free_port

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
ARTIFACTS = Path(os.environ.get("APOSE_ARTIFACTS", REPO / "artifacts")) / "e2e"


@pytest.fixture(scope="module")
def browser():
    if not CHROMIUM.is_file():
        reason = "Debian's chromium is not installed (bash scripts/setup.sh installs it: apt-get install chromium)"
        if os.environ.get("CI"):
            pytest.fail(reason)
        pytest.skip(reason)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        yield b
        b.close()


@pytest.fixture
def studio():
    from apose_studio.studio import serve

    server, st = serve(host="127.0.0.1", port=free_port())
    yield st
    server.stop()


def expect(locator):
    from playwright.sync_api import expect as pw_expect

    return pw_expect(locator)


def field(page, label: str):
    """The input(s) in the GUI row labelled `label` (viser puts the label beside them)."""
    row = page.locator("div").filter(has=page.get_by_text(label, exact=True)).filter(has=page.locator("input"))
    return row.last.locator("input:not([type=hidden])")


def type_into(page, label: str, text: str, index: int = 0) -> None:
    box = field(page, label).nth(index)
    box.fill(text)
    box.press("Enter")


def wait_until(cond, what, timeout: float = 60.0) -> None:
    t0 = time.time()
    while time.time() - t0 < timeout:
        if cond():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what() if callable(what) else what}")


def open_page(browser, st):
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    page.goto(f"http://127.0.0.1:{st.server.get_port()}")
    page.get_by_role("button", name="Add part(s)").wait_for(timeout=30000)
    return page


def test_author_a_step_and_save(browser, studio, tmp_path):
    asm_path = tmp_path / "gearbox" / "assembly.yaml"
    shutil.copytree(SAMPLES / "helical_gearbox", asm_path.parent)
    trimesh.creation.cylinder(radius=4.0, height=20.0).export(tmp_path / "dowel_pin.stl")  # mm, like the sample
    page = open_page(browser, studio)

    type_into(page, "Assembly file", str(asm_path))
    page.get_by_role("button", name="Open").click()
    page.get_by_text("Valid", exact=False).first.wait_for(timeout=30000)
    wait_until(lambda: len(studio.asm.steps) == 3, "the sample to open")

    type_into(page, "Mesh path or folder", str(tmp_path / "dowel_pin.stl"))
    page.get_by_role("button", name="Add part(s)").click()
    wait_until(lambda: "dowel_pin" in studio.asm.parts, "the part to be added")
    page.get_by_role("cell", name="dowel_pin").first.wait_for(timeout=10000)

    page.get_by_role("button", name="Add", exact=True).click()
    wait_until(lambda: len(studio.asm.steps) == 4, "the step to be added")
    # the page shows the new step (its pose fields were reset to identity) before we type into them
    expect(field(page, "Step").first).to_have_value("4. dowel_pin", timeout=10000)
    expect(field(page, "Translation (mm)").nth(2)).to_have_value("0", timeout=10000)
    for i, v in enumerate(("12.5", "-7", "30")):
        type_into(page, "Translation (mm)", v, i)
    type_into(page, "Rotation xyz (°)", "90", 0)
    wait_until(lambda: np.allclose(studio.asm.steps[3].T_base_part[:3, 3], [0.0125, -0.007, 0.030], atol=1e-9)
               and abs(studio.asm.steps[3].T_base_part[1, 2] + 1.0) < 1e-9,
               lambda: f"the typed pose to arrive (have {studio.asm.steps[3].T_base_part.round(4).tolist()})")
    page.get_by_role("button", name="Save").click()
    wait_until(lambda: "dowel_pin" in asm_path.read_text(), "the file to be saved")
    on_disk = yaml.safe_load(asm_path.read_text())
    step = on_disk["steps"][3]
    assert step["part"] == "dowel_pin" and step["base"][0] == "casing"
    assert step["pose_in_base"]["translation"] == [12.5, -7, 30]
    w, x, _, _ = step["pose_in_base"]["rotation"]["quat_wxyz"]
    assert abs(w - 0.7071068) < 1e-6 and abs(x - 0.7071068) < 1e-6
    page.get_by_text("Saved as").first.wait_for(timeout=10000)
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "assembly_tab.png"))
    # a second tab sees the same draft, and the server still serves after a broken file
    other = open_page(browser, studio)
    type_into(other, "Assembly file", str(tmp_path / "missing.yaml"))
    other.get_by_role("button", name="Open").click()
    other.get_by_text("file not found", exact=False).first.wait_for(timeout=10000)
    assert len(studio.asm.steps) == 4
    other.close()
    page.close()


def test_inspect_estimate_a_frame(browser, studio, gearbox_dataset):
    page = open_page(browser, studio)
    page.get_by_role("tab", name="Inspect").click()
    type_into(page, "Dataset or capture", str(gearbox_dataset))
    page.get_by_role("button", name="Open data").click()
    wait_until(lambda: "/inspect/scene" in studio.nodes, "the frame to be shown")
    field(page, "Orientation prior").first.check()
    wait_until(lambda: studio.i_prior.value, "the prior checkbox")
    page.get_by_role("button", name="Estimate frame").click()
    wait_until(lambda: "/inspect/box_est" in studio.nodes and "final" in studio.i_stage_md.content, "the estimate", timeout=120)
    for name in ("/inspect/box_est", "/inspect/box_gt", "/inspect/target", "/inspect/source", "/inspect/camera"):
        assert name in studio.nodes, name
    assert studio.result.ok and studio.score.mssd < 0.002
    page.get_by_text("MSSD", exact=True).first.wait_for(timeout=10000)
    page.get_by_text("final", exact=True).first.wait_for(timeout=10000)
    time.sleep(1.0)  # let the software renderer draw the clouds
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "inspect_tab.png"))
    page.close()
