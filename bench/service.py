"""Service throughput and latency with 1, 2 and 4 worker processes on this machine.

Starts the whole embedded service (``vehicle-pose-service run``: Redis, Celery workers, uvicorn)
once per worker count, submits a burst of registrations of synthetic 640x480 photos with rough
start cameras, and meanwhile polls job status from several threads. Reports jobs per minute,
p50/p95 time to result (submission to finished, queueing included), the API's p50/p95 latency
for status polls under that load, and the success rate (error <= 5 px).

    .venv/bin/python bench/service.py [--workers 1 2 4] [--jobs 12] [--pollers 4]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from datetime import datetime
from pathlib import Path

import numpy as np

from common import perturbed, projection_error, table, write_report

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "service"))
from vehicle_pose.geometry.camera import Camera, look_at_camera  # noqa: E402
from vehicle_pose.model.library import ModelLibrary  # noqa: E402
from vehicle_pose.model.metadata import parse_axis  # noqa: E402
from vehicle_pose.render.synth import LIGHTINGS, synthesize  # noqa: E402

from service_stack import encode, start_stack  # noqa: E402  (the tests' launcher of the real service)


def make_cases(n: int, seed: int = 0) -> list[tuple[bytes, Camera, Camera]]:
    model = ModelLibrary().load("sedan")
    centre, _ = model.mesh.sphere
    rng = np.random.default_rng(seed)
    cases = []
    for i in range(n):
        truth = look_at_camera(
            centre, parse_axis(model.info.forward), parse_axis(model.info.up),
            azimuth_deg=float(rng.uniform(0, 360)), elevation_deg=float(rng.uniform(8, 25)),
            distance=9.0, focal=float(rng.uniform(800, 1100)), width=640, height=480,
        )
        photo, _ = synthesize(model.mesh, truth, lighting=list(LIGHTINGS.values())[i % len(LIGHTINGS)], seed=i)
        cases.append((encode(photo), truth, perturbed(truth, rng, 5.0)))
    return cases


def _seconds(a: str, b: str) -> float:
    return (datetime.fromisoformat(b) - datetime.fromisoformat(a)).total_seconds()


def run(workers: int, cases: list[tuple[bytes, Camera, Camera]], pollers: int, points: np.ndarray) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        stack = start_stack(Path(tmp), workers=workers)
        try:
            with stack.client() as c:
                warm = c.post("/v1/registrations",
                              data={"model_id": "sedan", "init_camera": json.dumps(cases[0][2].to_dict())},
                              files={"photo": ("w.png", cases[0][0], "image/png")}).json()["id"]
                _wait(c, [warm])
                t0 = time.monotonic()
                ids = []
                for photo, _, start in cases:
                    r = c.post("/v1/registrations",
                               data={"model_id": "sedan", "init_camera": json.dumps(start.to_dict())},
                               files={"photo": ("car.png", photo, "image/png")})
                    r.raise_for_status()
                    ids.append(r.json()["id"])
                latencies: list[float] = []
                stop = threading.Event()
                threads = [threading.Thread(target=_poll, args=(stack, ids, stop, latencies)) for _ in range(pollers)]
                for t in threads:
                    t.start()
                bodies = _wait(c, ids)
                wall = time.monotonic() - t0
                stop.set()
                for t in threads:
                    t.join()
        finally:
            stack.stop()
    to_result = [_seconds(b["created_at"], b["finished_at"]) for b in bodies]
    errors = [
        projection_error(points, Camera.from_dict(b["result"]["camera"]),
                         truth) if b["status"] == "succeeded" else np.inf
        for b, (_, truth, _) in zip(bodies, cases, strict=True)
    ]
    lat = np.array(latencies) * 1000.0
    return {
        "workers": workers,
        "jobs": len(ids),
        "jobs_per_min": 60.0 * len(ids) / wall,
        "p50_result_s": float(np.percentile(to_result, 50)),
        "p95_result_s": float(np.percentile(to_result, 95)),
        "status_polls": int(lat.size),
        "poll_p50_ms": float(np.percentile(lat, 50)),
        "poll_p95_ms": float(np.percentile(lat, 95)),
        "success": float(np.mean(np.array(errors) <= 5.0)),
    }


def _poll(stack, ids: list[str], stop: threading.Event, out: list[float]) -> None:
    rng = np.random.default_rng(threading.get_ident() % 2**32)
    with stack.client() as c:
        while not stop.is_set():
            t = time.perf_counter()
            c.get(f"/v1/registrations/{ids[int(rng.integers(len(ids)))]}").raise_for_status()
            out.append(time.perf_counter() - t)
            time.sleep(0.02)


def _wait(client, ids: list[str], timeout: float = 900.0) -> list[dict]:
    deadline = time.monotonic() + timeout
    done: dict[str, dict] = {}
    while len(done) < len(ids):
        if time.monotonic() > deadline:
            raise RuntimeError(f"{len(ids) - len(done)} jobs unfinished after {timeout} s")
        for job_id in ids:
            if job_id not in done:
                body = client.get(f"/v1/registrations/{job_id}").json()
                if body["status"] in ("succeeded", "failed"):
                    done[job_id] = body
        time.sleep(0.25)
    return [done[i] for i in ids]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    p.add_argument("--jobs", type=int, default=12)
    p.add_argument("--pollers", type=int, default=4, help="threads polling job status meanwhile (~50 req/s each)")
    args = p.parse_args()
    cases = make_cases(args.jobs)
    points = ModelLibrary().load("sedan").mesh.sample_points(3000)
    rows = [run(w, cases, args.pollers, points) for w in args.workers]
    columns = ["workers", "jobs", "jobs_per_min", "p50_result_s", "p95_result_s", "status_polls", "poll_p50_ms",
               "poll_p95_ms", "success"]
    print(table(rows, columns))
    print(f"report: {write_report('service', {'args': vars(args), 'rows': rows})}")


if __name__ == "__main__":
    main()
