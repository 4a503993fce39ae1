"""The registration's options: frozen groups, validated once when they are made.

Every field is declared with :func:`option`, which carries what the command line and the
service's API need to offer it (help, bounds, choices; ``public`` fields only): the CLI's
flags and the API's schema are derived from these declarations. Why a default is what it is
lives in the decision records under ``docs/decisions/``, named in each group's docstring.

This module imports nothing heavy: ``vehicle-pose --help`` reads it.

>>> RegistrationOptions(budgets=Budgets(max_evaluations=150)).budgets.max_evaluations
150
>>> RegistrationOptions.from_flat(starts=3, max_size=320).search.starts
3
"""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from vehicle_pose.registry import LOSSES, OPTIMIZERS, PARAMETRIZATIONS

__all__ = [
    "RegistrationOptions", "Pyramid", "Segmentation", "Terms", "Structure", "Budgets", "Probes", "Search",
    "OptionSpec", "option", "WINDOW_MARGIN", "SIDES",
]

WINDOW_MARGIN = 0.3
"""The start-pose searches look at the vehicle's box grown by this fraction of its longer side."""
SIDES: tuple[str, ...] = ("auto", "left", "right")


@dataclass(frozen=True)
class OptionSpec:
    """How one option is offered and checked.

    ``low`` and ``high`` bound a number (each entry of a tuple); ``choices`` lists the values of
    a name. A ``public`` option is a CLI flag and a field of the API's ``options``: ``flag`` is
    its CLI form, by default ``--name-with-dashes``; a flag of a boolean sets the opposite of the
    default, a flag with ``flag_value`` sets that value.
    """

    help: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] | None = None
    public: bool = False
    flag: str | None = None
    flag_value: Any = None


def option(default: Any, help: str, **spec: Any) -> Any:
    """A dataclass field with its :class:`OptionSpec` as metadata."""
    return field(default=default, metadata={"spec": OptionSpec(help, **spec)})


def _check(owner: object) -> None:
    """ValueError naming the field and the reason when a value is out of its bounds or choices."""
    hints = typing.get_type_hints(type(owner))
    for f in dataclasses.fields(owner):  # type: ignore[arg-type]
        spec = f.metadata.get("spec")
        value = getattr(owner, f.name)
        if spec is None:
            if not isinstance(value, hints[f.name]):
                raise ValueError(f"{f.name} must be a {hints[f.name].__name__}, not {value!r}")
            continue
        _check_value(f.name, value, f.default, hints[f.name], spec)


def _check_value(name: str, value: Any, default: Any, kind: Any, spec: OptionSpec) -> None:
    if value is None:
        if type(None) not in typing.get_args(kind):
            raise ValueError(f"{name} may not be None")
        return
    if spec.choices is not None:
        if value not in spec.choices:
            raise ValueError(f"unknown {name} {value!r}; choose one of {', '.join(spec.choices)}")
        return
    if isinstance(default, bool) or bool in typing.get_args(kind):
        if not isinstance(value, bool):
            raise ValueError(f"{name} must be true or false, not {value!r}")
        return
    if isinstance(default, tuple):
        if not isinstance(value, tuple):
            raise ValueError(f"{name} must be a tuple, not {value!r}")
        numbers = [v for entry in value for v in (entry if isinstance(entry, tuple) else (entry,))]
    else:
        numbers = [value]
    for v in numbers:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"{name} must be a number, not {v!r}")
        if isinstance(default, int) and not isinstance(default, bool) and not isinstance(v, int):
            raise ValueError(f"{name} must be a whole number, not {v!r}")
        if not math.isfinite(v):
            raise ValueError(f"{name} must be a finite number, not {v!r}")
        if (spec.low is not None and v < spec.low) or (spec.high is not None and v > spec.high):
            bounds = f"in [{spec.low}, {spec.high}]" if spec.high is not None else f"at least {spec.low}"
            raise ValueError(f"{name} must be {bounds}, not {v!r}")


