"""View agreement: do the views agree with each other, and does the final model explain them?

A lab user has no reference volume for a real specimen, so a run must say when
its views disagree with each other.  The final mesh is projected through each
view's camera and compared with that view's silhouette (its sub-pixel coverage
at 0.5): the intersection over union, the silhouette pixels the model leaves
unexplained and the model pixels outside the silhouette.

A visual hull lies inside every silhouette, so views that disagree (a wrong
angle label, a specimen or board moved between stops, a bad threshold, the
same image repeated) show up as silhouette pixels the model does not explain.
That is measured on the surface the views carved (``hull_mesh``, the
marching-cubes surface before smoothing and remeshing, which round off edges a
few views leave sharp: resolution, not disagreement).  Pixels within
``tolerance_px`` of the silhouette's outline (a voxel's projected size, at
least 1 px) are a matter of resolution and are not counted; the rest is the
view's ``disagreement_px``, and over the outline's length it is a width,
``disagreement_width_px``: a view is flagged when it exceeds
:data:`AGREEMENT_LIMIT` px.  A limit on the width scales with the image (an
outline error of a pixel costs a fixed width whatever the silhouette's area);
issue 15's limit, 0.3 % of the area on the finished surface, flagged 3 of the 4
views of a correct 320 x 240 simulated capture at 2 mm.

Measured (issue 25; largest over the views): the docs' simulated capture
(320 x 240, 4 views) 0 px correct at 1 and 2 mm, 0.078 / 0.093 px with a view
15 degrees off; the sample session (640 x 480, 36 views) 0.037 / 0.032 px
correct at 1 / 2 mm, 0.218 / 0.098 px with view 050 labelled 40 degrees (at
2 mm every other view <= 0.041 px).  The limit 0.05 lies 1.35x above the
correct sample at 1 mm and 1.6x below the mislabelled simulated capture.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from .camera import Camera
from .carving import hull_field
from .grid import VoxelGrid
from .masks import Silhouette, as_arrays
from .mesh import Mesh
from .raster import MeshRaster, model_mask
from .surface import mesh_from_field

__all__ = ["AGREEMENT_LIMIT", "MANY_FLAGGED", "ViewAgreement", "hull_masks", "likely_causes", "model_mask",
           "suggest_angles", "view_agreement", "worst_views"]

#: Largest accepted silhouette area left unexplained beyond the outline tolerance, as a width
#: in pixels along the silhouette's outline (``disagreement_px / outline_px``): a limit that
#: scales with the outline, i.e. with what a pixel is there (module docstring: measured figures).
AGREEMENT_LIMIT = 0.05

#: The outline tolerance: at least this many pixels, at least a voxel's projected size.
_MIN_TOLERANCE_PX = 1.0

#: More than this fraction of views over the limit points at the whole set of views.
_MANY = 0.5

#: Threads over the views in :func:`view_agreement` (the machine the targets are set on has 2 cores).
_THREADS = 2

#: Public name of the same fraction (the engine asks for angle suggestions only below it).
MANY_FLAGGED = _MANY


@dataclass
class ViewAgreement:
    """Agreement of a model with every view.

    Attributes
    ----------
    views : list of dict
        One per view: ``iou``, ``silhouette_px``, ``model_px``,
        ``unexplained_silhouette_px`` (silhouette pixels outside the model's
        projection), ``unexplained_model_px`` (model pixels outside the
        silhouette), ``tolerance_px``, ``outline_px``, ``disagreement_px``
        (silhouette pixels the carved surface leaves unexplained beyond the
        tolerance), ``disagreement_width_px`` (the same over ``outline_px``),
        ``disagreement`` (the same as a fraction of the silhouette), ``ok``;
        ``raw_iou`` (the IoU of ``hull_mesh``) when it was given.
    worst : list of int
        View indices, worst first (:func:`worst_views`).
    warnings : list of str
        One line per problem, with the likely causes.
    limit : float, px of outline width
    """

    views: list
    worst: list
    warnings: list = field(default_factory=list)
    limit: float = AGREEMENT_LIMIT


def _one_view(model, sil, tol, hull=None):
    """The view's row; ``disagreement`` from ``hull`` (the views' own carving) when given, else from ``model``."""
    sil_px = int(np.count_nonzero(sil))
    miss = sil & ~model
    extra = model & ~sil
    # the distance and the erosion within the silhouette's box and a ring of one pixel (background,
    # clipped at the image's edge): the nearest background pixel of a silhouette pixel lies in it,
    # so the values are those of the whole image (about a quarter of it on the sample)
    box = _box(sil)
    s, h = sil[box], (model if hull is None else hull)[box]
    far = s & ~h
    far_miss = int(np.count_nonzero(_distance_to_background(s, far) > tol))
    outline_px = int(np.count_nonzero(s & ~_erode(s)))
    row = {
        "iou": _iou(model, sil),
        "silhouette_px": sil_px,
        "outline_px": outline_px,
        "model_px": int(np.count_nonzero(model)),
        "unexplained_silhouette_px": int(np.count_nonzero(miss)),
        "unexplained_model_px": int(np.count_nonzero(extra)),
        "tolerance_px": round(float(tol), 3),
        "disagreement_px": far_miss,
        "disagreement": far_miss / sil_px if sil_px else 0.0,
        "disagreement_width_px": far_miss / outline_px if outline_px else 0.0,
    }
    if hull is not None:  # the raw surface's IoU: what finishing changed in this view
        row["raw_iou"] = _iou(hull, sil)
    return row


#: Largest squared diagonal (px^2) of a box whose squared distances OpenCV's float32 distances give exactly:
#: there ``rint(d ** 2)`` recovers the integer d^2 (relative error of d^2 under 2^-23, so under 0.5).
_CV_EXACT_D2 = 2**22


def _distance_to_background(s, where):
    """``scipy.ndimage.distance_transform_edt(s)[where]``, the same float64 values.

    OpenCV's exact Euclidean transform (``DIST_MASK_PRECISE``; float32 square roots of the
    integer squared distances) at a third of scipy's CPU: its squared distances, rounded back to
    the integers they are, then ``sqrt`` in float64 as scipy takes it.  Larger boxes (whose
    float32 could round a squared distance), or a box with no background: scipy.
    """
    import cv2

    hh, ww = s.shape
    if hh * hh + ww * ww >= _CV_EXACT_D2 or s.all():
        from scipy import ndimage

        return ndimage.distance_transform_edt(s)[where]
    d = cv2.distanceTransform(s.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[where]
    return np.sqrt(np.rint(np.square(d, dtype=np.float64)))


def _erode(s):
    """``scipy.ndimage.binary_erosion(s)`` (the cross of 4 neighbours; outside the image is background)."""
    import cv2

    cross = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=np.uint8)
    return cv2.erode(s.view(np.uint8), cross, borderType=cv2.BORDER_CONSTANT, borderValue=0).view(bool)


def _box(mask):
    """Slices of ``mask``'s box of True pixels grown by one pixel (within the image); the whole image if none."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return np.s_[:, :]
    h, w = mask.shape
    return np.s_[max(rows[0] - 1, 0) : min(rows[-1] + 2, h), max(cols[0] - 1, 0) : min(cols[-1] + 2, w)]


