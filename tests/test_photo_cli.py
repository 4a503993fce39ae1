"""Photo decoding and the command line's exact interface and exit codes."""

from __future__ import annotations

import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from vehicle_pose import RegistrationOptions
from vehicle_pose.errors import PhotoError, PhotoTooLargeError
from vehicle_pose.photo import decode_photo, verify_photo

ROOT = Path(__file__).resolve().parents[1]


def _encode(img: Image.Image, fmt: str, **kw) -> bytes:
    buf = io.BytesIO()
    img.save(buf, fmt, **kw)
    return buf.getvalue()


def test_decodes_every_mode():
    rgb = Image.fromarray(np.random.default_rng(0).integers(0, 255, (20, 30, 3), dtype=np.uint8))
    for img, fmt in [(rgb, "PNG"), (rgb.convert("L"), "PNG"), (rgb.convert("RGBA"), "PNG"),
                     (rgb.convert("CMYK"), "JPEG"),
                     (rgb.convert("P"), "PNG"), (Image.fromarray(np.full((20, 30), 40000, np.uint16)), "PNG")]:
        arr = decode_photo(_encode(img, fmt))
        assert arr.shape == (20, 30, 3) and arr.dtype == np.uint8


def test_exif_orientation_is_applied():
    img = Image.new("RGB", (40, 20))
    exif = img.getexif()
    exif[0x0112] = 6
    arr = decode_photo(_encode(img, "JPEG", exif=exif))
    assert arr.shape[:2] == (40, 20)


@pytest.mark.parametrize("data", [b"not an image", _encode(Image.new("RGB", (64, 64)), "JPEG")[:200]])
def test_bad_bytes_are_photo_errors(data):
    with pytest.raises(PhotoError):
        decode_photo(data)


def _photos() -> list[bytes]:
    rng = np.random.default_rng(1)
    rgb = Image.fromarray(rng.integers(0, 255, (120, 200, 3), dtype=np.uint8))
    turned = Image.new("RGB", (40, 20))
    exif = turned.getexif()
    exif[0x0112] = 6
    return [_encode(rgb, "JPEG", quality=90), _encode(rgb, "PNG"), _encode(rgb.convert("CMYK"), "JPEG"),
            _encode(rgb, "WEBP"), _encode(turned, "JPEG", exif=exif), _encode(rgb.convert("L"), "TIFF")]


@pytest.mark.parametrize("index", range(6))
def test_verification_sees_the_size_decoding_gives(index):
    data = _photos()[index]
    assert verify_photo(data) == decode_photo(data).shape[1::-1]


@pytest.mark.parametrize("cut", [0.3, 0.6, 0.9])
def test_verification_refuses_what_decoding_refuses(cut):
    big = Image.fromarray(np.random.default_rng(2).integers(0, 255, (600, 800, 3), dtype=np.uint8))
    for data in (_encode(big, "JPEG", quality=92), _encode(big, "PNG")):
        short = data[: int(len(data) * cut)]
        with pytest.raises(PhotoError):
            decode_photo(short)
        with pytest.raises(PhotoError):
            verify_photo(short)
    with pytest.raises(PhotoTooLargeError):
        verify_photo(_encode(Image.new("L", (5000, 5000)), "PNG"), max_pixels=1_000_000)
    with pytest.raises(PhotoError, match="too small"):
        verify_photo(_encode(Image.new("RGB", (4, 30)), "PNG"))


def test_decompression_bomb_is_refused():
    with pytest.raises(PhotoTooLargeError):
        decode_photo(_encode(Image.new("L", (5000, 5000)), "PNG"), max_pixels=1_000_000)


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vehicle_pose.cli", *args], capture_output=True, text=True, cwd=ROOT)


