"""The command line: the shipped sample, options, bad input, signed axes, preparing models, lazy imports."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from vehicle_pose import RegistrationOptions
from vehicle_pose.model.library import ModelLibrary

SEDAN = ModelLibrary().info("sedan").mesh_path


def test_the_cli_prepares_once_with_progress_and_reads_back(tmp_path):
    env = {"VEHICLE_POSE_CACHE_DIR": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"}
    mesh = tmp_path / "sedan.glb"
    shutil.copyfile(SEDAN, mesh)
    cmd = [sys.executable, "-m", "vehicle_pose.cli", "prepare", str(mesh)]
    first = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert first.returncode == 0, first.stderr
    assert "preparing sedan" in first.stderr and "level 4096" in first.stderr
    second = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert second.returncode == 0 and "preparing" not in second.stderr
    assert (tmp_path / "cache" / "prepared").is_dir()


@pytest.mark.parametrize("args", [["--help"], ["models"]])
def test_help_and_models_do_not_import_the_engine(args):
    code = (
        "import sys\nfrom vehicle_pose.cli import main\n"
        "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
        "heavy = [m for m in ('trimesh', 'moderngl', 'scipy', 'cv2', 'numba', 'cma') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
    )
    done = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr


ROOT = Path(__file__).resolve().parents[1]


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "vehicle_pose.cli", *args], capture_output=True, text=True, cwd=ROOT)


@pytest.mark.slow
def test_cli_registers_the_shipped_sample(tmp_path):
    out, overlay, parts = tmp_path / "r" / "result.json", tmp_path / "overlay.png", tmp_path / "p" / "parts.png"
    proc = _cli("register", "examples/sedan.jpg", "--model", "sedan", "--init-camera", "examples/sedan_init.json",
                "--out", str(out), "--overlay", str(overlay), "--parts", str(parts))
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    assert result["model"]["id"] == "sedan" and result["start"]["source"] == "init_camera"
    with Image.open(overlay) as img:
        assert img.size == (800, 600)
    with Image.open(parts) as img:
        assert img.size == (800, 600) and img.mode == "P"
        legend = json.loads(img.info["legend"])
        counts = np.bincount(np.asarray(img).ravel(), minlength=len(legend) + 1)
    listed = {p["part"]: p["pixels"] for p in result["parts"]}
    assert listed and all(counts[legend[part]] == pixels for part, pixels in listed.items())
    from vehicle_pose import Camera, ModelLibrary

    from helpers import projection_error

    model = ModelLibrary().load("sedan")
    truth = Camera.load(ROOT / "examples" / "sedan_truth.json")
    assert projection_error(model, Camera.from_dict(result["camera"]), truth) < 2.0
    assert result["options"]["edge_weight"] == RegistrationOptions().terms.edge_weight


@pytest.mark.slow
def test_cli_options_reach_the_engine(tmp_path):
    out = tmp_path / "result.json"
    proc = _cli("register", "examples/sedan.jpg", "--model", "sedan", "--init-camera", "examples/sedan_init.json",
                "--bbox", "100,150,700,450", "--edge-weight", "0", "--box-weight", "0.5", "--no-box-refit",
                "--single-level", "--max-evaluations", "40", "--no-exif-focal", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    result = json.loads(out.read_text())
    opts = result["options"]
    assert (opts["edge_weight"], opts["box_weight"], opts["fit_start_to_box"]) == (0.0, 0.5, False)
    assert opts["exif_focal"] is False
    assert len(result["levels"]) == 1 and result["levels"][0]["objective"] >= result["levels"][0]["loss"]


def test_cli_reads_the_exif_focal_length_and_warns_of_one_that_cannot_be(tmp_path):
    import pillow_heif
    from PIL import ExifTags

    pillow_heif.register_heif_opener()  # to write a phone's HEIC
    with Image.open(ROOT / "examples" / "sedan.jpg") as img:
        pixels = img.copy()
    for equivalent, warned, fmt in ((1000, True, "JPEG"), (40, False, "JPEG"), (40, False, "HEIF")):
        exif = Image.Exif()
        exif[0x0112] = 1
        exif.get_ifd(ExifTags.IFD.Exif)[0xA405] = equivalent
        photo, out = tmp_path / f"lens{equivalent}.{fmt.lower()}", tmp_path / f"r{equivalent}{fmt}.json"
        pixels.save(photo, fmt, quality=95, exif=exif.tobytes())
        proc = _cli("register", str(photo), "--model", "sedan", "--init-camera", "examples/sedan_init.json",
                    "--single-level", "--max-evaluations", "40", "--out", str(out))
        assert proc.returncode == 0, proc.stderr
        result = json.loads(out.read_text())
        assert result["focal"]["source"] == "searched"  # the start camera's focal length wins
        assert result["focal"]["exif"]["equivalent_mm"] == equivalent
        assert bool(result["warnings"]) == warned and ("warning: the EXIF focal length" in proc.stderr) == warned
        if not warned:
            assert result["focal"]["exif"]["pixels"] == pytest.approx(40 / 43.2666 * 1000, rel=1e-3)


@pytest.mark.slow
def test_cli_without_a_start_camera_holds_the_exif_focal_length_and_says_so(tmp_path):
    from PIL import ExifTags

    with Image.open(ROOT / "examples" / "sedan.jpg") as img:
        pixels = img.copy()
    exif = Image.Exif()
    exif.get_ifd(ExifTags.IFD.Exif)[0xA405] = 40
    photo, out = tmp_path / "phone.jpg", tmp_path / "r.json"
    pixels.save(photo, "JPEG", quality=95, exif=exif.tobytes())
    proc = _cli("register", str(photo), "--model", "sedan", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    focal = json.loads(out.read_text())["focal"]
    assert focal["source"] == "exif"
    said = f"focal length {focal['pixels']:.0f} px (the EXIF's {focal['exif']['pixels']:.0f} px)"
    assert said in proc.stdout, proc.stdout


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
