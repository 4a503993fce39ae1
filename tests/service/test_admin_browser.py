"""The admin page in a real headless Chromium (Debian's), driven by Playwright."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from PIL import ExifTags, Image
from playwright.sync_api import sync_playwright

from vehicle_pose.model.parts import COLOURS
from vehicle_pose.render.synth import LIGHTINGS, synthesize

from helpers import perturbed, view
from service_stack import encode, wait_for

pytestmark = pytest.mark.slow


CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"


# Without these, Chromium tries Google's services at start; this machine's network refuses them.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).exists():
        pytest.fail("chromium is not installed; scripts/setup.sh installs Debian's chromium")
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        yield b
        b.close()


def test_admin_page_lists_and_opens_a_finished_job(service, browser, sedan, renderer, tmp_path):
    truth = view(sedan, 140.0, 20.0, focal=900.0)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["front"], renderer=renderer, seed=21)
    exif = Image.Exif()
    exif[0x0112] = 1  # Pillow writes a PNG's EXIF only when its first IFD holds a tag
    exif.get_ifd(ExifTags.IFD.Exif)[0xA405] = 49  # 900 pixels of an 800-pixel diagonal, 35 mm equivalent
    with service.client() as c:
        r = c.post(
            "/v1/registrations",
            data={"model_id": "sedan", "init_camera": json.dumps(perturbed(truth, 21).to_dict())},
            files={"photo": ("car.png", encode(photo, exif=exif), "image/png")},
        )
        job_id = r.json()["id"]
        assert wait_for(c, job_id)["status"] == "succeeded"

    refused = browser.new_context(http_credentials={"username": "claims-app", "password": service.keys["default"]})
    assert refused.new_page().goto(f"{service.url}/admin").status == 403
    refused.close()

    context = browser.new_context(
        http_credentials={"username": "admin", "password": service.keys["admin"]},
        viewport={"width": 1280, "height": 900}
    )
    page = context.new_page()
    assert page.goto(f"{service.url}/admin").status == 200
    row = page.locator(f'tr[data-id="{job_id}"]')
    row.wait_for()
    assert "succeeded" in row.inner_text() and "sedan" in row.inner_text()
    thumb = row.locator("img")
    thumb.wait_for()
    assert page.evaluate("img => img.complete && img.naturalWidth > 0", thumb.element_handle())
    page.screenshot(path=str(tmp_path / "admin-list.png"), full_page=True)

    page.select_option("#filter-status", "failed")
    page.click("button[type=submit]")
    page.wait_for_url("**/admin?status=failed*")
    assert page.locator(f'tr[data-id="{job_id}"]').count() == 0
    page.select_option("#filter-status", "succeeded")
    page.click("button[type=submit]")
    page.locator(f'tr[data-id="{job_id}"]').wait_for()

    page.click(f'tr[data-id="{job_id}"] a.id')
    page.wait_for_url(f"**/admin/registrations/{job_id}")
    overlay = page.locator("#overlay")
    overlay.wait_for()
    assert page.evaluate("img => img.complete && img.naturalWidth === 640", overlay.element_handle())
    table = page.locator("#parts")
    table.wait_for()
    rows = table.locator("tbody tr")
    assert rows.count() >= 5
    # the swatch is an SVG fill: the admin page's CSP allows no inline style
    first = json.loads(page.locator("#pose").inner_text())["parts"][0]
    swatch = rows.first.locator(".swatch rect")
    assert rows.first.locator("td").nth(1).inner_text() == first["part"].replace("_", " ")
    assert page.evaluate("e => getComputedStyle(e).fill", swatch.element_handle()) == "rgb({}, {}, {})".format(
        *COLOURS[first["part"]])
    pose = json.loads(page.locator("#pose").inner_text())
    assert len(pose["cam_K"]) == 9 and pose["model"]["id"] == "sedan"
    # The client's start camera wins over the photo's EXIF focal length, which the page shows.
    assert pose["focal"]["source"] == "searched"
    assert "searched" in page.locator("#focal").inner_text() and "49 mm" in page.locator("#focal").inner_text()
    page.screenshot(path=str(tmp_path / "admin-detail.png"), full_page=True)
    context.close()
    for name in ("admin-list.png", "admin-detail.png"):
        assert (tmp_path / name).stat().st_size > 10_000
    print(f"admin page screenshots: {tmp_path}")