def _tupled(value: Any) -> Any:
    """Lists (as JSON gives them) as tuples, nested ones too."""
    return tuple(_tupled(v) for v in value) if isinstance(value, list) else value


class _Group:
    """Checks the fields of an option group when it is made."""

    def __post_init__(self) -> None:
        _check(self)


@dataclass(frozen=True)
class Pyramid(_Group):
    """The coarse-to-fine levels (``docs/decisions/0001-coarse-to-fine.md``).

    The search runs on each of ``coarse_sizes`` (longer side, pixels; those not well below the
    working size are skipped), then at the working size, at most ``max_size``. Each level renders
    a decimation of the mesh with about ``faces_per_pixel`` faces per pixel of the start
    silhouette, rounded up to a power of two and at least ``min_faces``. With ``max_pixels``
    positive the working size is reduced until the start silhouette covers at most that many
    pixels.
    """

    coarse_to_fine: bool = option(True, "run the coarse levels before the working size", public=True,
                                  flag="--single-level")
    max_size: int = option(800, "longer side of the working photo (pixels)", low=16)
    coarse_sizes: tuple[int, ...] = option((160, 320), "longer sides of the coarse levels, coarsest first", low=8)
    faces_per_pixel: float = option(0.5, "faces per pixel of the start silhouette at each level", low=1e-6)
    min_faces: int = option(8192, "smallest face budget of a level", low=4)
    max_pixels: int = option(0, "when positive, the most pixels the start silhouette may cover", low=0)


@dataclass(frozen=True)
class Segmentation(_Group):
    """GrabCut (``docs/decisions/0004-resegmentation.md``).

    The first mask is seeded by the start silhouette grown by ``grabcut_margin`` of its diagonal
    (and, with a box, the box grown by ``box_margin``); after each coarse level GrabCut runs
    again (``resegment``), seeded by that level's pose grown by ``resegment_margin``, its shrunk
    silhouette certain foreground, for ``resegment_iterations`` iterations. With a box, the
    pixels of the grown box that GrabCut calls background count ``doubt_weight`` in the loss
    (1, as any background, by default: a lower weight helped the real photos, where GrabCut drops
    the dark lower body, tyres and shadow of a car, and cost the photoreal ones;
    ``docs/decisions/0006-real-photo-terms.md``).
    """

    grabcut: bool = option(True, "remove the background with GrabCut", public=True, flag="--no-grabcut")
    grabcut_margin: float = option(0.12, "seed margin of the first GrabCut (silhouette diagonals)", low=0.0, high=1.0)
    box_margin: float = option(0.04, "how far beyond the client's box GrabCut may claim the vehicle", low=0.0, high=1.0)
    resegment: bool = option(True, "run GrabCut again after each coarse level", public=True, flag="--no-resegment")
    resegment_margin: float = option(0.08, "seed margin of a resegmentation (silhouette diagonals)", low=0.0, high=1.0)
    resegment_iterations: int = option(2, "GrabCut iterations of a resegmentation", low=1, high=20)
    doubt_weight: float = option(1.0, "with a box: loss weight of the box's pixels that GrabCut calls background",
                                 low=0.0, high=1.0)


