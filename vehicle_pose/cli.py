"""The ``vehicle-pose`` command line.

Exit codes: 0 success; 2 bad input (unreadable photo, unknown model, mesh with no faces,
invalid camera or box, off-screen start pose, bad arguments) with a one-line reason on stderr;
3 when no OpenGL context can be created on this machine; 4 when the pose was searched without
a start camera and no candidate was credible (the result is written, with ``"failed": true``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from . import __version__
from .camera import Camera
from .errors import RenderError, VehiclePoseError
from .identify import register_or_identify
from .library import ModelLibrary, VehicleModel, model_from_mesh
from .losses import LOSSES
from .metadata import UNITS
from .optimize import OPTIMIZERS
from .overlay import draw_overlay, save_png
from .parametrize import PARAMETRIZATIONS
from .photo import load_photo
from .pipeline import RegistrationOptions

__all__ = ["main"]

class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, as for other bad input
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(2)


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog="vehicle-pose", description="Register a vehicle's 3D model onto a photo.")
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    r = sub.add_parser("register", help="find the model's pose in a photo")
    r.add_argument("photo", help="photo file (JPEG, PNG, ...)")
    r.add_argument("--model", required=True,
                   help="model id from the library, a mesh file path, a,b,c (identify among these ids) "
                        "or auto (identify among every library model)")
    r.add_argument("--out", required=True, help="where to write result.json")
    r.add_argument("--overlay", help="where to write the overlay PNG")
    r.add_argument("--init-camera", help="start camera JSON {K, R, t, width, height}")
    r.add_argument("--bbox", help="vehicle box X0,Y0,X1,Y1 in pixels (the search's start without --init-camera, "
                   "GrabCut's bound with it)")
    r.add_argument("--up", default="+z", help="mesh up axis, for a mesh path (default +z)")
    r.add_argument("--forward", default="+x", help="mesh forward axis, for a mesh path (default +x)")
    r.add_argument("--units", default="m", choices=sorted(UNITS), help="mesh units, for a mesh path")
    r.add_argument("--models-dir", help="model library folder (default: this checkout's vehicle_models/)")
    r.add_argument("--loss", default=RegistrationOptions.loss, choices=sorted(LOSSES))
    r.add_argument("--optimizer", default="nelder-mead", choices=sorted(OPTIMIZERS))
    r.add_argument("--parametrization", default="view", choices=PARAMETRIZATIONS,
                   help="search coordinates: a view perturbation (default) or the paper's theta")
    r.add_argument("--no-resegment", action="store_true", help="run GrabCut once, from the start pose only")
    r.add_argument("--no-focal-probes", action="store_true",
                   help="the second level searches from the first level's pose only, not also from its dolly zooms")
    r.add_argument("--edge-weight", type=float, default=RegistrationOptions.edge_weight,
                   help="weight of the edge alignment term (0: the loss alone)")
    r.add_argument("--box-weight", type=float, default=RegistrationOptions.box_weight,
                   help="with --init-camera and --bbox: weight of the cost of leaving the box (0: none)")
    r.add_argument("--no-box-refit", action="store_true",
                   help="with --init-camera and --bbox: keep the start camera's place and size instead of fitting them to the box")
    r.add_argument("--side", default="auto", choices=("auto", "left", "right"), help="visible side")
    r.add_argument("--color", action="store_true", help="score the three colour channels (n = 3)")
    r.add_argument("--no-grabcut", action="store_true", help="keep the photo's background")
    r.add_argument("--single-level", action="store_true", help="no coarse-to-fine pyramid")
    r.add_argument("--max-evaluations", type=int, default=RegistrationOptions.max_evaluations, help="per level")
    r.add_argument("--starts", type=int, default=RegistrationOptions.starts,
                   help="without --init-camera: distinct start poses screened")
    r.add_argument("--refine", type=int, default=RegistrationOptions.refine,
                   help="without --init-camera: screened poses refined at full size")
    r.add_argument("--shade", type=float, default=0.0, help="blend the shaded model into the overlay (0..1)")

    m = sub.add_parser("models", help="list the model library")
    m.add_argument("--models-dir", help="model library folder")
    return p


def _load_models(args: argparse.Namespace) -> list[VehicleModel]:
    path = Path(args.model)
    if path.suffix and (path.is_file() or "/" in args.model or "\\" in args.model):
        return [model_from_mesh(path, up=args.up, forward=args.forward, units=args.units,
                                meters_per_unit=UNITS[args.units])]
    lib = ModelLibrary(args.models_dir)
    return [lib.load(model_id) for model_id in lib.resolve(args.model)]


def _register(args: argparse.Namespace) -> int:
    photo = load_photo(args.photo)
    models = _load_models(args)
    init = Camera.load(args.init_camera) if args.init_camera else None
    options = RegistrationOptions(
        loss=args.loss,
        optimizer=args.optimizer,
        coarse_to_fine=not args.single_level,
        grabcut=not args.no_grabcut,
        color=args.color,
        max_evaluations=args.max_evaluations,
        side=args.side,
        parametrization=args.parametrization,
        resegment=not args.no_resegment,
        focal_starts=() if args.no_focal_probes else RegistrationOptions.focal_starts,
        starts=args.starts,
        refine=args.refine,
        edge_weight=args.edge_weight,
        box_weight=args.box_weight,
        fit_start_to_box=not args.no_box_refit,
    )
    result, data = register_or_identify(photo, models, init_camera=init, bbox=args.bbox, options=options)
    model = result.model
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(data, indent=2) + "\n")
    if args.overlay:
        image = draw_overlay(photo, model.mesh, result.camera, wheels=model.wheels, shade=args.shade)
        save_png(args.overlay, image)
    conf = "" if result.confidence is None else f", confidence {result.confidence:.2f}"
    print(
        f"registered {model.info.id}: loss {result.loss:.4f}{conf}, {result.evaluations} evaluations, "
        f"{result.seconds:.2f} s -> {out}"
    )
    if result.failed:
        print(f"vehicle-pose: no credible pose found (confidence {result.confidence:.2f}); "
              f"the result is marked failed", file=sys.stderr)
        return 4
    return 0


def _models(args: argparse.Namespace) -> int:
    lib = ModelLibrary(args.models_dir)
    for model_id in lib.ids():
        info = lib.info(model_id)
        print(f"{info.id}\t{info.name}\t{info.mesh_path.name}")
    return 0


_AXIS_OPTIONS = ("--up", "--forward")


def _join_signed_axes(argv: list[str]) -> list[str]:
    """``--forward -y`` as ``--forward=-y``: argparse takes a value that starts with a dash
    for an option of its own, and a mesh's axes are often negative."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        if argv[i] in _AXIS_OPTIONS and i + 1 < len(argv) and argv[i + 1][:1] == "-" \
                and argv[i + 1][1:].lower() in ("x", "y", "z"):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
            continue
        out.append(argv[i])
        i += 1
    return out


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(_join_signed_axes(list(sys.argv[1:] if argv is None else argv)))
    try:
        if args.command == "register":
            return _register(args)
        return _models(args)
    except RenderError as exc:
        print(f"vehicle-pose: error: {exc}", file=sys.stderr)
        return 3
    except (VehiclePoseError, ValueError) as exc:
        print(f"vehicle-pose: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"vehicle-pose: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