def view_agreement(mesh: Mesh, cameras: Sequence[Camera], silhouettes: Sequence[Silhouette | np.ndarray], *,
                   voxel_size: float, names: Sequence[str] | None = None, limit: float = AGREEMENT_LIMIT,
                   hull_mesh: Mesh | None = None, turntable: Sequence[bool] | None = None,
                   hull_masks: Sequence[np.ndarray] | None = None) -> ViewAgreement:
    """How well a model's projection matches every view's silhouette.

    Parameters
    ----------
    mesh : organlab.surface.Mesh
        The final model, world frame, mm.
    cameras : sequence of Camera
        One per view.
    silhouettes : sequence of organlab.silhouette.Silhouette, or of (H, W) arrays
        One per view; compared at ``coverage >= 0.5`` (a bool mask as it is).
    voxel_size : float, mm
        Resolution of the model: the outline tolerance is at least a voxel's
        projected size.
    names : sequence of str, optional
        View names for the warnings (default ``views[i]``).
    limit : float
        Largest accepted ``disagreement`` (fraction of the silhouette).
    hull_mesh : organlab.surface.Mesh, optional
        The surface the views carved, before any finishing (the run's
        marching-cubes mesh).  When given, ``disagreement`` (do the views
        contradict each other?) is measured on it, and ``iou`` and the
        ``unexplained_*`` counts on ``mesh``: smoothing and remeshing round
        off edges a few views leave sharp, which is resolution, not views
        that disagree.
    turntable : sequence of bool, optional
        Per view, whether its pose comes from a turntable calibration and its
        table angle (default: all True).  The warnings' likely causes follow:
        angles and the table for those views, the camera file for given poses.
    hull_masks : sequence of (H, W) bool, optional
        ``hull_mesh`` seen by each camera, when already made by :func:`hull_masks`
        with the same mesh, cameras and silhouettes (the engine makes them while
        the surface is finished); ``hull_mesh`` must be given too.

    Returns
    -------
    ViewAgreement

    Examples
    --------
    >>> import tempfile
    >>> import organlab as ol
    >>> from organlab.synthetic import with_true_cameras
    >>> s = ol.load_session(with_true_cameras("sample_sessions/aaa_phantom", tempfile.mkdtemp() + "/aaa", step=6))
    >>> from organlab.agreement import view_agreement
    >>> cal, _ = ol.calibration_for(s)
    >>> cameras, grid, sils = cal.cameras(s), ol.VoxelGrid.from_session(s, voxel_size=4.0), ol.silhouettes(s)
    >>> mesh = ol.mesh_from_field(ol.hull_field(sils, cameras, grid, sparse=True), grid)
    >>> a = view_agreement(mesh, cameras, sils, voxel_size=4.0)
    >>> all(v["ok"] for v in a.views), a.warnings, round(float(min(v["iou"] for v in a.views)), 3)
    (True, [], 0.985)
    """
    if len(cameras) != len(silhouettes):
        raise ValueError(f"got {len(cameras)} cameras for {len(silhouettes)} silhouettes")
    if not (np.isfinite(limit) and limit >= 0):
        raise ValueError(f"limit must be a finite width >= 0 (px of outline), got {limit}")
    names = list(names) if names is not None else [f"views[{i}]" for i in range(len(cameras))]
    if hull_masks is not None:
        if hull_mesh is None:
            raise ValueError("hull_masks are hull_mesh's projections: give hull_mesh too")
        if len(hull_masks) != len(cameras):
            raise ValueError(f"got {len(hull_masks)} hull_masks for {len(cameras)} cameras")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    centre = verts.mean(axis=0) if len(verts) else np.zeros(3)
    model_raster = MeshRaster(mesh.vertices, mesh.faces)
    hull_raster = None if hull_mesh is None or hull_masks is not None else MeshRaster(hull_mesh.vertices,
                                                                                      hull_mesh.faces)

    def one(cam, s, given):
        sil = np.asarray(as_arrays([s], "coverage")[0]) >= 0.5
        depth = float(cam.world_to_camera(centre[None])[0, 2])
        px_per_mm = cam.K[0, 0] / depth if depth > 0 else 0.0
        tol = max(_MIN_TOLERANCE_PX, voxel_size * px_per_mm)
        if given is not None and np.shape(given) != sil.shape:
            raise ValueError(f"a hull mask of shape {np.shape(given)} for a silhouette of shape {sil.shape}")
        hull = given if given is not None else None if hull_raster is None else hull_raster.mask(cam, sil.shape)
        v = _one_view(model_raster.mask(cam, sil.shape), sil, tol, hull)
        v["ok"] = bool(v["disagreement_width_px"] <= limit)
        return v

    # the views on two threads: the raster kernels, OpenCV and numpy's reductions release the GIL
    given = [None] * len(cameras) if hull_masks is None else list(hull_masks)
    with ThreadPoolExecutor(max_workers=_THREADS) as pool:
        views = list(pool.map(one, cameras, silhouettes, given))
    turntable = [True] * len(views) if turntable is None else [bool(t) for t in turntable]
    return ViewAgreement(views, worst_views(views), _warnings(views, names, limit, turntable), limit)


