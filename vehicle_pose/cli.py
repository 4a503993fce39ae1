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
from typing import TYPE_CHECKING, NoReturn

from vehicle_pose import __version__
from vehicle_pose.errors import RenderError, VehiclePoseError
from vehicle_pose.model.metadata import UNITS
from vehicle_pose.registration.options import RegistrationOptions

if TYPE_CHECKING:
    from vehicle_pose.model.library import VehicleModel
    from vehicle_pose.model.store import ModelStore

# The renderer, the optimisers and trimesh are imported by the commands that use them:
# ``--help`` and ``models`` answer without them.

__all__ = ["main", "build_parser", "join_signed_axes", "options_from_args"]

class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one line, exit 2, as for other bad input
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="vehicle-pose", description="Register a vehicle's 3D model onto a photo.")
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    r = sub.add_parser("register", help="find the model's pose in a photo")
    r.add_argument("photo", help="photo file (JPEG, PNG, ...)")
    r.add_argument("--model", required=True,
                   help="model id from the library, a mesh file path, a,b,c (identify among these ids) "
                        "or auto (identify among every library model)")
    r.add_argument("--out", required=True, help="where to write result.json")
    r.add_argument("--overlay", help="where to write the overlay PNG (parts tinted, with a legend)")
    r.add_argument("--parts", help="where to write the part map: an indexed PNG, each pixel its part's label "
                                   "(the legend in result.json's parts and the PNG's legend text)")
    r.add_argument("--init-camera", help="start camera JSON {K, R, t, width, height}")
    r.add_argument("--bbox", help="vehicle box X0,Y0,X1,Y1 in pixels (the search's start without --init-camera, "
                   "GrabCut's bound with it)")
    r.add_argument("--up", default="+z", help="mesh up axis, for a mesh path (default +z)")
    r.add_argument("--forward", default="+x", help="mesh forward axis, for a mesh path (default +x)")
    r.add_argument("--units", default="m", choices=sorted(UNITS), help="mesh units, for a mesh path")
    r.add_argument("--models-dir", help="model library folder (default: this checkout's vehicle_models/)")
    _add_option_flags(r)
    r.add_argument("--shade", type=float, default=0.0, help="blend the shaded model into the overlay (0..1)")

    m = sub.add_parser("models", help="list the model library")
    m.add_argument("--models-dir", help="model library folder")

    q = sub.add_parser("prepare", help="prepare models for the cache now (registration does it on first use)")
    q.add_argument("model", nargs="*",
                   help="model ids or mesh file paths (default: every model of the library)")
    q.add_argument("--up", default="+z", help="mesh up axis, for mesh paths (default +z)")
    q.add_argument("--forward", default="+x", help="mesh forward axis, for mesh paths (default +x)")
    q.add_argument("--units", default="m", choices=sorted(UNITS), help="mesh units, for mesh paths")
    q.add_argument("--models-dir", help="model library folder")
    for a in (r, q):
        a.add_argument("--texture-dir", action="append", default=[], metavar="DIR",
                       help="for a mesh path: a further folder searched for its texture images (repeatable)")
        a.add_argument("--cache-dir", help="where prepared models are kept (default $VEHICLE_POSE_CACHE_DIR, "
                       "else $XDG_CACHE_HOME/vehicle-pose, else ~/.cache/vehicle-pose)")
    r.add_argument("--no-cache", action="store_true",
                   help="prepare the model in memory only, reading and writing no cache")
    return p


def _add_option_flags(parser: argparse.ArgumentParser) -> None:
    """A flag for each public registration option, from its declaration (registration/options.py):
    a boolean's flag sets the opposite of its default, a flag with a value sets that value."""
    for name, f, spec in RegistrationOptions.specs():
        if not spec.public:
            continue
        flag = spec.flag or "--" + name.replace("_", "-")
        if spec.flag_value is not None or isinstance(f.default, bool):
            const = spec.flag_value if spec.flag_value is not None else not f.default
            negates = const is False or const == ()
            parser.add_argument(flag, dest=name, action="store_const", const=const, default=None,
                                help=f"off: {spec.help}" if negates else spec.help)
        else:
            kind = type(f.default)
            parser.add_argument(flag, dest=name, type=kind, default=None, choices=spec.choices,
                                metavar=None if spec.choices else kind.__name__.upper(),
                                help=f"{spec.help} (default {f.default})")


def options_from_args(args: argparse.Namespace) -> RegistrationOptions:
    """The registration options: the defaults, with those set on the command line."""
    given = {name: getattr(args, name) for name, _, spec in RegistrationOptions.specs()
             if spec.public and getattr(args, name, None) is not None}
    return RegistrationOptions.from_flat(given)


def _store(args: argparse.Namespace) -> ModelStore | None:
    from vehicle_pose.model.store import ModelStore

    if getattr(args, "no_cache", False):
        return None
    return ModelStore(Path(args.cache_dir) / "prepared" if args.cache_dir else None)


