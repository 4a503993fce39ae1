"""The shipped sample: a synthetic photo of a library model, a rough start camera, the truth.

Run ``python -m vehicle_pose.render.sample DIR`` to (re)write it into DIR (default ``examples``).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from vehicle_pose.geometry.camera import Camera, look_at_camera
from vehicle_pose.model.library import ModelLibrary
from vehicle_pose.model.metadata import parse_axis
from vehicle_pose.render.synth import LIGHTINGS, synthesize

__all__ = ["write_sample"]


def write_sample(folder: str | Path, model_id: str = "sedan") -> list[Path]:
    """Write the shipped sample: a synthetic photo, a rough start camera and the true camera."""
    model = ModelLibrary().load(model_id)
    centre, _ = model.mesh.sphere
    truth = look_at_camera(
        centre, parse_axis(model.info.forward), parse_axis(model.info.up),
        azimuth_deg=125.0, elevation_deg=14.0, distance=8.5, focal=1000.0, width=800, height=600,
    )
    rgb, _ = synthesize(model.mesh, truth, lighting=LIGHTINGS["side"], seed=7)
    tilt = Rotation.from_rotvec(np.radians([3.0, -6.0, 2.0])).as_matrix()
    start = Camera(truth.K * np.array([[0.9, 1, 1], [1, 0.9, 1], [1, 1, 1]]), tilt @ truth.R,
                   truth.t * [1.02, 0.97, 1.04], 800, 600)
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{model_id}.jpg", out / f"{model_id}_init.json", out / f"{model_id}_truth.json"]
    cv2.imwrite(str(paths[0]), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 92])
    paths[1].write_text(json.dumps(start.to_dict(), indent=2) + "\n")
    paths[2].write_text(json.dumps(truth.to_dict(), indent=2) + "\n")
    return paths


if __name__ == "__main__":
    for written in write_sample(sys.argv[1] if len(sys.argv) > 1 else "examples"):
        print(written)