@dataclass(frozen=True)
class Terms(_Group):
    """What joins the loss when a start camera is given (``docs/decisions/0006-real-photo-terms.md``).

    With a box, the start is first moved and scaled to fill it (``fit_start_to_box``), and the
    objective is raised by ``box_weight`` times how far the projection leaves the box grown by
    ``box_tolerance`` of its size, or falls short of it by more than ``box_shortfall``
    (:func:`~vehicle_pose.search.views.box_overflow`). The edge term adds ``edge_weight`` times
    the directional chamfer cost of the model's edges (normal creases above ``edge_crease``)
    against the photo's (:class:`~vehicle_pose.loss.edges.EdgeLoss`). The search without a start
    camera runs without the edge term (``docs/decisions/0007-no-hint-search.md``). With a start
    camera and no box, the view-sphere search's cost is raised by ``start_weight`` times the
    square of the angle the pose is turned from the start's rotation over
    ``structure.structure_spread`` (a start's rotation error): the start is evidence about the
    pose, weighed with the edges (``docs/decisions/0039-start-prior.md``). The weight is divided
    by the share of the model's points the start shows inside the frame: a car cut by the frame
    leaves the edges less evidence (``docs/decisions/0050-a-cut-start-weighs-more.md``).
    """

    fit_start_to_box: bool = option(True, "with a start camera and a box: fit the start's place and size to the box",
                                    public=True, flag="--no-box-refit")
    box_weight: float = option(1.0, "with a start camera and a box: weight of the cost of leaving the box (0: none)",
                               low=0.0, high=100.0, public=True)
    box_tolerance: float = option(0.05, "how far the projection may pass the box free of cost (box sizes)",
                                  low=0.0, high=1.0)
    box_shortfall: float | None = option(0.15, "how far short of the box a side may fall free of cost "
                                         "(box sizes; None: any)", low=0.0, high=1.0)
    edge_weight: float = option(0.5, "with a start camera: weight of the edge alignment term (0: the loss alone)",
                                low=0.0, high=10.0, public=True)
    start_weight: float = option(0.03, "with a start camera and no box: weight of the start's rotation in the "
                                 "view-sphere search, times (degrees turned from it / structure_spread) squared "
                                 "(0: none)", low=0.0, high=10.0)
    edge_crease: float = option(0.6, "change of a normal component between pixels that makes a model edge",
                                low=0.0, high=2.0)


@dataclass(frozen=True)
class Structure(_Group):
    """The structure's pose, with a start camera and a box (``docs/decisions/0012-structure-first.md``).

    When the shading fit's loss over its maximum is above ``shading_screen`` with a box,
    ``shading_trust`` without (the shading model does not explain the photo: real paint and
    glass mirror their surroundings), the pose is
    found on the photo's edges instead, from the client's start (a shading fit whose first
    level ends above ``shading_screen``, or is still above it after ``screen_after``
    evaluations, stops there: ``docs/decisions/0022-shading-screen.md``,
    ``0041-camera-and-box-by-the-view-sphere.md``). With a box, by default the view-sphere
    search narrowed to the start refitted to the box; with ``anchored_search``
    the rotation and focal length are searched on the directional chamfer (truncated at
    ``anchor_tau`` of the diagonal) with the place and size fitted to the box, at
    ``structure_size`` pixels, by the cross-entropy method (``anchor_population`` samples a
    generation, the first spread by ``structure_spread`` degrees, ``anchor_evaluations`` a
    search; ``structure_runs`` searches with their own samples, seeded from ``structure_seed``
    on, their results averaged: ``docs/decisions/0016-averaged-anchors.md``,
    ``0028-seed-spread.md``); then all coordinates on the chamfer (truncated at
    ``structure_tau``) and the box term (``structure_evaluations``).
    """

    structure: bool = option(True, "with a start camera and a box: find the pose on the photo's edges and the box "
                             "where the shading fit is not credible", public=True, flag="--no-structure")
    structure_size: int = option(320, "longer side of the photo for the structure stages (pixels)", low=16)
    structure_spread: float = option(10.0, "spread of the anchored search's first samples (degrees)", low=0.0,
                                     high=45.0)
    anchor_tau: float = option(0.05, "chamfer truncation of the anchored search, the view-sphere search and the "
                               "edge evidence (photo diagonals)", low=1e-3, high=1.0)
    structure_tau: float = option(0.03, "chamfer truncation of the free structure refinement (photo diagonals)",
                                  low=1e-3, high=1.0)
    anchor_population: int = option(100, "samples per generation of the anchored search", low=10, high=1000)
    anchor_evaluations: int = option(301, "evaluations of each anchored search (whole generations, and their mean)",
                                     low=11)
    structure_evaluations: int = option(300, "evaluations of the free structure refinement", low=0)
    structure_runs: int = option(2, "independent anchored searches, each with its own samples, whose results are "
                                 "averaged", low=1, high=8)
    structure_seed: int = option(0, "seed of the first anchored search's sampler (the others follow it): the "
                                 "pose depends on it by a degree or two on a real photo", low=0)
    shading_trust: float = option(0.15, "loss over its maximum up to which the shading fit is credible, but with a "
                                  "start camera and a box (there: shading_screen)", low=0.0, high=1.0)
    shading_screen: float = option(0.3, "with a start camera, where the structure can find the pose instead: the "
                                   "loss over its maximum at the shading fit's first level above which the fit "
                                   "ends there, and with a box at its end above which the edges find the pose "
                                   "(at least shading_trust; 1: every level runs, and with a box the shading's "
                                   "pose stands)",
                                   low=0.0, high=1.0)
    screen_after: int = option(100, "where the shading fit has a screen: evaluations of its first level after which "
                               "a loss over its maximum still above the screen ends the fit there (0: only at the "
                               "level's end)", low=0)
    anchored_search: bool = option(False, "with a start camera and a box, where the shading is not credible: the "
                                   "structure's anchored search in the box (docs/decisions/0012-structure-first.md) "
                                   "instead of the view-sphere search narrowed to the start refitted to the box "
                                   "(docs/decisions/0041-camera-and-box-by-the-view-sphere.md)")
    sphere_without_box: bool = option(True, "with a start camera and no box, where the shading is not credible: "
                                      "the pose found by the view-sphere search narrowed to the views near the "
                                      "start (search.sphere_spread)")
    polish_evaluations: int = option(200, "evaluations of each coarse level of the shading fit that polishes a "
                                     "pose found without a start camera", low=20, high=5000)
    shading_polish: float = option(0.45, "loss over its maximum of the edges' pose up to which the shading fit "
                                   "polishes it", low=0.0, high=1.0)
    rival_polish: bool = option(True, "without a start camera, where the polish is credible: the refined pose "
                                "at least 15 degrees away that the shading explains best is polished too, the "
                                "lower loss wins and the two losses' margin is the pose's uniqueness "
                                "(docs/decisions/0033-the-shading-judges-its-rival.md)")