def _is_path(spec: str) -> bool:
    return bool(Path(spec).suffix) and (Path(spec).is_file() or "/" in spec or "\\" in spec)


def _load_models(args: argparse.Namespace, specs: list[str]) -> list[VehicleModel]:
    """Models named by mesh paths or library specs, each prepared completely on its first
    use (levels of detail and exterior passes, with a progress line) when a store is on."""
    from vehicle_pose.model.library import ModelLibrary, model_from_mesh
    from vehicle_pose.model.store import default_budgets
    from vehicle_pose.render.renderer import Renderer

    store = _store(args)
    lib = ModelLibrary(args.models_dir, store=store)
    models = []
    for spec in specs:
        if _is_path(spec):
            models.append(model_from_mesh(spec, up=args.up, forward=args.forward, units=args.units,
                                          meters_per_unit=UNITS[args.units], store=store,
                                          texture_dirs=tuple(args.texture_dir)))
        else:
            models += [lib.load(model_id) for model_id in lib.resolve(spec)]
    if store is not None:
        renderer = Renderer()
        for model in models:
            assert model.levels is not None
            missing = model.levels.missing(default_budgets(model.mesh.n_faces), renderer)
            if missing:
                _prepare(model, missing, renderer)
    return models


def _prepare(model: VehicleModel, budgets: list[int], renderer: object) -> None:
    import time

    t = time.perf_counter()
    print(f"vehicle-pose: preparing {model.info.id} ({model.mesh.n_faces} faces) for the cache, once",
          file=sys.stderr, flush=True)
    model.prepare(renderer, budgets, progress=lambda line: print(f"  {line}", file=sys.stderr, flush=True))  # type: ignore[arg-type]
    where = model.levels.entry.folder if model.levels is not None and model.levels.entry is not None else "memory"
    print(f"vehicle-pose: prepared {model.info.id} in {time.perf_counter() - t:.1f} s -> {where}",
          file=sys.stderr, flush=True)


def _prepare_command(args: argparse.Namespace) -> int:
    from vehicle_pose.model.library import ModelLibrary

    specs = args.model or ModelLibrary(args.models_dir).ids()
    for model in _load_models(args, specs):
        print(f"{model.info.id}\tprepared")
    return 0


def _register(args: argparse.Namespace) -> int:
    from vehicle_pose.geometry.camera import Camera
    from vehicle_pose.photo import load_photo_focal
    from vehicle_pose.registration.identify import register_or_identify
    from vehicle_pose.render.overlay import draw_overlay, save_png

    photo, exif = load_photo_focal(args.photo)
    models = _load_models(args, [args.model])
    init = Camera.load(args.init_camera) if args.init_camera else None
    options = options_from_args(args)
    result, data = register_or_identify(photo, models, init_camera=init, bbox=args.bbox, options=options, exif=exif)
    model = result.model
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(data, indent=2) + "\n")
    if args.overlay:
        image = draw_overlay(photo, model.mesh, result.camera, wheels=model.wheels, shade=args.shade,
                             parts=result.parts)
        save_png(args.overlay, image)
    if args.parts and result.parts is not None:
        where = Path(args.parts)
        where.parent.mkdir(parents=True, exist_ok=True)
        where.write_bytes(result.parts.png())
    for warning in result.warnings:
        print(f"vehicle-pose: warning: {warning}", file=sys.stderr)
    conf = "" if result.confidence is None else f", confidence {result.confidence:.2f}"
    focal = result.focal
    lens = ""
    if focal.get("source") == "exif" and focal.get("exif"):
        lens = f", focal length {focal['pixels']:.0f} px (the EXIF's {focal['exif']['pixels']:.0f} px)"
    print(
        f"registered {model.info.id}: loss {result.loss:.4f}{conf}{lens}, {result.evaluations} evaluations, "
        f"{result.seconds:.2f} s -> {out}"
    )
    if result.failed:
        print(f"vehicle-pose: no credible pose found (confidence {result.confidence:.2f}); "
              f"the result is marked failed", file=sys.stderr)
        return 4
    return 0


def _models(args: argparse.Namespace) -> int:
    from vehicle_pose.model.library import ModelLibrary

    lib = ModelLibrary(args.models_dir)
    for model_id in lib.ids():
        info = lib.info(model_id)
        print(f"{info.id}\t{info.name}\t{info.mesh_path.name}")
    return 0


_AXIS_OPTIONS = ("--up", "--forward")


def join_signed_axes(argv: list[str]) -> list[str]:
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
    args = build_parser().parse_args(join_signed_axes(list(sys.argv[1:] if argv is None else argv)))
    try:
        if args.command == "register":
            return _register(args)
        if args.command == "prepare":
            return _prepare_command(args)
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