def hull_masks(hull_mesh: Mesh, cameras: Sequence[Camera], silhouettes: Sequence[Silhouette | np.ndarray]) -> list:
    """``hull_mesh`` seen by each camera, the masks :func:`view_agreement` compares with the silhouettes.

    Made ahead, they are :func:`view_agreement`'s ``hull_masks`` (the engine makes them on a second
    thread while the surface is finished: the carved surface has 6x the finished one's faces at
    0.25 mm, and these masks were half of the agreement's CPU there).

    Parameters
    ----------
    hull_mesh : organlab.surface.Mesh
        The carved surface, world frame, mm.
    cameras : sequence of Camera
        One per view.
    silhouettes : sequence of organlab.silhouette.Silhouette, or of (H, W) arrays
        One per view: the shape of each mask.

    Returns
    -------
    list of (H, W) bool
        Pixels whose centre sees ``hull_mesh`` (:func:`organlab.raster.model_mask`), one per view.

    Examples
    --------
    >>> import numpy as np
    >>> from organlab.camera import Camera
    >>> from organlab.mesh import Mesh
    >>> cam = Camera(np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]]), np.zeros(5),
    ...              np.eye(3), np.array([0.0, 0.0, 100.0]), image_size=(64, 48))
    >>> square = Mesh(np.array([[-5.0, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]]), np.array([[0, 1, 2], [0, 2, 3]]))
    >>> [int(m.sum()) for m in hull_masks(square, [cam], [np.zeros((48, 64), bool)])]
    [121]
    """
    if len(cameras) != len(silhouettes):
        raise ValueError(f"got {len(cameras)} cameras for {len(silhouettes)} silhouettes")
    raster = MeshRaster(hull_mesh.vertices, hull_mesh.faces)
    return [raster.mask(cam, np.shape(as_arrays([s], "coverage")[0])) for cam, s in zip(cameras, silhouettes)]