@dataclass(frozen=True)
class Budgets(_Group):
    """Loss evaluations per search (``docs/decisions/0001-coarse-to-fine.md``).

    ``max_evaluations`` per level, but ``fine_evaluations`` at the working size after coarser
    levels (it starts within a pixel or two); ``focal_evaluations`` per perspective probe;
    ``spread_evaluations`` for the evolution strategy of a fit from a start camera's first level
    (0: none; ``docs/decisions/0025-spread-first-level.md``);
    ``screen_evaluations`` per screened start and ``refine_evaluations`` per refined pose of the
    search without a start camera.
    """

    max_evaluations: int = option(400, "loss evaluations per level", low=20, high=5000, public=True)
    fine_evaluations: int = option(250, "loss evaluations at the working size after coarser levels", low=1)
    focal_evaluations: int = option(150, "loss evaluations per perspective probe", low=1)
    spread_evaluations: int = option(500, "from a start camera: loss evaluations of the first level's evolution "
                                     "strategy (0: none)", low=0)
    screen_evaluations: int = option(300, "without a start camera: loss evaluations per screened start", low=1)
    refine_evaluations: int = option(1000, "without a start camera: loss evaluations per refined pose", low=1)


@dataclass(frozen=True)
class Probes(_Group):
    """Perspective probes (``docs/decisions/0005-perspective-probes.md``).

    The second level also searches from dolly zooms of the first level's pose by
    ``focal_starts`` (and, when its focal length is outside ``focal_range`` image widths, one to
    the range's geometric middle), on the same mask; a probe that ends below the main search's
    loss times ``1 + probe_margin`` is searched on. From a start camera, the first level also runs
    an evolution strategy from the start with a spread of ``start_spread`` first-level simplex
    steps (about how far a rough start is off), and its runner-up is probed at the second level
    as well (``docs/decisions/0025-spread-first-level.md``). ``dolly_pivot`` is where the view
    coordinates' focal length keeps the image size (bounding-sphere radii in front of the
    centre, ``docs/decisions/0003-view-coordinates.md``).
    """

    focal_starts: tuple[float, ...] = option((0.6, 1.7), "focal factors of the perspective probes", low=1e-3,
                                             public=True, flag="--no-focal-probes", flag_value=())
    focal_range: tuple[float, float] = option((0.7, 4.0), "focal lengths of most photos (image widths)", low=1e-3)
    dolly_pivot: float = option(0.5, "dolly zoom pivot (bounding-sphere radii in front of the centre)", low=0.0)
    probe_margin: float = option(0.1, "a probe within this share of the main search's loss is searched on", low=0.0)
    start_spread: float = option(2.0, "spread of the first level's evolution strategy (first-level simplex steps)",
                                 low=1e-3)


