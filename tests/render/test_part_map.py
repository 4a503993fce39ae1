"""The part map: labels where the model is, the parts' figures, the PNG, a registration's map."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from PIL import Image

from vehicle_pose import register
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.model.parts import VOCABULARY, model_frame
from vehicle_pose.render.parts import part_map
from vehicle_pose.render.synth import synthesize

from helpers import perturbed, view


def _shoelace(poly: list[list[float]]) -> float:
    p = np.asarray(poly)
    return 0.5 * abs(float(np.dot(p[:, 0], np.roll(p[:, 1], 1)) - np.dot(p[:, 1], np.roll(p[:, 0], 1))))


def test_the_map_covers_the_model_and_names_the_side_seen(sedan, renderer):
    cam = view(sedan, 60.0, 15.0)
    parts = part_map(sedan, cam, renderer)
    assert np.array_equal(parts.image() > 0, renderer.render(sedan.mesh, cam).coverage)
    centre = -cam.R.T @ cam.t
    seen = "left" if model_frame(sedan.info.up, sedan.wheels).local(centre[None])[0, 1] > 0 else "right"
    hidden = "right" if seen == "left" else "left"
    names = [p.part for p in parts.parts]
    assert f"front_door_{seen}" in names and f"wheel_front_{seen}" in names
    assert sum(p.pixels for p in parts.parts if p.part.endswith(hidden)) < 0.02 * sum(p.pixels for p in parts.parts)
    assert sum(p.pixels for p in parts.parts) == int((parts.image() > 0).sum())
    for p in parts.parts:
        assert 0.0 < p.visible_share <= 1.0 and 0.0 <= p.incidence_deg <= 90.0
        assert not p.estimated  # wheels and lamps named, the body and glass labelled by construction
        area = sum(_shoelace(poly) for poly in p.polygons)
        if p.pixels > 2000:
            assert abs(area - p.pixels) < 0.1 * p.pixels, (p.part, area, p.pixels)


def test_a_part_faced_squarely_has_a_small_angle_and_a_grazing_one_a_large_one(sedan, renderer):
    """From straight above, the roof faces the camera and the doors are seen edge-on."""
    top = view(sedan, 90.0, 89.0, distance=12.0)
    parts = {p.part: p for p in part_map(sedan, top, renderer).parts}
    assert parts["roof"].incidence_deg < 25.0
    doors = [p for name, p in parts.items() if "door" in name and "window" not in name]
    mean = sum(p.incidence_deg * p.pixels for p in doors) / sum(p.pixels for p in doors)
    assert mean > parts["roof"].incidence_deg + 20.0


def test_the_png_is_indexed_with_the_parts_colours_and_legend(sedan, renderer):
    cam = view(sedan, 200.0, 10.0, width=320, height=240, focal=450.0)
    parts = part_map(sedan, cam, renderer)
    img = Image.open(io.BytesIO(parts.png()))
    assert img.mode == "P" and img.size == (320, 240)
    legend = json.loads(img.info["legend"])
    assert legend == {part: k + 1 for k, part in enumerate(VOCABULARY)}
    assert np.array_equal(np.asarray(img), parts.image())
    pal = img.getpalette()
    assert pal is not None and pal[:3] == [0, 0, 0]


def test_a_large_photo_is_mapped_reduced_and_answered_in_its_own_pixels(sedan, renderer):
    cam = view(sedan, 60.0, 15.0, width=3200, height=2400, focal=4500.0)
    parts = part_map(sedan, cam, renderer, max_size=800)
    assert parts.labels.shape == (600, 800) and parts.image().shape == (2400, 3200)
    biggest = parts.parts[0]
    xy = np.concatenate([np.asarray(poly) for poly in biggest.polygons])
    assert xy[:, 0].max() > 800 and xy[:, 1].max() > 600  # photo pixels, not the map's
    assert abs(biggest.pixels - 16 * int((parts.labels == biggest.label).sum())) <= 16


def test_a_model_off_screen_has_no_parts(sedan, renderer):
    cam = view(sedan, 60.0, 15.0)
    away = Camera(cam.K, cam.R, cam.t + np.array([500.0, 0.0, 0.0]), cam.width, cam.height)
    parts = part_map(sedan, away, renderer)
    assert parts.parts == [] and not parts.image().any()


@pytest.mark.slow
def test_a_registration_maps_the_parts_as_the_true_pose_does(sedan, renderer):
    """The registered pose from a rough start labels at least 97 % of the car's pixels (by
    the true pose's map) with the same part."""
    truth = view(sedan, 130.0, 12.0)
    photo, _ = synthesize(sedan.mesh, truth, renderer=renderer)
    result = register(photo, sedan, init_camera=perturbed(truth, 5), renderer=renderer)
    assert result.parts is not None
    true_map = part_map(sedan, truth, renderer).image()
    found = result.parts.image()
    car = true_map > 0
    assert (found[car] == true_map[car]).mean() >= 0.97
    assert result.timings["parts"] < 1.0
    listed = result.to_dict()["parts"]
    assert [p["part"] for p in listed] == [p.part for p in result.parts.parts]
