"""Pictures of results: an off-screen rendering of a mesh (pyvista, EGL), calibration check figures.

pyvista is imported inside the function, so ``import organlab`` stays fast.
Off-screen rendering goes through EGL: no X server is needed.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .errors import OrganlabError

__all__ = ["mesh_snapshot", "aaa_picture", "check_figures", "agreement_chart", "agreement_overlay"]


def mesh_snapshot(mesh, path, *, window_size=(800, 600), title=None, elevation_deg=20.0, azimuth_deg=-60.0):
    """Render a mesh off-screen to a PNG.

    Parameters
    ----------
    mesh : organlab.surface.Mesh
        World frame, mm (Z up).
    path : str or Path
        PNG to write.
    window_size : (2,) int
        ``(width, height)`` px.
    title : str, optional
        Text drawn in the upper-left corner.
    elevation_deg, azimuth_deg : float
        Viewing direction, degrees (azimuth from +X about +Z, elevation above
        the XY plane).

    Returns
    -------
    Path
    """
    p, poly = _plotter(mesh, window_size)
    if mesh.vertex_colors is not None:
        poly.point_data["rgb"] = np.asarray(mesh.vertex_colors, dtype=np.uint8)
        p.add_mesh(poly, scalars="rgb", rgb=True, smooth_shading=True)
    else:
        p.add_mesh(poly, color="#d98c7a", smooth_shading=True, specular=0.2)
    p.show_grid(xtitle="x (mm)", ytitle="y (mm)", ztitle="z (mm)", font_size=8)
    if title:  # a line of its own above the scene, 10 px from the top and left edges
        p.add_text(title, position=(10, window_size[1] - 28), font_size=10, color="black")
    # the grid's tick labels and titles lie outside the mesh's bounds: 1.6 x its bounding sphere keeps them and
    # the title inside the picture (1.15 clipped the x title at the bottom and ran the top labels into the title)
    return _shoot(p, mesh, path, elevation_deg, azimuth_deg, 1.6)


def aaa_picture(mesh, measures, path, *, window_size=(900, 900)):
    """The mesh (translucent) with its centreline and the maximum-diameter section, off-screen (pyvista, EGL).

    Parameters
    ----------
    mesh : organlab.surface.Mesh
        World frame, mm.
    measures : organlab.surface.AAAMeasures
    path : str or Path
        PNG to write.
    window_size : (2,) int
        ``(width, height)`` px.

    Returns
    -------
    Path
    """
    import pyvista as pv

    p, poly = _plotter(mesh, window_size)
    p.add_mesh(poly, color="#d98c7a", opacity=0.35, smooth_shading=True)
    p.add_mesh(pv.lines_from_points(measures.centreline), color="#1f4e9c", line_width=5)
    sec = np.vstack([measures.max_section, measures.max_section[:1]])
    p.add_mesh(pv.lines_from_points(sec), color="#c0102a", line_width=6)
    p.add_mesh(pv.PolyData(measures.max_location_mm[None]), color="#c0102a", point_size=14, render_points_as_spheres=True)
    s = measures.summary()
    p.add_text(
        f"max diameter {s['max_diameter_mm']:.1f} mm (equivalent {s['max_equivalent_diameter_mm']:.1f} mm)\n"
        f"at z = {s['max_location_mm'][2]:.1f} mm, {s['max_arc_mm']:.0f} mm along the centreline\n"
        f"neck {s['neck_diameter_mm']:.1f} mm, sac {s['sac_length_mm']:.0f} mm long, {s['sac_volume_mm3'] / 1000:.1f} cm3",
        position="upper_left", font_size=11, color="black",
    )
    return _shoot(p, mesh, path, 22.0, -70.0, 1.1)


def _plotter(mesh, window_size):
    """An off-screen pyvista plotter on white, and the mesh as PolyData."""
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).ravel()
    poly = pv.PolyData(np.asarray(mesh.vertices, dtype=np.float64), faces)
    p = pv.Plotter(off_screen=True, window_size=tuple(window_size))
    p.set_background("white")
    return p, poly


def _shoot(p, mesh, path, elevation_deg, azimuth_deg, margin):
    """Aim at the mesh from a direction (degrees) and write the PNG."""
    lo, hi = mesh.bounds
    center = (lo + hi) / 2
    # far enough that the bounding sphere (times margin) fits in pyvista's 30-degree vertical view angle
    dist = margin * float(np.linalg.norm(hi - lo)) / 2 / np.tan(np.deg2rad(15.0))
    el, az = np.deg2rad(elevation_deg), np.deg2rad(azimuth_deg)
    eye = center + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    p.camera_position = [tuple(eye), tuple(center), (0, 0, 1)]
    path = Path(path)
    p.screenshot(str(path))
    p.close()
    return path


# ========================================================= calibration check figures
_GREEN = (40, 220, 40)
_RED = (255, 60, 60)
_YELLOW = (255, 220, 0)
_CYAN = (0, 220, 255)


def _pts(uv, scale):
    return [(int(round(u * scale * 16)), int(round(v * scale * 16))) for u, v in uv if np.isfinite(u) and np.isfinite(v)]


def _draw(img, detected, reprojected, scale, lines, extra=None):
    import cv2

    out = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST) if scale != 1 else img.copy()
    if out.ndim == 2:
        out = cv2.cvtColor(out, cv2.COLOR_GRAY2RGB)
    if extra is not None:
        extra(out)
    if reprojected is not None:
        for p in _pts(reprojected, scale):
            cv2.circle(out, p, 5 * 16, _RED, 1, cv2.LINE_AA, shift=4)
    if detected is not None:
        for (u, v) in _pts(detected, scale):
            cv2.drawMarker(out, (u // 16, v // 16), _GREEN, cv2.MARKER_CROSS, 9, 1, cv2.LINE_AA)
    y = 18
    for text in lines:
        (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
        cv2.rectangle(out, (4, y - th - 3), (12 + tw, y + base), (0, 0, 0), -1)
        cv2.putText(out, text, (8, y), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        y += 20
    return out


def _save(path, rgb):
    import cv2

    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OrganlabError(f"{path}: could not encode the figure")
    Path(path).write_bytes(buf.tobytes())
    return Path(path)


def _fig_name(name):
    stem = str(name).replace("\\", "/").rsplit(".", 1)[0]
    return stem.replace("/", "_") + ".png"


def check_figures(session, calibration, out_dir):
    """Draw detected (+, green) and reprojected (o, red) corners over every calibration image.

    As the thesis's Figure 1: a good calibration puts every circle on its
    cross.  Turntable images also show the table axis (yellow, from the
    board surface up) and the circle that the board's first corner sweeps as
    the table turns (cyan): every image's first corner must lie on it.

    Parameters
    ----------
    session : Session
    calibration : organlab.calibration.Calibration
        The detected corners it keeps per image are drawn as they are; an
        image without them (rejected, or an older file) is detected again.
    out_dir : str or Path
        Created when missing; one PNG per calibration image.

    Returns
    -------
    list of Path
    """
    from .calibration import Calibration, board_points
    from .errors import CalibrationError

    if not isinstance(calibration, Calibration):
        raise TypeError(f"calibration must be an organlab Calibration, got {type(calibration).__name__}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    intr, tt = calibration.intrinsics, calibration.turntable
    pattern = session.pattern
    if pattern is None and ((intr is not None and session.intrinsic_images) or tt is not None):
        raise CalibrationError(
            f"{session.json_path}: pattern is required to draw the calibration figures: "
            "{'inner_corners': [cols, rows], 'square_size': mm}"
        )
    obj = None if pattern is None else board_points(pattern)
    scale = 2 if calibration.camera.width < 1000 else 1
    paths = []
    if intr is not None:
        for pth in session.intrinsic_images:
            name = session.relpath(pth)
            img = session.read(pth, key="calibration.intrinsic_images", grey=False)
            paths.append(_save(out_dir / ("intrinsic_" + _fig_name(name)), _intrinsic_figure(img, name, intr, obj, pattern, scale)))
    if tt is not None:
        for pth, angle in session.turntable_images:
            name = session.relpath(pth)
            img = session.read(pth, key="calibration.turntable_images", grey=False)
            fig = _turntable_figure(img, name, angle, tt, obj, pattern, scale)
            paths.append(_save(out_dir / ("turntable_" + _fig_name(name)), fig))
    return paths


def _intrinsic_figure(img, name, intr, obj, pattern, scale):
    from .calibration import detect_board

    det = intr.corners.get(name)
    if det is None:
        det = detect_board(img, pattern)
    rep = None
    lines = [f"intrinsic {name}"]
    if name in intr.extrinsics:
        import cv2

        rvec, tvec = intr.extrinsics[name]
        rep = intr.camera.with_pose(cv2.Rodrigues(np.asarray(rvec, float))[0], tvec).project(obj)
        lines.append(f"RMS {intr.per_image_rms[name]:.3f} px  (all images {intr.rms_px:.3f} px)")
    if name in intr.rejected:
        lines.append(f"REJECTED: {intr.rejected[name]}")
    lines.append("+ detected   o reprojected")
    return _draw(img, det, rep, scale, lines)


def _turntable_figure(img, name, angle, tt, obj, pattern, scale):
    import cv2

    from .calibration import detect_board

    off = np.array(list(np.asarray(tt.board_offset_mm, float)) + [0.0])
    radius = float(np.hypot(*off[:2]))
    ts = np.linspace(0, 2 * np.pi, 181)
    circle = np.stack([radius * np.cos(ts), radius * np.sin(ts), np.zeros_like(ts)], axis=1)
    axis_pts = np.array([[0.0, 0.0, z] for z in np.linspace(0.0, float(np.ptp(obj[:, 0])), 11)])
    cam = tt.camera.at_table_angle(angle)
    det = tt.corners.get(name)
    if det is None:
        det = detect_board(img, pattern, require_orientation=True)
    rep, circ, ax = cam.project(obj + off), cam.project(circle), cam.project(axis_pts)

    def extra(out):
        poly = np.array(_pts(circ, scale), np.int32)
        if len(poly) > 1:
            cv2.polylines(out, [poly], False, _CYAN, 1, cv2.LINE_AA, shift=4)
        axp = np.array(_pts(ax, scale), np.int32)
        if len(axp) > 1:
            cv2.polylines(out, [axp], False, _YELLOW, 2, cv2.LINE_AA, shift=4)
        o = _pts(rep[:1], scale)
        if o:
            cv2.circle(out, o[0], 9 * 16, _CYAN, 2, cv2.LINE_AA, shift=4)

    lines = [f"turntable {name}  angle {angle:g} deg"]
    if name in tt.per_image_rms:
        lines.append(f"RMS {tt.per_image_rms[name]:.3f} px  (joint fit {tt.rms_px:.3f} px)"
                     + ("  FLAGGED: board moved?" if name in tt.flagged else ""))
    if name in tt.rejected:
        lines.append(f"REJECTED: {tt.rejected[name]}")
    lines.append("+ detected  o reprojected  | axis  O sweep of first corner")
    return _draw(img, det, rep, scale, lines, extra)


def agreement_chart(report, path):
    """Bar chart of every view's agreement with the model (``report['views'][i]['agreement']``).

    Parameters
    ----------
    report : dict
        A reconstruction report with view agreement (organlab.agreement).
    path : str or Path
        PNG to write.

    Returns
    -------
    Path
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [(Path(v["image"]).stem, v["agreement"]) for v in report["views"]]
    limit = report["agreement"]["limit"]
    vals = np.array([100 * a["disagreement"] for _, a in rows])
    fig, ax = plt.subplots(figsize=(max(6.0, 0.22 * len(rows) + 2), 3.2), layout="constrained")
    ax.bar(range(len(rows)), vals, color=["#c0392b" if not a["ok"] else "#4a7fb0" for _, a in rows])
    ax.axhline(100 * limit, color="k", ls="--", lw=1, label=f"limit {100 * limit:.2f} %")
    ax.set_xticks(range(len(rows)), [n for n, _ in rows], rotation=90, fontsize=7)
    ax.set_ylabel("silhouette unexplained (%)")
    ax.set_title(f"{report.get('session', '')}: view agreement (red: over the limit)", fontsize=10)
    ax.legend(loc="upper right", fontsize=8)
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def agreement_overlay(image, silhouette, model, path, *, title=None):
    """A view's image with its silhouette and the model's projection drawn over it.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8
    silhouette : (H, W) bool
    model : (H, W) bool
        Pixels covered by the model's projection (organlab.agreement.model_mask).
    path : str or Path
        PNG to write: red = silhouette the model does not explain, blue = model
        outside the silhouette, green = both.
    title : str, optional

    Returns
    -------
    Path
    """
    from PIL import Image, ImageDraw

    img = np.asarray(image)
    rgb = np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else img[..., :3]
    out = rgb.astype(np.float32) * 0.5
    for m, colour in ((silhouette & model, (0, 200, 0)), (silhouette & ~model, (255, 0, 0)), (model & ~silhouette, (0, 80, 255))):
        out[m] = 0.4 * out[m] + 0.6 * np.array(colour, np.float32)
    pic = Image.fromarray(np.clip(out, 0, 255).astype(np.uint8))
    if title:
        ImageDraw.Draw(pic).text((6, 6), title, fill=(255, 255, 255))
    path = Path(path)
    pic.save(path)
    return path