@dataclass(frozen=True)
class Search(_Group):
    """The search without a start camera (``docs/decisions/0007-no-hint-search.md``).

    The vehicle's region is found by GrabCut from rectangles ``region_borders`` inside the
    photo's border (the further ones only when the first region's best view scores above
    ``region_fit``); ``starts`` distinct start poses (view search, ``wheels`` pairs, and the
    best at ``start_focals`` image widths) are screened at ``screen_size`` pixels on a window of
    the box grown by ``window_margin`` (None: the whole photo); the best ``refine`` are refined
    with ``refine_optimizer``. A pose whose confidence is below ``min_confidence`` is flagged
    failed (``docs/decisions/0008-confidence.md``); when it is, a ``second_pass`` searches again
    in the foreground segmented around it. Where the shading does not explain the photo either
    (the loss over its maximum above ``photo_loss``), the ``photo_search`` finds
    the pose on the parts' colours and the edges instead: ``photo_hypotheses`` distinct views
    of the grid at ``photo_elevations`` and ``photo_focal`` image widths, ranked on
    ``photo_clusters`` colour classes (and, next to the first ``photo_neighbours`` of them,
    the best view the distinct choice set aside, ``docs/decisions/0019-colour-neighbour.md``),
    refined and verified on the edges
    (``docs/decisions/0014-photo-search.md``); its pose replaces the shading pose where the
    model's edges fit the photo's better (``docs/decisions/0015-one-footing.md``).
    """

    starts: int = option(4, "the classic chain (pose_search classic): distinct start poses screened", low=1,
                         high=12, public=True)
    refine: int = option(2, "the classic chain (pose_search classic): screened poses refined at full size", low=1,
                         high=4, public=True)
    screen_size: int = option(200, "longer side of the photo for screening (pixels)", low=16)
    window_margin: float | None = option(WINDOW_MARGIN, "window around the vehicle's box (longer sides; None: "
                                         "the whole photo)", low=0.0)
    refine_optimizer: str = option("cma-es", "optimiser of the refinement of screened poses",
                                   choices=OPTIMIZERS.names)
    second_pass: bool = option(True, "search again around a pose that is not credible")
    wheels: bool = option(True, "add start poses from matched wheel ellipses")
    start_focals: tuple[float, ...] = option((0.8, 3.0), "focal lengths (image widths) the best start is also "
                                             "screened at", low=1e-3)
    region_borders: tuple[tuple[float, float], ...] = option(
        ((0.08, 0.1), (0.18, 0.2), (0.28, 0.3)), "GrabCut rectangles of the region search (fractions of W, H "
        "inside the border)", low=0.0, high=0.49)
    region_fit: float = option(0.3, "view-search score under which the first region is kept", low=0.0)
    min_confidence: float = option(0.5, "confidence under which a pose found without a start camera fails",
                                   low=0.0)
    photo_search: bool = option(True, "the classic chain (pose_search classic): where the shading does not "
                                "explain the photo, search on the parts' colours and the edges", public=True,
                                flag="--no-photo-search")
    photo_loss: float = option(0.2, "loss over its maximum above which a pose that is not credible is searched "
                               "again by the photo search (0.2: where the confidence's fit score is 0)",
                               low=0.0, high=1.0)
    photo_hypotheses: int = option(4, "distinct hypotheses the photo search refines", low=1, high=12)
    photo_neighbours: int = option(1, "the photo search also refines the best view that the choice of distinct "
                                   "views set aside next to each of this many best hypotheses "
                                   "(docs/decisions/0019-colour-neighbour.md)", low=0, high=12)
    photo_elevations: tuple[float, ...] = option((4.0, 16.0), "elevations of the photo search's views (degrees)",
                                                 low=-30.0, high=60.0)
    photo_focal: float = option(8.0, "focal length of the photo search's views (image widths)", low=0.1)
    photo_clusters: int = option(12, "colour classes of the photo search's mutual information", low=2, high=64)
    pose_search: str = option("sphere", "the search without a start camera: the view-sphere search (sphere, "
                              "docs/decisions/0020-view-sphere-search.md) or the chain of decisions 0007-0019 "
                              "(classic: region, wheels and view grid, shading refinement, photo search), kept to "
                              "compare against", choices=("sphere", "classic"), public=True)
    sphere_spread: float = option(30.0, "with a start camera: degrees from its rotation of the views searched",
                                  low=1.0, high=180.0)
    sphere_scales: tuple[float, float] = option((0.8, 2.0), "scales of the placed templates, factors of the one "
                                                "that fits a template's box to the target's", low=0.05, high=20.0)
    sphere_iou: float = option(0.6, "least IoU of a placed template's projection (cut to the frame) with its "
                               "target box", low=0.0, high=1.0)
    sphere_size: int = option(240, "longer side of the photo for the view-sphere search (pixels)", low=32)
    sphere_votes: tuple[int, ...] = option((200, 320), "other sizes (pixels) at which the view-sphere search "
                                           "runs again, in turn, about its pose's target where the shading does "
                                           "not explain its pose: the sizes vote on the pose, and one they do not "
                                           "all agree on fails (docs/decisions/0036-sizes-vote.md)", low=32)
    sphere_stride: int = option(1, "positions of the templates tried first every this many steps (4 % of the "
                                "template's size), then about the best one step either way", low=1, high=8)
    sphere_rank: int = option(64, "placed templates of each target ranked on the two-way chamfer", low=1,
                              high=2000)
    sphere_apart: float = option(20.0, "degrees apart of the ranked poses refined", low=0.0, high=180.0)
    sphere_refine: int = option(2, "ranked poses of each target refined", low=1, high=16)
    sphere_twin: bool = option(True, "without a start camera, where the edges decide: each search's best pose "
                               "weighed against its half-turn twin, refined as its poses were (decision 0037)")
    sphere_hold: int = option(100, "evaluations of each refinement's first stage, its rotation held", low=0)
    sphere_start_region: bool = option(True, "with a start camera and no box, the box of the start's projection "
                                       "grown to the vehicle's region GrabCut finds about the start's silhouette "
                                       "(decision 0060)")
    sphere_frame_choice: bool = option(True, "without a hint, where the edges decide: the frame's own best pose "
                                       "(weighed against its twin) stands where it costs less than the pose "
                                       "decided on the frame and that pose's target together (decision 0063)")
    sphere_clutter: float = option(0.55, "cost of a photo edge outside a target's box but inside another "
                                   "target's, in the two-way chamfer of the targets", low=0.0, high=1.0)
    sphere_evaluations: int = option(200, "evaluations of each refinement's second stage", low=0)
    sphere_step: float = option(0.3, "first steps of the refinement, in the view coordinates' steps", low=1e-3,
                                high=10.0)
    exif_focal: bool = option(True, "without a start camera, the view-sphere search starts from the focal length "
                              "in the photo's EXIF and keeps within exif_tolerance of it", public=True,
                              flag="--no-exif-focal")
    exif_tolerance: float = option(1.0, "factor either way from the EXIF focal length that the search may reach "
                                   "(1: held at it; docs/decisions/0021-exif-focal.md)", low=1.0, high=10.0)
    exif_refine: float = option(0.0003, "weight of the EXIF focal length's prior in a last run of the shading "
                                "polish with the focal length free, per (log of the focal length over the EXIF's "
                                "/ 0.03) squared (0: no such run, the focal length held; decision 0048)",
                                low=0.0, high=1.0)


