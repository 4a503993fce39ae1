"""Real photos: what the wheel detector finds (the seed paper's start cue, and a candidate term).

Usage: .venv/bin/python bench/real_wheels.py [--shared ../shared/real]

For each case of ``../shared/real`` the detector (``vehicle_pose.search.wheels.detect_wheels``)
looks for wheel ellipses in the case's box, as the no-hint search does; the real photos carry
no wheel annotation, so the contact sheet ``bench/results/real_wheels.png`` (the two best
ellipses red, the others yellow) is there to be looked at, and ``real_wheels.json`` lists the
ellipses per case.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from vehicle_pose.photo import load_photo
from vehicle_pose.search.wheels import detect_wheels
from vehicle_pose.segment.region import VehicleRegion

from common import RESULTS, write_report

TILE = 360


def _tile(photo: np.ndarray, ellipses: list, label: str) -> np.ndarray:
    img = cv2.cvtColor(photo, cv2.COLOR_RGB2BGR)
    for k, e in enumerate(ellipses):
        colour = (0, 0, 255) if k < 2 else (0, 255, 255)
        cv2.ellipse(img, (round(e.centre[0]), round(e.centre[1])), (round(e.a), round(e.b)),
                    float(np.degrees(e.angle)), 0.0, 360.0, colour, 2)
    scale = TILE / img.shape[1]
    img = cv2.resize(img, (TILE, round(img.shape[0] * scale)), interpolation=cv2.INTER_AREA)
    cv2.putText(img, label, (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 255, 0), 1)
    return img


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shared", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "real")
    args = ap.parse_args()
    tiles, found = [], {}
    for case in sorted((args.shared / "cases").iterdir()):
        photo = load_photo(case / "photo.jpg")
        H, W = photo.shape[:2]
        x0, y0, x1, y1 = (round(v) for v in json.loads((case / "init.json").read_text())["bbox"])
        box = np.zeros((H, W), bool)
        box[max(0, y0) : y1, max(0, x0) : x1] = True
        ellipses = detect_wheels(photo, VehicleRegion.from_mask(box), max_count=4)
        found[case.name] = [e.to_dict() for e in ellipses]
        tiles.append(_tile(photo, ellipses, f"{case.name} {len(ellipses)}"))
        print(f"{case.name} {W}x{H}: {len(ellipses)} ellipses", flush=True)
    height = max(t.shape[0] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, height - t.shape[0], 0, 0, cv2.BORDER_CONSTANT) for t in tiles]
    if len(tiles) % 2:
        tiles.append(np.zeros_like(tiles[0]))
    sheet = np.vstack([np.hstack(tiles[i : i + 2]) for i in range(0, len(tiles), 2)])
    RESULTS.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(RESULTS / "real_wheels.png"), sheet)
    print(write_report("real_wheels", {"ellipses": found}))
    print(RESULTS / "real_wheels.png")


if __name__ == "__main__":
    main()
