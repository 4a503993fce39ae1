"""Write the sample photo ``examples/sedan.jpg``: the shipped sedan rendered by the project's own
synthesizer at ``examples/sedan_truth.json`` (side lighting, a smooth random background, seed 7).

Run it again whenever the shipped models are generated anew (``python -m
vehicle_pose.model.procedural vehicle_models``), so that the sample is a photo of the model the
README's command registers: ``.venv/bin/python examples/make_sample.py``.
"""

from __future__ import annotations

from pathlib import Path

from PIL import Image

from vehicle_pose import Camera, ModelLibrary
from vehicle_pose.render.synth import LIGHTINGS, synthesize

HERE = Path(__file__).resolve().parent


def main() -> None:
    model = ModelLibrary().load("sedan")
    truth = Camera.load(HERE / "sedan_truth.json")
    photo, _ = synthesize(model.mesh, truth, lighting=LIGHTINGS["side"], seed=7)
    Image.fromarray(photo).save(HERE / "sedan.jpg", quality=95)
    print(f"wrote {HERE / 'sedan.jpg'}")


if __name__ == "__main__":
    main()