def worst_views(views: Sequence[dict]) -> list[int]:
    """View indices, worst first: the one ranking the report, the CLI and the viewer use.

    Parameters
    ----------
    views : sequence of dict
        ``ViewAgreement.views`` (or ``report.json``'s ``views[i].agreement``).

    Returns
    -------
    list of int
        By ``disagreement_width_px`` (``disagreement`` in reports without it; largest first), ties by
        ``iou`` (smallest first), then index.
    """
    key = lambda i: (-views[i].get("disagreement_width_px", views[i]["disagreement"]), views[i]["iou"], i)  # noqa: E731
    return sorted(range(len(views)), key=key)


def _warnings(views, names, limit, turntable):
    bad = [i for i, v in enumerate(views) if not v["ok"]]
    if not bad:
        return []
    bad.sort(key=lambda i: -views[i]["disagreement_width_px"])
    listed = ", ".join(f"{names[i]} {views[i]['disagreement_px']} px ({100 * views[i]['disagreement']:.2f} %)"
                       for i in bad[:5])
    more = f" and {len(bad) - 5} more" if len(bad) > 5 else ""
    head = (f"{len(bad)} of {len(views)} views disagree with the model (silhouette unexplained beyond a voxel "
            f"of the outline, more than {limit:g} px of outline width): {listed}{more}")
    return [f"{head}; {likely_causes(len(bad) > _MANY * len(views), any(turntable[i] for i in bad))}"]


def likely_causes(many: bool, turntable: bool) -> str:
    """The causes a warning names, fitted to the session.

    Parameters
    ----------
    many : bool
        More than half the views disagree (the whole set is suspect).
    turntable : bool
        The flagged views' poses come from a turntable calibration and their
        table angles; otherwise they were given (``views[i].pose``, e.g. from
        ``organlab init --cameras``).

    Returns
    -------
    str
    """
    if turntable and many:
        return ("likely causes: the views do not belong together (the same image repeated, a wrong angle step or "
                "direction), a wrong turntable calibration (board moved), or a bad silhouette threshold")
    if turntable:
        return ("likely causes: a wrong angle label for these views, the specimen or the board moved at these "
                "stops, or a bad silhouette threshold in these images")
    if many:
        return ("likely causes: bad silhouettes (threshold, shadows, a stand, the specimen leaving the frame), or "
                "cameras that do not belong to these images (another camera file, names matched to the wrong images, "
                "translations in other units)")
    return ("likely causes: a wrong pose for these views in the camera file, the specimen moved between these "
            "photos, or a bad silhouette in these images (threshold, shadows, the specimen leaving the frame)")