_GROUPS: dict[str, type[Any]] = {
    "pyramid": Pyramid, "segmentation": Segmentation, "terms": Terms, "structure": Structure, "budgets": Budgets,
    "probes": Probes, "search": Search,
}


@dataclass(frozen=True)
class RegistrationOptions(_Group):
    """How to register; the defaults are the paper's method with the measured changes of
    ``docs/decisions/``.

    ``loss`` is a name of :data:`~vehicle_pose.registry.LOSSES` (``invariant-parts``: one
    unknown response per material kind, ``docs/decisions/0002-parts-loss.md``), ``optimizer``
    of :data:`~vehicle_pose.registry.OPTIMIZERS`, ``parametrization`` of
    :data:`~vehicle_pose.registry.PARAMETRIZATIONS` (``docs/decisions/0003-view-coordinates.md``);
    ``side`` is the visible side (``auto``: from the start pose); ``color`` scores the three
    colour channels instead of the luminance. The groups are documented on their classes.

    Every field is checked when the options are made: ValueError names the field and why.
    """

    loss: str = option("invariant-parts", "loss to minimise", choices=LOSSES.names, public=True)
    optimizer: str = option("nelder-mead", "optimiser", choices=OPTIMIZERS.names, public=True)
    parametrization: str = option("view", "search coordinates: a view perturbation or the paper's theta",
                                  choices=PARAMETRIZATIONS.names, public=True)
    side: str = option("auto", "visible side", choices=SIDES, public=True)
    color: bool = option(False, "score the three colour channels (n = 3)", public=True)
    pyramid: Pyramid = field(default_factory=Pyramid)
    segmentation: Segmentation = field(default_factory=Segmentation)
    terms: Terms = field(default_factory=Terms)
    structure: Structure = field(default_factory=Structure)
    budgets: Budgets = field(default_factory=Budgets)
    probes: Probes = field(default_factory=Probes)
    search: Search = field(default_factory=Search)

    @classmethod
    def specs(cls) -> Iterator[tuple[str, dataclasses.Field[Any], OptionSpec]]:
        """Every option as ``(flat name, field, spec)``: the top-level ones, then each group's."""
        for f in dataclasses.fields(cls):
            if "spec" in f.metadata:
                yield f.name, f, f.metadata["spec"]
        for group in _GROUPS.values():
            for f in dataclasses.fields(group):
                yield f.name, f, f.metadata["spec"]

    @classmethod
    def from_flat(cls, values: Mapping[str, Any] | None = None, /, **more: Any) -> RegistrationOptions:
        """Options from flat names (``max_size=320``) put into their groups; ValueError for an
        unknown name (the CLI, the API and the benchmarks speak flat names)."""
        return cls().replace(**{**(values or {}), **more})

    def replace(self, **values: Any) -> RegistrationOptions:
        """A copy with the options named by flat names changed (and checked)."""
        where = {name: group for group, kind in _GROUPS.items() for name in (f.name for f in dataclasses.fields(kind))}
        top: dict[str, Any] = {}
        groups: dict[str, dict[str, Any]] = {}
        for name, value in values.items():
            value = _tupled(value)
            if name in where:
                groups.setdefault(where[name], {})[name] = value
            elif name in {f.name for f in dataclasses.fields(self)} and name not in _GROUPS:
                top[name] = value
            else:
                raise ValueError(f"unknown option {name!r}")
        for group, changed in groups.items():
            top[group] = dataclasses.replace(getattr(self, group), **changed)
        return dataclasses.replace(self, **top)

    def flat(self) -> dict[str, Any]:
        """Every option by its flat name (the result JSON's ``options``)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in _GROUPS}
        for group in _GROUPS:
            out |= dataclasses.asdict(getattr(self, group))
        return out
