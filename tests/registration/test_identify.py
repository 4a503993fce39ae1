"""Model identification: which body type is in the photo."""

from __future__ import annotations

import json

import pytest

from vehicle_pose import RegistrationOptions
from vehicle_pose.cli import main
from vehicle_pose.geometry.camera import Camera
from vehicle_pose.registration.identify import identify
from vehicle_pose.render.overlay import save_png
from vehicle_pose.render.synth import LIGHTINGS, synthesize

from helpers import projection_error, view


@pytest.mark.slow
def test_identification_picks_the_right_body_type(library, renderer):
    candidates = [library.load(m) for m in ("sedan", "van", "pickup")]
    options = RegistrationOptions.from_flat(starts=3, refine=1, max_size=320, screen_size=160)
    for model, azimuth in zip(candidates, (60.0, 230.0, 120.0), strict=True):
        truth = view(model, azimuth, 12.0, focal=500.0, distance=11.0, width=320, height=240)
        photo, _ = synthesize(model.mesh, truth, lighting=LIGHTINGS["front"], renderer=renderer, seed=9)
        ranking = identify(photo, candidates, options=options, renderer=renderer)
        assert ranking[0].model is model, [(c.model.info.id, c.score) for c in ranking]
        assert ranking[0].score < ranking[1].score


@pytest.mark.slow
def test_cli_identifies_without_a_hint(library, renderer, tmp_path, capsys):
    van = library.load("van")
    truth = view(van, 60.0, 10.0, focal=500.0, distance=11.0, width=320, height=240)
    photo, _ = synthesize(van.mesh, truth, renderer=renderer, seed=10)
    save_png(tmp_path / "photo.png", photo)
    out = tmp_path / "result.json"
    code = main(["register", str(tmp_path / "photo.png"), "--model", "sedan,van", "--out", str(out),
                 "--overlay", str(tmp_path / "overlay.png"), "--starts", "3", "--refine", "1"])
    assert code == 0, capsys.readouterr().err
    data = json.loads(out.read_text())
    assert data["model"]["id"] == "van" and [c["model"] for c in data["identification"]] == ["van", "sedan"]
    assert data["start"]["source"] == "none" and data["failed"] is False and data["confidence"] >= 0.5
    assert projection_error(van, Camera.from_dict(data["camera"]), truth) < 2.0
    assert (tmp_path / "overlay.png").stat().st_size > 0
    assert main(["register", str(tmp_path / "photo.png"), "--model", "sedan,bus", "--out", str(out)]) == 2
    assert "bus" in capsys.readouterr().err