def suggest_angles(table_camera: Camera, angles_deg: Sequence[float], silhouettes: Sequence[Silhouette | np.ndarray],
                   flagged: Sequence[int], grid: VoxelGrid, *, names: Sequence[str] | None = None,
                   search_deg: float = 20.0, step_deg: float = 0.5, gain: float = 0.005,
                   min_iou: float = 0.95) -> list[dict]:
    """For views flagged by :func:`view_agreement`: the table angle at which each agrees best.

    A wrong angle label is the first likely cause of a flagged view.  The
    hull of the views that are not flagged (the sub-voxel hull field, meshed)
    is projected through the table camera at angles around the label; the
    angle whose projection matches the flagged view's silhouette best (IoU)
    is suggested when it beats the label by more than ``gain`` and no other
    angle more than 2 degrees away comes within ``gain / 2`` of it (a nearly
    rotation-symmetric specimen matches many angles: nothing is suggested).

    Parameters
    ----------
    table_camera : Camera
        The camera at table angle 0 (``TurntableCalibration.camera``).
    angles_deg : sequence of float
        Every view's labelled table angle, degrees.
    silhouettes : sequence of Silhouette or (H, W) arrays
        One per view (compared at ``coverage >= 0.5``).
    flagged : sequence of int
        The views to look at (e.g. those whose ``ok`` is False).
    grid : VoxelGrid
        Where to carve the other views' hull (the run's grid).
    names : sequence of str, optional
    search_deg, step_deg : float, degrees
        Angles tried: label +- ``search_deg`` in steps of ``step_deg``.
    gain : float
        Smallest IoU gain over the label worth a suggestion.
    min_iou : float
        Smallest IoU at the suggested angle: a hull of the other views that
        explains the view this poorly even at its best angle (a few views
        leave a fat hull, which holds the mislabelled view itself) does not
        say which view is wrong.  Measured: the sample's view 050 labelled 40
        degrees 0.985 at its best angle; the docs' 4-view simulated capture
        with view 090 labelled 105, its opposite view 270 0.857 at 289 degrees
        (a wrong suggestion, now withheld).

    Returns
    -------
    dict of str -> dict
        Per flagged view (by name): ``labelled``, ``best`` (degrees or None),
        ``iou_labelled``, ``iou_best``.
    """
    n = len(silhouettes)
    if len(angles_deg) != n:
        raise ValueError(f"got {len(angles_deg)} angles for {n} silhouettes")
    names = list(names) if names is not None else [f"views[{i}]" for i in range(n)]
    flagged = sorted({int(i) for i in flagged})
    others = [i for i in range(n) if i not in flagged]
    if not flagged or len(others) < 3:
        return {}
    cov = as_arrays(silhouettes, "coverage")
    cams = [table_camera.at_table_angle(angles_deg[i]) for i in others]
    mesh = mesh_from_field(hull_field([cov[i] for i in others], cams, grid, sparse=True), grid)
    out = {}
    for i in flagged:
        sil = np.asarray(cov[i]) >= 0.5
        tried = angles_deg[i] + np.arange(-search_deg, search_deg + step_deg / 2, step_deg)
        iou = np.array([_iou(model_mask(mesh, table_camera.at_table_angle(a), sil.shape), sil) for a in tried])
        k, at_label = int(np.argmax(iou)), int(np.argmin(np.abs(tried - angles_deg[i])))
        rivals = np.abs(tried - tried[k]) > 2.0
        clear = (iou[k] - iou[at_label] > gain and iou[k] >= min_iou
                 and not (rivals & (iou > iou[k] - gain / 2)).any())
        out[names[i]] = {"labelled": float(angles_deg[i]), "best": float(tried[k]) if clear else None,
                         "iou_labelled": float(iou[at_label]), "iou_best": float(iou[k])}
    return out


def _iou(a, b):
    union = np.count_nonzero(a | b)
    return np.count_nonzero(a & b) / union if union else 1.0


def suggestion_text(suggestions):
    """One clause for a warning: the views that agree best at another angle (empty when none)."""
    parts = [f"{name} agrees best at {s['best']:g} degrees (labelled {s['labelled']:g}; IoU {s['iou_best']:.3f} "
             f"against {s['iou_labelled']:.3f})" for name, s in suggestions.items() if s["best"] is not None]
    return "; ".join(parts)
