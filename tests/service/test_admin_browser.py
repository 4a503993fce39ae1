"""The admin page in a real headless Chromium (Debian's), driven by Playwright."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pillow_heif
import pytest
from PIL import ExifTags, Image
from playwright.sync_api import sync_playwright

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.parts import COLOURS
from vehicle_pose.render.synth import LIGHTINGS, synthesize

from helpers import perturbed, projection_error, view
from service_stack import encode, submit, wait_for

pytestmark = pytest.mark.slow


pillow_heif.register_heif_opener()  # to write the phone's HEIC below

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


def test_a_phone_s_heic_is_registered_and_shown_upright(service, browser, sedan, renderer):
    # An iPhone's photo: HEIC, stored as the sensor wrote it (a quarter turn from upright) with
    # the turn in the file, and the lens's 35 mm equivalent in its EXIF.
    truth = view(sedan, 60.0, 15.0, width=320, height=240, focal=480.0)
    photo, _ = synthesize(sedan.mesh, truth, lighting=LIGHTINGS["top"], renderer=renderer, seed=23)
    exif = Image.Exif()
    exif[0x0112] = 6  # shown turned a quarter clockwise
    exif.get_ifd(ExifTags.IFD.Exif)[0xA405] = 52  # 480 pixels of a 400-pixel diagonal, 35 mm equivalent
    heic = encode(np.ascontiguousarray(np.rot90(photo, 1)), "HEIF", quality=95, exif=exif.tobytes())
    assert heic[4:12] == b"ftypheic"
    with service.client() as c:
        job = submit(c, heic, start=perturbed(truth, 23, degrees=4.0), filename="IMG_0001.HEIC").json()
        body = wait_for(c, job["id"])
        assert body["status"] == "succeeded", body
        assert (body["photo"]["width"], body["photo"]["height"]) == (320, 240)
        assert projection_error(sedan, Camera.from_dict(body["result"]["camera"]), truth) < 3.0
        assert body["result"]["focal"]["exif"]["equivalent_mm"] == pytest.approx(52.0)
        stored = c.get(body["links"]["photo"])
        assert stored.headers["content-type"] == "image/heic" and stored.content == heic

    context = browser.new_context(http_credentials={"username": "admin", "password": service.keys["admin"]})
    page = context.new_page()
    assert page.goto(f"{service.url}/admin/registrations/{job['id']}").status == 200
    shown = page.locator("#photo")
    shown.wait_for()
    # A browser shows no HEIC: the page shows the photo as a JPEG, upright.
    assert shown.get_attribute("src").endswith("/photo.jpg")
    page.wait_for_function("img => img.complete", arg=shown.element_handle())
    assert page.evaluate("img => [img.naturalWidth, img.naturalHeight]", shown.element_handle()) == [320, 240]
    assert "image/heic" in page.locator("dl.facts").inner_text()
    context.close()
