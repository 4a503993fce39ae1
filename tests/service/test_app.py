"""The API's own checks: uploads sniffed by content, options and hints refused with reasons."""

from __future__ import annotations

import json

import pytest

from app.uploads import sniff_image


@pytest.mark.parametrize(
    "head,media_type",
    [
        (b"\xff\xd8\xff\xe0\x00\x10JFIF", "image/jpeg"),
        (b"\x89PNG\r\n\x1a\n\x00\x00", "image/png"),
        (b"RIFF\x00\x00\x00\x00WEBPVP8 ", "image/webp"),
        (b"II*\x00\x08\x00\x00\x00", "image/tiff"),
        (b"BM\x00\x00", "image/bmp"),
        (b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic", "image/heic"),  # an iPhone's
        (b"\x00\x00\x00\x18ftypmif1\x00\x00\x00\x00mif1heic", "image/heic"),
        (b"\x00\x00\x00\x14ftypmif1\x00\x00\x00\x00mif1", "image/heif"),
        (b"\x00\x00\x00\x20ftypavif\x00\x00\x00\x00avifmif1miafMA1B", "image/avif"),
        (b"\x00\x00\x00\x18ftypmif1\x00\x00\x00\x00mif1avif", "image/avif"),
        (b"\x00\x00\x00\x18ftypisom\x00\x00\x02\x00isomiso2", None),  # an MP4 video
        (b"RIFF\x00\x00\x00\x00WAVEfmt ", None),
        (b"GIF89a", None),
        (b"<html>", None),
        (b"", None),
    ],
)
def test_sniff_image_trusts_content_not_names(head, media_type):
    assert sniff_image(head) == media_type


def test_real_photo_options_reach_the_engine_and_are_bounded():

    from app.schemas import RegistrationOptionsIn
    from vehicle_pose import RegistrationOptions

    kwargs = RegistrationOptionsIn.model_validate_json(
        '{"edge_weight": 0, "box_weight": 2.5, "fit_start_to_box": false}').engine_kwargs()
    assert kwargs == {"edge_weight": 0.0, "box_weight": 2.5, "fit_start_to_box": False}
    terms = RegistrationOptions.from_flat(kwargs).terms
    assert (terms.edge_weight, terms.box_weight, terms.fit_start_to_box) == (0.0, 2.5, False)
    for bad in ('{"edge_weight": -1}', '{"box_weight": 1e9}', '{"fit_start_to_box": "maybe"}'):
        with pytest.raises(ValueError):
            RegistrationOptionsIn.model_validate_json(bad)


@pytest.mark.parametrize(
    ("options", "words"),
    [
        ('{"max_evaluations": 1}', ("max_evaluations", "greater than")),
        ('{"loss": "nope"}', ("loss", "nope")),
        ('{"edge_weight": "heavy"}', ("edge_weight", "number")),
        ('{"max_evaluations": 1, "starts": 0}', ("max_evaluations", "starts")),
    ],
)
def test_invalid_options_name_the_field_and_the_reason(options, words):
    from app.problems import Problem
    from app.registrations import Photo, parse_hints

    photo = Photo(b"", "image/png", 640, 480)
    with pytest.raises(Problem) as info:
        parse_hints(None, None, options, photo)
    assert info.value.slug == "invalid-options"
    detail = info.value.detail
    assert "validation error for" not in detail
    for word in words:
        assert word in detail, detail


def test_a_start_camera_of_another_aspect_ratio_is_a_422():
    from app.problems import Problem
    from app.registrations import Photo, parse_hints

    cam = {"K": [[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1]], "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
           "t": [0, 0, 10], "width": 640, "height": 480}
    assert parse_hints(json.dumps(cam), None, None, Photo(b"", "image/png", 320, 240))[0]["width"] == 640
    with pytest.raises(Problem) as info:
        parse_hints(json.dumps(cam), None, None, Photo(b"", "image/png", 480, 640))
    assert info.value.slug == "invalid-camera" and "aspect ratio" in info.value.detail