@pytest.mark.slow
def test_cli_registers_the_shipped_sample(tmp_path):
    out, overlay = tmp_path / "r" / "result.json", tmp_path / "overlay.png"
    proc = _cli("register", "examples/sedan.jpg", "--model", "sedan", "--init-camera", "examples/sedan_init.json",
                "--out", str(out), "--overlay", str(overlay))
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    assert result["model"]["id"] == "sedan" and result["start"]["source"] == "init_camera"
    with Image.open(overlay) as img:
        assert img.size == (800, 600)
    from vehicle_pose import Camera, ModelLibrary

    from conftest import projection_error

    model = ModelLibrary().load("sedan")
    truth = Camera.load(ROOT / "examples" / "sedan_truth.json")
    assert projection_error(model, Camera.from_dict(result["camera"]), truth) < 2.0
    assert result["options"]["edge_weight"] == RegistrationOptions().terms.edge_weight


@pytest.mark.slow
def test_cli_options_reach_the_engine(tmp_path):
    out = tmp_path / "result.json"
    proc = _cli("register", "examples/sedan.jpg", "--model", "sedan", "--init-camera", "examples/sedan_init.json",
                "--bbox", "100,150,700,450", "--edge-weight", "0", "--box-weight", "0.5", "--no-box-refit",
                "--single-level", "--max-evaluations", "40", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    opts = result["options"]
    assert (opts["edge_weight"], opts["box_weight"], opts["fit_start_to_box"]) == (0.0, 0.5, False)
    assert len(result["levels"]) == 1 and result["levels"][0]["objective"] >= result["levels"][0]["loss"]


@pytest.mark.parametrize(
    "args,message",
    [
        (["register", "pyproject.toml", "--model", "sedan", "--out", "x.json"], "not a readable image"),
        (["register", "missing.jpg", "--model", "sedan", "--out", "x.json"], "cannot read photo"),
        (["register", "examples/sedan.jpg", "--model", "no-such-car", "--out", "x.json"], "unknown model"),
        (["register", "examples/sedan.jpg", "--model", "sedan", "--out", "x.json", "--init-camera", "pyproject.toml"],
         "not valid JSON"),
        (["register", "examples/sedan.jpg", "--model", "sedan", "--out", "x.json", "--bbox", "1,2"], "bbox"),
        (["register", "examples/sedan.jpg", "--out", "x.json"], "--model"),
    ],
)
def test_cli_bad_input_exits_2_with_one_line(args, message):
    proc = _cli(*args)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0]


def test_cli_empty_mesh_and_bad_camera_json(tmp_path):
    empty = tmp_path / "empty.obj"
    empty.write_text("v 0 0 0\n")
    proc = _cli("register", "examples/sedan.jpg", "--model", str(empty), "--out", str(tmp_path / "r.json"))
    assert proc.returncode == 2 and "no faces" in proc.stderr
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]],
                               "t": [0, 0, 1], "width": 10, "height": 10}))
    proc = _cli("register", "examples/sedan.jpg", "--model", "sedan", "--init-camera", str(cam), "--out",
                str(tmp_path / "r.json"))
    assert proc.returncode == 2 and "rotation" in proc.stderr


@pytest.mark.parametrize("up,forward", [("+z", "-y"), ("-y", "+x"), ("-Z", "-X")])
def test_cli_takes_signed_axes_as_documented(up, forward):
    from vehicle_pose.cli import build_parser, join_signed_axes

    argv = ["register", "p.jpg", "--model", "m.obj", "--out", "r.json", "--up", up, "--forward", forward]
    args = build_parser().parse_args(join_signed_axes(argv))
    assert (args.up, args.forward) == (up, forward)


def test_cli_documented_axis_form_reaches_the_mesh_loader(tmp_path):
    # The README's form, negative axes and all; up and forward along one line are refused
    # by the loader, not by the argument parser.
    mesh = tmp_path / "tri.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    proc = _cli("register", "examples/sedan.jpg", "--model", str(mesh), "--out", str(tmp_path / "r.json"),
                "--up", "-y", "--forward", "-y")
    assert proc.returncode == 2 and "expected one argument" not in proc.stderr
    assert "axis" in proc.stderr or "axes" in proc.stderr


def test_cli_lists_models():
    proc = _cli("models")
    assert proc.returncode == 0 and "sedan" in proc.stdout
