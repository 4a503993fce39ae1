"""The registration's options (a light module: the command line reads its defaults without
importing the renderer or the optimisers)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["RegistrationOptions", "WINDOW_MARGIN", "LOSS_NAMES", "OPTIMIZER_NAMES", "PARAMETRIZATION_NAMES"]

WINDOW_MARGIN = 0.3
"""The start-pose searches look at the vehicle's box grown by this fraction of its longer side."""

LOSS_NAMES: tuple[str, ...] = (
    "invariant", "invariant-paper", "invariant-parts", "correlation", "squared", "silhouette-iou",
    "mutual-information",
)
"""Names of :data:`vehicle_pose.loss.registry.LOSSES` (tests/test_loss.py checks they agree)."""
OPTIMIZER_NAMES: tuple[str, ...] = ("nelder-mead", "powell", "cma-es")
"""Names of :data:`vehicle_pose.search.optimize.OPTIMIZERS`."""
PARAMETRIZATION_NAMES: tuple[str, ...] = ("theta", "view")
"""Names of :data:`vehicle_pose.geometry.parametrize.PARAMETRIZATIONS`."""


@dataclass(frozen=True)
class RegistrationOptions:
    """How to register; the defaults are the paper's method plus coarse-to-fine.

    Attributes
    ----------
    loss : str
        A name from :data:`vehicle_pose.loss.registry.LOSSES`. The default, ``invariant-parts``, is the
        invariant loss with one indicator channel per material kind of the model (body, glass,
        tyre, wheel, light), so each material gets its own unknown response (method.md §2); on
        a model without material groups it equals ``invariant``. Measured against
        ``invariant`` it registered 65 % of the photoreal cases instead of 55 %
        (docs/benchmarks.md).
    optimizer : str
        A name from :data:`vehicle_pose.search.optimize.OPTIMIZERS`.
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
        ``min_faces``); a triangle of a few pixels changes the loss no more than pixel
        quantisation does, and :meth:`VehicleModel.lod` keeps each level's outline.
    min_faces : int
        Smallest face budget of a level.
    max_pixels : int
        When positive, the finest level is reduced until the start silhouette covers at most
        this many pixels: an evaluation costs in proportion to the silhouette's area. Off by
        default: at 40000 the photoreal cases registered as well and faster, but the
        synthetic sub-pixel cases ended 1.6 px off instead of below 1 px.
    grabcut : bool
        Remove the background with GrabCut seeded by the start pose.
    grabcut_margin : float
        GrabCut seed margin, fraction of the start silhouette's diagonal.
    box_margin : float
        With a start camera and a box, GrabCut may also claim the box grown by this fraction
        of its diagonal: a rough start pose often leaves part of the vehicle outside its
        grown silhouette, and GrabCut would call that part certain background.
    fit_start_to_box : bool
        With a start camera and a box, first move and scale the start (rotation and focal
        length kept) so that the model's projection, cut to the photo, fills the box.
    box_weight : float
        With a start camera and a box, the loss is raised by this times how far the model's
        projection goes beyond the box grown by ``box_tolerance`` of its size, or falls short
        of it by more than ``box_shortfall`` (:func:`~vehicle_pose.search.views.box_overflow`;
        going beyond a side on the photo's border is free).
    box_tolerance : float
        How far, as a fraction of the box's size, the projection may pass the box free of cost
        (an annotated box is loose by a few pixels, a CAD model not exactly the car).
    box_shortfall : float or None
        The box term also counts how far a side of the projection falls short of the box's by
        more than this fraction of its size (None: not at all): a model that fills less of the
        box than that has shrunk inside the vehicle, onto a panel or the beltline. Loose boxes
        stay free: the tolerance is three times ``box_tolerance``.
    edge_weight : float
        With a start camera, the loss is raised by this times the directional chamfer cost of
        the rendered model's edges against the photo's edges near the foreground
        (:class:`~vehicle_pose.loss.edges.EdgeLoss`, in [0, 1]): outline, window frames and lights
        hold the model where reflections in the paint and glass leave the invariant loss
        blind. 0 leaves the loss alone.
    edge_crease : float
        Change of a camera-space normal component between neighbouring pixels that makes a
        model edge of the edge term (0.6: a crease of about 35 degrees).
    resegment : bool
        Run GrabCut again after each coarse level, seeded by that level's pose with
        ``resegment_margin`` and its shrunk silhouette as certain foreground: a better pose
        seeds a better mask.
    resegment_margin : float
    resegment_iterations : int
        GrabCut iterations of a resegmentation (the first segmentation runs 4): seeded by a
        pose within a few pixels and with a certain-foreground core, two iterations registered
        the photoreal cases as well as four (100 %, median 0.77 px against 0.75) and took 0.15 s
        less per photo (docs/benchmarks.md).
    color : bool
        Score colour photos with n = 3 channels; by default the photo's luminance is scored
        (n = 1, the paper's setting); docs/benchmarks.md compares the two.
    max_evaluations : int
        Loss evaluations allowed per level (but the finest, see ``fine_evaluations``).
    fine_evaluations : int
        Loss evaluations allowed at the finest level when coarser levels ran before it, and at
        the final level of a registration without a start camera: it starts within a pixel or
        two and polishes. On the photoreal cases 150 registered as well as 400; on the
        synthetic sub-pixel cases the error still falls with more (one case: 1.03 px at 150,
        0.57 at 250, 0.47 at 400), hence 250.
    side : str
        ``"auto"`` (from the start pose), ``"left"`` or ``"right"``: the visible side.
    parametrization : str
        Search coordinates: ``"view"`` (default) or ``"theta"`` (the paper's), see
        :mod:`vehicle_pose.geometry.parametrize`; the paper's theta succeeded on 50 % of the photoreal
        cases even with the true mask, the view coordinates on 85 % (docs/benchmarks.md).
    starts : int
        Without a start camera: how many distinct start poses (view search and wheel pairs)
        are screened on a reduced photo.
    refine : int
        How many of the best distinct screened poses are refined at full size.
    screen_size : int
        Longer side of the photo for screening (one level).
    screen_evaluations : int
        Loss evaluations allowed per screened start.
    window_margin : float or None
        The view search, the screening and the refinement of the screened poses look at a
        window of the photo: the vehicle's box grown by this fraction of its longer side on
        every side, reduced to their sizes, so a small vehicle is seen at the resolution of a
        large one (:class:`~vehicle_pose.geometry.window.Window`). None: the whole photo.
    refine_optimizer : str
        A name from :data:`vehicle_pose.search.optimize.OPTIMIZERS`: the optimiser of the refinement
        of the screened poses (no start camera). CMA-ES, because near-frontal and near-rear views
        with a short lens leave a simplex stuck in a narrow valley (docs/engine.md).
    refine_evaluations : int
        Loss evaluations allowed per refined screened pose.
    second_pass : bool
        When the pose found without a start camera is not credible, search again with the
        foreground segmented around it as the vehicle's region, and keep the lower loss. On
        the photoreal cases it raised no-hint success from 75 to 90 % (docs/benchmarks.md).
    wheels : bool
        Add start poses from matched wheel ellipses to those of the view search.
    start_focals : tuple of float
        Focal lengths (image widths) at which the best start is screened again besides its
        own, refitted to the region: the view search assumes 1.5 W, photos range from a strong
        perspective (0.8 W) to a long lens.
    region_borders : tuple of (float, float)
        With no hint at all, the vehicle's region is found by GrabCut from a rectangle this far
        (fractions of width and height) inside the photo's border, once per entry; the region
        whose best search view fits it best is used. The further rectangles are tried only
        when the first region's best view scores above ``region_fit``. (Dropping a narrower
        region that reaches its rectangle, as cut, lost 3 of 20 photoreal cases.)
    region_fit : float
        View-search score (1 - IoU + loss / max) under which the first region is kept as it is.
    min_confidence : float
        A pose found without a start camera whose confidence is lower is flagged ``failed``.
    focal_starts : tuple of float
        The second coarse-to-fine level searches from the first level's pose and from its
        dolly zooms by these factors (the same centre, size and orientation in the
        image, the focal length times the factor) on the same mask, ``focal_evaluations``
        evaluations each; a probe that ends lower than the main search is searched on. A rough
        start's perspective is what the simplex corrects least (docs/engine.md). Empty: the
        paper's single search.
    focal_evaluations : int
    focal_range : (float, float)
        Focal lengths (image widths) of most photos: when the first level ends outside this
        range (the paper's start has f = 10 W), the probes also include a dolly zoom to its
        geometric middle (about 1.7 W). From the photoreal cases' hard starts (f = 10 W,
        15-30 degrees off) it raised success from 10 % to 50 % (docs/benchmarks.md).
    dolly_pivot : float
        The view coordinates' focal length moves the camera along its line of sight so that
        the image size stays put at this many bounding-sphere radii in front of the model's
        centre (:class:`~vehicle_pose.geometry.parametrize.ViewParams`), about where the visible
        outline lies. Pivoting at the centre (0) couples focal length and size: on synthetic
        starts with 1.7-1.8 times the true focal length, 4 of 8 ended more than 1 px off
        (the simplex crawls along the diagonal valley); at 0.5 none did (docs/engine.md).
    probe_margin : float
        A probe is searched on when it ends below the main search's loss times
        ``1 + probe_margin``: a probe stops after ``focal_evaluations``, short of where it would
        settle, so a probe that nearly ties the main search is often in the better basin.
    """

    loss: str = "invariant-parts"
    optimizer: str = "nelder-mead"
    coarse_to_fine: bool = True
    max_size: int = 800
    coarse_sizes: tuple[int, ...] = (160, 320)
    faces_per_pixel: float = 0.5
    min_faces: int = 8192
    grabcut: bool = True
    grabcut_margin: float = 0.12
    box_margin: float = 0.04
    fit_start_to_box: bool = True
    box_weight: float = 1.0
    box_tolerance: float = 0.05
    box_shortfall: float | None = 0.15
    edge_weight: float = 0.5
    edge_crease: float = 0.6
    resegment: bool = True
    resegment_margin: float = 0.08
    resegment_iterations: int = 2
    color: bool = False
    max_evaluations: int = 400
    max_pixels: int = 0
    side: str = "auto"
    parametrization: str = "view"
    starts: int = 4
    refine: int = 2
    screen_size: int = 200
    screen_evaluations: int = 300
    window_margin: float | None = WINDOW_MARGIN
    refine_optimizer: str = "cma-es"
    refine_evaluations: int = 1000
    second_pass: bool = True
    wheels: bool = True
    start_focals: tuple[float, ...] = (0.8, 3.0)
    region_borders: tuple[tuple[float, float], ...] = ((0.08, 0.1), (0.18, 0.2), (0.28, 0.3))
    region_fit: float = 0.3
    min_confidence: float = 0.5
    focal_starts: tuple[float, ...] = (0.6, 1.7)
    focal_evaluations: int = 150
    focal_range: tuple[float, float] = (0.7, 4.0)
    fine_evaluations: int = 250
    dolly_pivot: float = 0.5
    probe_margin: float = 0.1
