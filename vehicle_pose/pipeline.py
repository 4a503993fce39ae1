"""The registration pipeline (method.md §5): start pose, GrabCut, coarse-to-fine simplex search.

>>> result = register(photo_rgb, model, init_camera=camera)      # doctest: +SKIP
>>> result.camera.K, result.camera.R, result.camera.t             # doctest: +SKIP
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from .camera import Camera
from .errors import CameraError, PoseError
from .initialize import central_box, parse_bbox, start_from_box
from .library import VehicleModel
from .loss import make_target
from .losses import LOSSES, make_loss
from .optimize import OPTIMIZERS, Optimizer
from .parametrize import PARAMETRIZATIONS, Parametrization, ThetaParams, ViewParams
from .pose import Side, Theta, camera_to_theta, visible_side
from .render import Renderer
from .segment import grabcut_foreground

__all__ = ["RegistrationOptions", "LevelReport", "RegistrationResult", "register"]

Progress = Callable[[str, int, float], None]
_INVALID = 10.0


@dataclass(frozen=True)
class RegistrationOptions:
    """How to register; the defaults are the paper's method plus coarse-to-fine.

    Attributes
    ----------
    loss : str
        A name from :data:`vehicle_pose.losses.LOSSES`.
    optimizer : str
        A name from :data:`vehicle_pose.optimize.OPTIMIZERS`.
    coarse_to_fine : bool
        First optimise on a reduced photo with a decimated mesh, then at full working size.
    max_size : int
        Longer side (pixels) of the finest working image; larger photos are reduced.
    coarse_sizes : tuple of int
        Longer sides of the coarse levels, coarsest first; those not well below the working
        size are skipped.
    faces_per_pixel : float
        Level of detail: each level renders a decimation of the mesh with about this many
        faces per pixel of the start silhouette (rounded up to a power of two, at least
        ``min_faces``); finer triangles than pixels change no pixel of the render.
    min_faces : int
        Smallest face budget of a level.
    grabcut : bool
        Remove the background with GrabCut seeded by the start pose.
    grabcut_margin : float
        GrabCut seed margin, fraction of the start silhouette's diagonal.
    resegment : bool
        Run GrabCut again after each coarse level, seeded by that level's pose with
        ``resegment_margin`` and its shrunk silhouette as certain foreground: a better pose
        seeds a better mask.
    resegment_margin : float
    color : bool
        Score colour photos with n = 3 channels; by default the photo's luminance is scored
        (n = 1, the paper's setting); docs/benchmarks.md compares the two.
    max_evaluations : int
        Loss evaluations allowed per level.
    side : str
        ``"auto"`` (from the start pose), ``"left"`` or ``"right"``: the visible side.
    parametrization : str
        Search coordinates: ``"view"`` (default) or ``"theta"`` (the paper's), see
        :mod:`vehicle_pose.parametrize`; the paper's theta succeeded on 50 % of the photoreal
        cases even with the true mask, the view coordinates on 85 % (docs/benchmarks.md).
    """

    loss: str = "invariant"
    optimizer: str = "nelder-mead"
    coarse_to_fine: bool = True
    max_size: int = 800
    coarse_sizes: tuple[int, ...] = (160, 320)
    faces_per_pixel: float = 1.0
    min_faces: int = 16384
    grabcut: bool = True
    grabcut_margin: float = 0.12
    resegment: bool = True
    resegment_margin: float = 0.08
    color: bool = False
    max_evaluations: int = 400
    side: str = "auto"
    parametrization: str = "view"


@dataclass(frozen=True)
class LevelReport:
    """What one pyramid level did."""

    width: int
    height: int
    faces: int
    evaluations: int
    restarts: int
    loss: float
    seconds: float


@dataclass
class RegistrationResult:
    """A registered pose and how it was found.

    ``camera`` maps mesh coordinates to pixels of the photo as given (OpenCV convention);
    ``foreground`` is the GrabCut mask at the photo's size.
    """

    camera: Camera
    theta: Theta
    loss: float
    evaluations: int
    restarts: int
    seconds: float
    model: VehicleModel
    start_source: str
    start_camera: Camera
    levels: list[LevelReport]
    options: RegistrationOptions
    foreground: npt.NDArray[np.bool_] = field(repr=False)
    timings: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The JSON result: camera, theta, BOP-style fields, loss, counts, timings."""
        cam = self.camera
        info = self.model.info
        return {
            "camera": cam.to_dict(),
            "theta": self.theta.to_dict(),
            "loss": self.loss,
            "loss_name": self.options.loss,
            "evaluations": self.evaluations,
            "restarts": self.restarts,
            "seconds": self.seconds,
            "model": {
                "id": info.id,
                "name": info.name,
                "units": info.units,
                "wheels": self.model.wheels.to_dict(),
                "estimated": list(info.estimated),
            },
            "start": {"source": self.start_source, "camera": self.start_camera.to_dict()},
            "levels": [vars(level) for level in self.levels],
            "timings": self.timings,
            "cam_R_m2c": cam.R.reshape(-1).tolist(),
            "cam_t_m2c": cam.t.tolist(),
            "cam_K": cam.K.reshape(-1).tolist(),
        }


def _resize(rgb: npt.NDArray[np.uint8], width: int, height: int) -> npt.NDArray[np.uint8]:
    if (rgb.shape[1], rgb.shape[0]) == (width, height):
        return rgb
    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)


def _resize_mask(mask: npt.NDArray[np.bool_], width: int, height: int) -> npt.NDArray[np.bool_]:
    if (mask.shape[1], mask.shape[0]) == (width, height):
        return mask
    return cv2.resize(mask.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST) > 0


def _level_sizes(width: int, height: int, options: RegistrationOptions) -> list[tuple[int, int]]:
    longer = max(width, height)
    sizes = []
    if options.coarse_to_fine:
        for size in options.coarse_sizes:
            if size < 0.75 * longer:
                s = size / longer
                sizes.append((max(8, round(width * s)), max(8, round(height * s))))
    return [*sizes, (width, height)]


def _face_budget(pixels: float, options: RegistrationOptions) -> int:
    wanted = max(float(options.min_faces), options.faces_per_pixel * pixels)
    return int(2 ** np.ceil(np.log2(wanted)))


def register(
    photo: npt.NDArray[np.uint8],
    model: VehicleModel,
    *,
    init_camera: Camera | None = None,
    bbox: str | Sequence[float] | None = None,
    options: RegistrationOptions = RegistrationOptions(),
    renderer: Renderer | None = None,
    optimizer: Optimizer | None = None,
    progress: Progress | None = None,
    foreground: npt.NDArray[np.bool_] | None = None,
) -> RegistrationResult:
    """Find the camera that makes the model coincide with the vehicle in the photo.

    Parameters
    ----------
    photo : (H, W, 3) uint8
        RGB photo (gray photos have three equal channels).
    model : VehicleModel
    init_camera : Camera, optional, keyword-only
        Start pose; a camera for a photo of another size is rescaled to this one.
    bbox : "X0,Y0,X1,Y1" or 4 numbers, optional, keyword-only
        The vehicle's box, used when there is no start camera.
    options : RegistrationOptions, keyword-only
    renderer : Renderer, optional, keyword-only
        Defaults to a renderer on the process's EGL context.
    optimizer : Optimizer, optional, keyword-only
        Overrides ``options.optimizer``.
    progress : callable(stage, evaluations, loss), optional, keyword-only
    foreground : (H, W) bool, optional, keyword-only
        The vehicle's pixels, when the caller knows them; replaces GrabCut.

    Raises
    ------
    CameraError
        The start camera or box is malformed.
    PoseError
        The start pose puts the model behind the camera or off-screen.
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    if photo.ndim != 3 or photo.shape[2] != 3 or photo.dtype != np.uint8:
        raise ValueError("photo must be an (H, W, 3) uint8 RGB array")
    H0, W0 = photo.shape[:2]
    renderer = renderer if renderer is not None else Renderer()
    if optimizer is None:
        if options.optimizer not in OPTIMIZERS:
            raise ValueError(f"unknown optimizer {options.optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
        optimizer = OPTIMIZERS[options.optimizer]()
    if options.parametrization not in PARAMETRIZATIONS:
        raise ValueError(f"unknown parametrization {options.parametrization!r}; choose one of {', '.join(PARAMETRIZATIONS)}")
    if options.loss not in LOSSES:
        raise ValueError(f"unknown loss {options.loss!r}; choose one of {', '.join(LOSSES)}")

    s = min(1.0, options.max_size / max(W0, H0))
    Wf, Hf = max(8, round(W0 * s)), max(8, round(H0 * s))
    work = _resize(photo, Wf, Hf)

    t = time.perf_counter()
    if init_camera is not None:
        source = "init_camera"
        start = init_camera.scaled(Wf, Hf)
    else:
        source = "bbox" if bbox is not None else "none"
        box = parse_bbox(bbox, W0, H0) if bbox is not None else central_box(W0, H0)
        box = tuple(v * Wf / W0 if i % 2 == 0 else v * Hf / H0 for i, v in enumerate(box))
        start = start_from_box(work, model, box, renderer, max_faces=options.min_faces)  # type: ignore[arg-type]
    timings["start"] = time.perf_counter() - t

    side: Side
    if options.side in ("left", "right"):
        side = options.side  # type: ignore[assignment]
    elif options.side == "auto":
        side = visible_side(start, model.wheels.side("left"))
    else:
        raise ValueError(f"side must be 'auto', 'left' or 'right', not {options.side!r}")
    geometry = model.wheels.side(side)

    coarse_mesh = model.lod(options.min_faces)
    silhouette = renderer.render(coarse_mesh, start).coverage
    if silhouette.sum() < 16:
        raise PoseError("the start pose puts the model off-screen or behind the camera")

    t = time.perf_counter()
    segment_again = options.grabcut and options.resegment and foreground is None
    if foreground is not None:
        if foreground.shape != (H0, W0):
            raise ValueError(f"foreground mask is {foreground.shape}, the photo {(H0, W0)}")
        foreground = _resize_mask(foreground.astype(bool), Wf, Hf)
    elif options.grabcut:
        foreground = grabcut_foreground(work, silhouette, margin=options.grabcut_margin)
    else:
        foreground = np.ones((Hf, Wf), bool)
    timings["grabcut"] = time.perf_counter() - t

    camera = start
    levels: list[LevelReport] = []
    sizes = _level_sizes(Wf, Hf, options)
    for li, (w, h) in enumerate(sizes):
        t = time.perf_counter()
        mesh = model.lod(_face_budget(float(silhouette.sum()) * (w * h) / (Wf * Hf), options))
        target = make_target(_resize(work, w, h), _resize_mask(foreground, w, h), color=options.color)
        loss_fn = make_loss(options.loss, target)
        params: Parametrization
        if options.parametrization == "view":
            params = ViewParams(camera.scaled(w, h), model.mesh.sphere[0])
        else:
            params = ThetaParams(camera.scaled(w, h), geometry, side)
        try:
            x0 = params.start()
        except PoseError:
            raise PoseError(f"the start pose does not show the {side} side's wheels") from None
        steps = params.steps() * 0.4**li
        stage = f"level {li + 1}/{len(sizes)} ({w}x{h})"
        counter = [0]

        def objective(x: npt.NDArray[np.float64]) -> float:
            try:
                cam = params.camera(x)
            except (PoseError, CameraError):
                return _INVALID
            value = float(loss_fn(renderer.render(mesh, cam)))
            counter[0] += 1
            if progress is not None and counter[0] % 20 == 0:
                progress(stage, counter[0], value)
            return value

        res = optimizer(objective, x0, steps, max_evaluations=options.max_evaluations)
        camera = params.camera(res.x).scaled(Wf, Hf)
        levels.append(LevelReport(w, h, mesh.n_faces, res.evaluations, res.restarts, res.fun, time.perf_counter() - t))
        if progress is not None:
            progress(stage, res.evaluations, res.fun)
        if segment_again and li < len(sizes) - 1:
            t = time.perf_counter()
            current = renderer.render(coarse_mesh, camera).coverage
            if current.sum() >= 16:
                foreground = grabcut_foreground(work, current, margin=options.resegment_margin, sure_core=True)
            timings["grabcut"] += time.perf_counter() - t

    final = camera.scaled(W0, H0)
    side = visible_side(final, model.wheels.side("left"))
    theta = camera_to_theta(final, model.wheels.side(side), side)
    seconds = time.perf_counter() - t_start
    timings["optimize"] = sum(level.seconds for level in levels)
    return RegistrationResult(
        camera=final,
        theta=theta,
        loss=levels[-1].loss,
        evaluations=sum(level.evaluations for level in levels),
        restarts=sum(level.restarts for level in levels),
        seconds=seconds,
        model=model,
        start_source=source,
        start_camera=start.scaled(W0, H0),
        levels=levels,
        options=options,
        foreground=_resize_mask(foreground, W0, H0),
        timings=timings,
    )
