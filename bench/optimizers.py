"""Which minimiser reaches the lowest cost in the fewest evaluations, on the searches' own costs.

Usage: .venv/bin/python bench/optimizers.py [--cases N] [--shared ../shared/real] [--start none|init.json]
       [--methods powell,cobyqa,cma-es] [--tolerance 0.002] [--tag T]

Each real photo is registered as ``bench/real.py`` does (no hint by default), with the
default optimiser, the restarted downhill simplex (``nelder-mead``). Every call the engine makes
to it is replayed from the same start, with the same steps and budget, by each other method on
the same cost (the registration itself goes on with the simplex's result, so every call is one
the engine really makes). For each kind of call (its dimension and budget: the view sphere's
refinements are the 4-coordinate first stage, rotation held, and the 7-coordinate second) the
table gives per method: the evaluations used, how far its best value ends above the simplex's
(median, and the calls more than 0.005 above), the same after half the budget, and the
evaluations it needs to come within ``--tolerance`` of the simplex's final value (median; calls
that never do). Writes bench/results/optimizers[_TAG].json.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from real import load_models
from scipy.optimize import minimize

from vehicle_pose.geometry.camera import Camera
from vehicle_pose.photo import load_photo
from vehicle_pose.registration.register import register
from vehicle_pose.render.renderer import Renderer
from vehicle_pose.search.optimize import CMAES, NelderMeadRestarts, Objective, OptimizeResult, Powell

from common import table, write_report

SHARED = Path(__file__).resolve().parents[2] / "shared"


class _Spent(Exception):
    """The replay's budget is spent."""


def _cobyqa(fun: Objective, x0: np.ndarray, steps: np.ndarray, *, max_evaluations: int) -> None:
    """SciPy's COBYQA (a derivative-free trust-region method on quadratic models), its first
    trust region one step wide and its last a twentieth of one (the simplex's ``xtol``)."""
    minimize(lambda z: fun(x0 + z * steps), np.zeros_like(x0), method="COBYQA",
             options={"maxfev": max_evaluations, "initial_tr_radius": 1.0, "final_tr_radius": 0.05})


REPLAYS: dict[str, Callable[..., object]] = {"powell": Powell(), "cobyqa": _cobyqa, "cma-es": CMAES()}


def _trace(method: Callable[..., object], fun: Objective, x0: np.ndarray, steps: np.ndarray,
           budget: int) -> list[float]:
    """The lowest value seen after each evaluation of ``method`` minimising ``fun`` from ``x0``."""
    seen: list[float] = []

    def counted(x: np.ndarray) -> float:
        if len(seen) >= budget:
            raise _Spent
        seen.append(float(fun(x)))
        return seen[-1]

    try:
        method(counted, np.asarray(x0, np.float64), np.asarray(steps, np.float64), max_evaluations=budget)
    except _Spent:
        pass
    return np.minimum.accumulate(seen).tolist() if seen else [np.inf]


class Replaying:
    """The default simplex, each of its calls replayed by the other ``methods`` (traces kept in
    ``calls``)."""

    def __init__(self, methods: list[str]) -> None:
        self.simplex = NelderMeadRestarts()
        self.methods = methods
        self.calls: list[dict] = []

    def __call__(self, fun: Objective, x0: np.ndarray, steps: np.ndarray, *, max_evaluations: int) -> OptimizeResult:
        seen: list[float] = []

        def counted(x: np.ndarray) -> float:
            seen.append(float(fun(x)))
            return seen[-1]

        res = self.simplex(counted, x0, steps, max_evaluations=max_evaluations)
        call = {"dim": len(x0), "budget": max_evaluations, "nelder-mead": np.minimum.accumulate(seen).tolist()}
        for m in self.methods:
            call[m] = _trace(REPLAYS[m], fun, np.asarray(x0, np.float64), np.asarray(steps, np.float64),
                             max_evaluations)
        self.calls.append(call)
        return res


def summary(calls: list[dict], methods: list[str], tolerance: float) -> list[dict]:
    rows = []
    for dim, budget in sorted({(c["dim"], c["budget"]) for c in calls}):
        sel = [c for c in calls if c["dim"] == dim and c["budget"] == budget]
        for m in ["nelder-mead", *methods]:
            ends, halves, reach = [], [], []
            for c in sel:
                ref, tr = c["nelder-mead"][-1], c[m]
                ends.append(tr[-1] - ref)
                halves.append(tr[min(len(tr), budget // 2) - 1] - ref)
                reach.append(next((i + 1 for i, v in enumerate(tr) if v <= ref + tolerance), None))
            got = [r for r in reach if r is not None]
            rows.append({"coordinates": dim, "budget": budget, "calls": len(sel), "method": m,
                         "evaluations": float(np.median([len(c[m]) for c in sel])),
                         "above the simplex": float(np.median(ends)),
                         "> 0.005 above": int(np.sum(np.array(ends) > 0.005)),
                         "above at half": float(np.median(halves)),
                         "> 0.005 at half": int(np.sum(np.array(halves) > 0.005)),
                         "to reach, of those that do": float(np.median(got)) if got else float("nan"),
                         "never": len(reach) - len(got)})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=6, help="photos, spread evenly over the set (0: all)")
    ap.add_argument("--shared", type=Path, default=SHARED / "real")
    ap.add_argument("--start", default="none", choices=("none", "init.json"))
    ap.add_argument("--methods", default=",".join(REPLAYS))
    ap.add_argument("--tolerance", type=float, default=0.002)
    ap.add_argument("--tag", default="")
    args = ap.parse_args()
    methods = [m for m in args.methods.split(",") if m]
    for m in methods:
        if m not in REPLAYS:
            raise SystemExit(f"unknown method {m!r}: one of {', '.join(REPLAYS)}")
    model = next(iter(load_models(args.shared).values()))
    renderer = Renderer()
    folders = sorted((args.shared / "cases").iterdir())
    if 0 < args.cases < len(folders):
        folders = [folders[i] for i in np.linspace(0, len(folders) - 1, args.cases).round().astype(int)]
    replaying = Replaying(methods)
    for case in folders:
        hint = json.loads((case / "init.json").read_text()) if args.start != "none" else None
        res = register(load_photo(case / "photo.jpg"), model, renderer=renderer, optimizer=replaying,
                       init_camera=None if hint is None else Camera.from_dict(hint),
                       bbox=None if hint is None else hint.get("bbox"))
        print(f"{case.name}: {res.pose_stage}, {len(replaying.calls)} calls so far", flush=True)
    rows = summary(replaying.calls, methods, args.tolerance)
    print(table(rows, list(rows[0])))
    name = "optimizers" + (f"_{args.tag}" if args.tag else "")
    print(write_report(name, {"rows": rows, "calls": replaying.calls, "cases": [c.name for c in folders],
                              "start": args.start, "tolerance": args.tolerance}))


if __name__ == "__main__":
    main()
