"""The ``organlab`` command line.

    organlab reconstruct SESSION --out DIR [--voxel-size MM] [--threshold T]
                         [--method hull|coloring|space_carving|photo] [--color-threshold X]
                         [--calibration PATH] [--recalibrate] [--measure] [--raw-surface]
    organlab calibrate SESSION (--out DIR | --in-place) [--figures DIR]
    organlab init FOLDER [--step DEG] [--cameras FILE] [--board 9x6] [--square MM] [--roi ...] [--backdrop ...] [--force]
    organlab export-cameras RESULT_DIR --format colmap|meshroom [--out PATH] [--images SESSION]
    organlab mesh RESULT_DIR [--repair] [--smooth] [--remesh MM] [--tetra] [--measure] [--picture]
    organlab synth OUT [--seed N] [--specimen aaa|grooved|dented] [--small] [--hard] [--force] [...]
    organlab capture --turntable sim|PORT --camera sim|INDEX|URL --step DEG --out SESSION [--view [--port P]] [...]
    organlab view SESSION [--result DIR] [--port P] [--host H] [--voxel-size MM]
    organlab sweep SESSION --out DIR [--threshold 10:40:5] [--voxel-size 2,1] [--method hull,coloring] [...]
                   [--workers N | --scheduler ADDRESS]
    organlab batch SESSION... --out DIR [--voxel-size MM] [--threshold T] [...] [--workers N | --scheduler ADDRESS]
    organlab --version

Errors caused by the input print one line (``organlab: error: ...``) naming
the file and the fix, and exit with status 2; nothing is printed as a
traceback for them.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
from pathlib import Path

import numpy as np

from . import __version__
from .cliparser import OneLineParser as _Parser
from .errors import OrganlabError, SettingsError
from .lazy import later
from .preflight import atomic_output_dir, check_output_dir, check_remesh_memory, lock_output_dir, parse_memory
from .progress import NullProgress, ProgressBar
from .session import load_session
from .validate import printable

# The stages, the engine and the viewers: imported when a command first calls them, so that building the parser
# (--help, --version, a mistyped flag) loads none of them (numba, OpenCV, viser: --help took 5.5 s with them at
# the top).  Each line is the import it stands for (tests/test_architecture.py reads them as imports); a command
# that needs another stage function adds one line here, never a top-level 'from .stage import' (test_cli_help.py
# fails when --help loads a stage).
model_mask = later("organlab.agreement", "model_mask")
batch = later("organlab.batch", "batch")
parse_values = later("organlab.batch", "parse_values")
sweep = later("organlab.batch", "sweep")
calibrate = later("organlab.calibration", "calibrate")
export_cameras = later("organlab.calibration", "export_cameras")
run_capture = later("organlab.capture", "run_capture")
agreement_chart = later("organlab.figures", "agreement_chart")
agreement_overlay = later("organlab.figures", "agreement_overlay")
check_figures = later("organlab.figures", "check_figures")
mesh_snapshot = later("organlab.figures", "mesh_snapshot")
reconstruct = later("organlab.pipeline", "reconstruct")
summary_table = later("organlab.pipeline", "summary_table")
write_outputs = later("organlab.pipeline", "write_outputs")
init_session = later("organlab.scaffold", "init_session")
warm_kernels = later("organlab.silhouette", "warm_kernels")
warm_hull_kernels = later("organlab.carving", "warm_kernels")
warm_pose_kernels = later("organlab.poses", "warm_kernels")
warm_surface_kernels = later("organlab.surface", "warm_kernels")
mesh_result = later("organlab.surface", "mesh_result")
carved_depth_picture = later("organlab.coloring", "carved_depth_picture")
Reconstruction = later("organlab.engine", "Reconstruction")
SimRig = later("organlab.synthetic", "SimRig")
synth_main = later("organlab.synthetic", "main")
CaptureViewer = later("organlab.viewer", "CaptureViewer")
SessionViewer = later("organlab.viewer", "SessionViewer")
is_loopback = later("organlab.viewer", "is_loopback")

#: Settings (organlab.engine.Settings) whose flag is not --NAME
_FLAGS = {"finish": "--raw-surface", "measure": "--measure"}


def _positive_float(text):
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return v


def _port(text):
    """A TCP port, 0 (any free one) to 65535: a bad one ends in one line, before a server starts."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"must be a TCP port from 0 to 65535 (0: any free port), got {v}")
    return v


def _check_listen(host, port, option="--port"):
    """Bind ``host:port`` once in this thread, so that what the server thread would die of is one line here.

    ``port`` None: the default 8080, or the next free port when taken (viser's search);
    an explicit port in use is refused.
    """
    import socket

    try:
        infos = socket.getaddrinfo(host, 0 if port is None else port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError, ValueError) as e:
        raise OrganlabError(f"--host {host!r}: not an address of this machine ({e}); use 127.0.0.1") from None
    family, kind, proto, _, addr = infos[0]
    with socket.socket(family, kind, proto) as sock:
        try:
            sock.bind(addr)
        except OSError as e:
            if port is not None and e.errno in (98, 48, 10048):  # EADDRINUSE (Linux, macOS, Windows)
                raise OrganlabError(f"{option} {port}: already in use on {host}; give another port, or 0 for any "
                                    "free one") from None
            raise OrganlabError(f"cannot listen on {host}:{port if port is not None else 0} ({e.strerror or e}); "
                                "use --host 127.0.0.1 and another --port") from None
    return 8080 if port is None else port


def _loopback(host):
    return is_loopback(host)


def _warn_host(host):
    """The warning of a viewer bound to an address other machines reach (it then needs its token)."""
    if not _loopback(host):
        print(f"organlab: warning: --host {printable(host)} is not this machine only: anyone who can reach it and "
              "has the link with its token gets the session's photos and can start reconstructions; requests "
              "without the token are refused; use 127.0.0.1 (and an SSH tunnel) unless the network is trusted",
              file=sys.stderr)


def _start_server(start, what):
    """``start()``, with an exception of a thread started meanwhile (the server's) ending it in one line.

    viser starts its server in a thread and waits for it; a thread that dies before it is ready
    (a port it cannot bind) left the main thread waiting for ever.  The thread's exception is
    caught here, the wait interrupted (SIGINT to the main thread) and one line raised.
    """
    import signal
    import threading

    failed = []
    previous = threading.excepthook

    def hook(args):
        if args.thread is not threading.main_thread() and not failed:
            failed.append(args.exc_value)
            signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)
        else:
            previous(args)

    threading.excepthook = hook
    try:
        return start()
    except KeyboardInterrupt:
        if failed:
            e = failed[0]
            raise OrganlabError(f"{what}: the server could not start ({type(e).__name__}: {e}); "
                                "check --host and --port") from None
        raise
    finally:
        threading.excepthook = previous


def _parser():
    p = _Parser(prog="organlab", description="From a specimen on a turntable to a measured, watertight 3D model.")
    p.add_argument("--version", action="version", version=f"organlab {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("reconstruct", help="carve the specimen of a session and write voxels, mesh and report")
    r.add_argument("session", type=Path, help="session folder (holds session.json)")
    r.add_argument("--out", type=Path, required=True, help="output folder")
    r.add_argument("--voxel-size", type=_positive_float, default=1.0, metavar="MM", help="voxel edge in mm (default 1)")
    r.add_argument("--threshold", type=_positive_float, default=None, metavar="T",
                   help="silhouette threshold in grey levels (default: Li's automatic threshold per view)")
    r.add_argument("--method", choices=["hull", "coloring", "space_carving", "photo"], default="hull",
                   help="hull: visual hull (default); coloring: Seitz & Dyer voxel coloring on the hull (recovers concavities "
                        "no silhouette shows; needs the cameras above the specimen); space_carving: the same for any "
                        "camera layout (slower); photo: patch NCC between neighbouring views (recommended for a "
                        "textured specimen)")
    r.add_argument("--hull", choices=["subvoxel", "thesis"], default="subvoxel",
                   help="subvoxel: sub-pixel silhouettes, surface between voxel centres (default); "
                        "thesis: the thesis's 8-corner bounding-box test")
    r.add_argument("--color-threshold", type=_positive_float, default=None, metavar="X",
                   help="photo-consistency threshold (grey levels) for --method coloring/space_carving "
                   "(default: automatic, from the hull's surface and the image noise; report.json coloring.threshold); "
                   "for --method photo the NCC gain (default 0.25)")
    r.add_argument("--tolerance", type=int, default=0, metavar="K", help="views allowed to disagree before a voxel is carved")
    r.add_argument("--calibration", type=Path, default=None, metavar="PATH",
                   help="use this calibration.json (checked against the session) instead of the session's own")
    r.add_argument("--recalibrate", action="store_true",
                   help="calibrate from the board images even when the session's calibration.json matches it")
    r.add_argument("--picture", action="store_true", help="also render the mesh to DIR/mesh.png (pyvista, off-screen)")
    r.add_argument("--quiet", action="store_true", help="no progress bars")
    r.add_argument("--strict", action="store_true", help="exit with status 2 when the run raises a warning "
                   "(views that disagree with the model, a poor turntable fit, ...)")
    r.add_argument("--max-memory", default=None, metavar="SIZE",
                   help="memory the voxel grid may take, e.g. 8G (default: the memory available now)")
    r.add_argument("--measure", action="store_true", help="AAA measurements in the report (default: when the session is an AAA)")
    r.add_argument("--refine-poses", choices=["auto", "on", "off"], default="auto",
                   help="correct the poses from the silhouettes (a bumped camera, a table that lost steps, a specimen that "
                        "slid), kept only when views left out of the fit agree better; auto: when views disagree (default)")
    r.add_argument("--joint-silhouettes", choices=["auto", "on", "off"], default="auto",
                   help="segment every view again with the hull of all the views as a prior: adds what the other views "
                        "require and the colour does not deny (dark parts, shaded rims), drops what no view explains; "
                        "auto (default): for backdrop sessions with >= 8 views; on: also background subtraction (the sample: "
                        "unchanged, +3 s)")
    r.add_argument("--raw-surface", action="store_true", help="keep the marching-cubes surface (no repair/remeshing)")
    r.add_argument("--allow-outside-paths", action="store_true",
                   help="accept image paths in session.json that lead out of the session folder (.., absolute, symlinks)")

    c = sub.add_parser("calibrate", help="calibrate intrinsics and turntable from the session's board images")
    c.add_argument("session", type=Path, help="session folder (holds session.json)")
    where = c.add_mutually_exclusive_group(required=True)
    where.add_argument("--out", type=Path, metavar="DIR",
                       help="write DIR/calibration.json and the check figures in DIR/calibration_check")
    where.add_argument("--in-place", action="store_true",
                       help="write them into the session folder (later reconstructions reuse its calibration.json)")
    c.add_argument("--figures", type=Path, default=None, metavar="DIR",
                   help="where to write the check figures (default: calibration_check beside calibration.json)")
    c.add_argument("--force", action="store_true", help="with --out: replace the calibration.json already in DIR")
    c.add_argument("--quiet", action="store_true", help="no progress bars")

    _init_parser(sub)
    _export_parser(sub)
    _add_view_parser(sub)
    _mesh_parser(sub)

    s = sub.add_parser("synth", add_help=False, help="generate a synthetic session (same as python -m organlab.synthetic; "
                       "'organlab synth --help' lists its options)")
    s.add_argument("args", nargs=argparse.REMAINDER, help="OUT and the generator's options: 'organlab synth --help'")
    _capture_parser(sub)
    _sweep_parsers(sub)
    return p


def _init_parser(sub):
    i = sub.add_parser("init", help="write a session.json for a folder of images (views sorted by name), to edit")
    i.add_argument("folder", type=Path, help="folder with views/ (or the view images), background/, calibration/...")
    i.add_argument("--step", type=float, default=None, metavar="DEG",
                   help="table rotation between views, degrees (default: the angles in the views' names, e.g. 030.png; "
                        "not needed when --cameras gives every view's pose)")
    i.add_argument("--cameras", type=Path, default=None, metavar="FILE",
                   help="known cameras instead of board images: a Middlebury *_par.txt, a COLMAP text model (folder or "
                        "cameras.txt/images.txt), Bouguet's Calib_Results.m or an OpenCV .yml/.xml (poses where it has them)")
    i.add_argument("--cameras-scale", type=_positive_float, default=None, metavar="MM",
                   help="mm per unit of the camera file's translations (default 1000 for Middlebury, metres; 1 otherwise)")
    i.add_argument("--angles", choices=["names", "step"], default="auto",
                   help="where the views' angles come from (default: the names when every name is a number, else --step)")
    i.add_argument("--start", type=float, default=0.0, metavar="DEG", help="angle of the first view (default 0)")
    i.add_argument("--board", default="9x6", metavar="CxR", help="board's inner corners, columns x rows (default 9x6)")
    i.add_argument("--square", type=_positive_float, default=20.0, metavar="MM", help="board's square size (default 20)")
    i.add_argument("--roi", default=None, metavar="X0,Y0,Z0,X1,Y1,Z1", help="voxel space, mm (default a 200 mm box)")
    i.add_argument("--backdrop", default=None, metavar="border|frames|R,G,B",
                   help="key the views against a uniform backdrop: the image border's colour, the background frames, "
                        "or an RGB colour (default: background subtraction with frames; 'border' without)")
    i.add_argument("--force", action="store_true", help="overwrite an existing session.json")


def _init(a):
    try:
        corners = tuple(int(v) for v in a.board.lower().split("x"))
        roi = None if a.roi is None else [float(v) for v in a.roi.split(",")]
    except ValueError:
        raise OrganlabError(f"--board must be like 9x6 and --roi 6 numbers separated by commas, got {a.board!r}, {a.roi!r}") from None
    backdrop = a.backdrop
    if backdrop is not None and backdrop not in ("border", "frames"):
        try:
            backdrop = [int(v) for v in backdrop.split(",")]
        except ValueError:
            backdrop = None
        if backdrop is None or len(backdrop) != 3 or not all(0 <= v <= 255 for v in backdrop):
            raise OrganlabError(f"--backdrop must be 'border', 'frames' or R,G,B in 0-255, got {a.backdrop!r}")
    if len(corners) != 2 or min(corners) < 2:
        raise OrganlabError(f"--board must be COLUMNSxROWS of inner corners (each >= 2), got {a.board!r}")
    path, notes = init_session(a.folder, step_deg=a.step, start_deg=a.start, cameras=a.cameras,
                               cameras_scale=a.cameras_scale, angles=a.angles, inner_corners=corners,
                               square_size=a.square, roi=roi, backdrop=backdrop, force=a.force)
    doc = json.loads(path.read_text())
    posed = sum("pose" in v for v in doc["views"])
    print(f"organlab init: wrote {path} ({len(doc['views'])} views{f' ({posed} with their pose)' if posed else ''}, "
          f"{len(doc.get('background_images', []))} background frames, "
          f"{len(doc.get('calibration', {}).get('intrinsic_images', []))} intrinsic and "
          f"{len(doc.get('calibration', {}).get('turntable_images', []))} turntable board images); check:")
    for n in notes:
        print(f"  - {n}")
    return 0


def _export_parser(sub):
    e = sub.add_parser("export-cameras", help="write the cameras a reconstruction used for another MVS program "
                       "(COLMAP text model or Meshroom cameras.sfm)")
    e.add_argument("result", type=Path, help="output folder of 'organlab reconstruct' (holds report.json)")
    e.add_argument("--format", required=True, choices=["colmap", "meshroom"],
                   help="colmap: cameras.txt, images.txt, points3D.txt; meshroom: an AliceVision SfMData .sfm")
    e.add_argument("--out", type=Path, default=None, metavar="PATH",
                   help="folder (colmap) or .sfm file (meshroom); default RESULT/colmap or RESULT/cameras.sfm")
    e.add_argument("--images", type=Path, default=None, metavar="SESSION",
                   help="the folder the views' names are relative to (the session folder; default: the current folder)")


def _export_cameras(a):
    paths = export_cameras(a.result, a.out, format=a.format, images=a.images)
    print(f"organlab export-cameras: wrote {', '.join(str(p) for p in paths)}")
    return 0


def _capture_parser(sub):
    k = sub.add_parser("capture", help="capture a session with a turntable and a camera (or the simulated rig); "
                       "continues a stopped capture")
    k.add_argument("--turntable", required=True, metavar="sim|PORT", help="'sim' (simulated MDrive on a pty) or a serial port")
    k.add_argument("--camera", default=None, metavar="sim|INDEX|URL", help="'sim', a device index, a URL or folder:DIR "
                   "(default: sim with the simulated table, else 0)")
    k.add_argument("--step", type=_positive_float, default=10.0, metavar="DEG", help="table step between stops (default 10)")
    k.add_argument("--out", type=Path, required=True, metavar="SESSION", help="session folder")
    k.add_argument("--background", type=int, default=20, metavar="N", help="frames of the empty scene (default 20)")
    k.add_argument("--intrinsics", type=int, default=0, metavar="N", help="hand-held board images for the intrinsics (default 0)")
    k.add_argument("--camera-file", type=Path, default=None, metavar="JSON",
                   help="known intrinsics: a calibration.json or session.json with 'camera'")
    k.add_argument("--no-board", action="store_true", help="no board images on the table (no turntable calibration, no audit)")
    k.add_argument("--audit-limit", type=_positive_float, default=None, metavar="DEG", help="angle audit limit (default 0.5)")
    k.add_argument("--no-stop-on-flag", action="store_true", help="flag a failed angle audit but go on")
    k.add_argument("--steps-per-rev", type=int, default=200, help="motor full steps per revolution (default 200)")
    k.add_argument("--microsteps", type=int, default=256, help="MS microstep resolution (default 256)")
    k.add_argument("--gear-ratio", type=_positive_float, default=90.0, help="motor turns per table turn (default 90)")
    k.add_argument("--baud", type=int, default=9600, help="serial baud rate (default 9600)")
    k.add_argument("--device-name", default=None, help="party mode: the controller's one-letter DN")
    k.add_argument("--home-switch", action="store_true", help="the table has a home switch on input 1 (real tables)")
    k.add_argument("--settle", type=int, default=3, metavar="N", help="frames discarded before each image (default 3)")
    k.add_argument("--average", type=int, default=1, metavar="N", help="frames averaged into each image (default 1)")
    k.add_argument("--sim-size", default="640x480", metavar="WxH", help="simulated camera image size (default 640x480)")
    k.add_argument("--quiet", action="store_true", help="no progress bars")
    k.add_argument("--view", action="store_true", help="watch the capture in the live 3D viewer (browser): each view at "
                   "its camera, the hull carved as the table turns; the viewer stays open after the capture (Ctrl-C stops)")
    k.add_argument("--port", type=_port, default=None, help="with --view: TCP port on 127.0.0.1 (default 8080, the next "
                   "free one if taken; a port given and taken is refused)")
    k.add_argument("--host", default="127.0.0.1", help="with --view: interface to bind (default 127.0.0.1: this "
                   "machine only; any other needs the token printed in the URL)")
    k.add_argument("--view-voxel-size", type=_positive_float, default=2.0, metavar="MM",
                   help="with --view: voxel edge of the live hull in mm (default 2)")


def _add_view_parser(sub):
    v = sub.add_parser("view", help="live 3D viewer in the browser (viser): the views, the hull as it grows, "
                       "controls that re-run it")
    v.add_argument("session", type=Path, help="session folder (holds session.json)")
    v.add_argument("--result", type=Path, default=None, metavar="DIR",
                   help="show a folder written by 'organlab reconstruct' instead of reconstructing at start")
    v.add_argument("--port", type=_port, default=None, help="TCP port (default 8080, the next free one if taken; a port "
                   "given and taken is refused)")
    v.add_argument("--host", default="127.0.0.1", help="interface to bind (default 127.0.0.1: this machine only)")
    v.add_argument("--voxel-size", type=_positive_float, default=1.0, metavar="MM", help="voxel edge in mm (default 1)")


def _view(a):
    import time

    port = _check_listen(a.host, a.port)
    _warn_host(a.host)
    # the session and --result are checked before the server starts; then the URL, then each start-up step
    print("organlab view: loading the viewer (its address follows in a few seconds)", flush=True)  # imports: 3-15 s
    app = _start_server(lambda: SessionViewer(a.session, result=a.result, voxel_size=a.voxel_size, host=a.host,
                                              port=port, say=lambda line: print(line, flush=True)), "organlab view")
    try:
        shown = ""
        while app.result is None and not app.errors:  # the start-up's stages, one line each
            stage = app.status.split(": view ")[0]
            if stage != shown:
                print(f"  {stage}", flush=True)
                shown = stage
            time.sleep(0.2)
        print(f"  {app.status}" if app.result is not None else f"organlab view: {app.status}", flush=True)
        while True:
            time.sleep(1.0)
    finally:
        app.stop()
def _mesh_parser(sub):
    m = sub.add_parser("mesh", help="repair, smooth, remesh, tetrahedralize and measure a reconstruction's surface")
    m.add_argument("result", type=Path, help="output folder of 'organlab reconstruct' (holds voxels.npz)")
    m.add_argument("--repair", action="store_true", help="close holes, remove non-manifold edges/vertices and specks")
    m.add_argument("--smooth", action="store_true", help="Taubin smoothing")
    m.add_argument("--remesh", type=_positive_float, default=None, metavar="MM", help="isotropic remeshing to edges of MM")
    m.add_argument("--tetra", action="store_true", help="tetrahedral mesh (gmsh) as tetra.vtu/.msh/.inp/.xdmf")
    m.add_argument("--measure", action="store_true", help="AAA centreline and diameters to aaa.json")
    m.add_argument("--picture", action="store_true", help="with --measure: aaa_measures.png")
    return m


def _mesh(a):
    if a.result.is_dir():  # a read-only result folder: one line before the work
        _check_writable(a.result / "surface" if (a.result / "surface").is_dir() else a.result)
    with lock_output_dir(a.result, required=False):  # not while a reconstruct replaces the same folder
        return _mesh_locked(a)


def _mesh_locked(a):
    steps = a.repair or a.smooth or a.remesh is not None
    # no step named: all of them, remeshing at 1.5 voxels
    rec = Reconstruction.load(a.result, mesh=False)  # every file it reads checked: one line for a damaged one
    if a.remesh is not None:  # a tiny edge length: the remeshed surface's memory, before pymeshlab tries
        occ = np.pad(rec.occupancy, 1)
        faces = sum(int(np.count_nonzero(np.diff(occ, axis=k))) for k in range(3))  # the voxels' staircase area
        check_remesh_memory(faces * rec.grid.voxel_size ** 2, a.remesh)
    report, paths = mesh_result(
        a.result,
        volume=(rec.surface_volume(), rec.grid),
        repair=a.repair or not steps,
        smooth=a.smooth or not steps,
        remesh=a.remesh if steps else "auto",
        tetra=a.tetra,
        measure=a.measure,
        picture=a.picture,
    )
    q = report["final"]
    print(f"organlab mesh: {a.result} -> {a.result / 'surface'}")
    print(f"  {q['faces']} faces, watertight {'yes' if report['watertight'] else 'NO'}, smallest angle "
          f"{q['min_angle_deg']:.1f} deg, volume {q['volume_mm3'] / 1000:.2f} cm3 ({report['volume_change_pct']:+.2f} %)")
    if "tetra" in report:
        t = report["tetra"]
        print(f"  {t['tets']} tetrahedra, radius ratio min {t['radius_ratio_min']:.2f}, scaled Jacobian min {t['scaled_jacobian_min']:.2f}")
    if "aaa" in report:
        m = report["aaa"]
        print(f"  max diameter {m['max_diameter_mm']:.1f} mm at z {m['max_location_mm'][2]:.1f} mm, "
              f"sac {m['sac_length_mm']:.0f} mm, {m['sac_volume_mm3'] / 1000:.1f} cm3")
    print(f"  wrote {', '.join(p.name for p in paths.values())}")
    return 0


def _bars(quiet):
    return (lambda stage: NullProgress()) if quiet else (lambda stage: ProgressBar(stage))


def _reconstruct(a):
    with lock_output_dir(a.out) as recovered:  # one run at a time into --out; a killed run's leftovers recovered
        for note in recovered:
            print(f"organlab: {note}", file=sys.stderr)
        return _reconstruct_locked(a)


def _reconstruct_locked(a):
    check_output_dir(a.out)  # before the long work
    max_memory = parse_memory(a.max_memory) if a.max_memory is not None else None
    session = _load_session(a)
    try:
        rec = _run_reconstruct(a, session, max_memory)
    except SettingsError as e:  # the library names its parameter; the user typed a flag
        raise OrganlabError(e.for_flag(_FLAGS.get(e.parameter, f"--{e.parameter.replace('_', '-')}"))) from None
    with atomic_output_dir(a.out) as tmp:  # an interrupted run leaves the previous result intact
        paths = write_outputs(rec, tmp, atomic=False)
        if a.picture:
            paths.update(_pictures(rec, tmp, a.voxel_size))
    print(f"organlab reconstruct: {rec.session.name} -> {a.out}")
    print(summary_table(rec.report))
    print(f"  wrote {', '.join(p.name for p in paths.values())}")
    for what in ("intrinsic", "turntable"):
        for name, why in rec.report.get("calibration", {}).get(f"{what}_rejected", {}).items():
            print(f"  {what} image {printable(name)} not used: {printable(why)}")
    warnings = rec.report.get("warnings", [])
    if warnings and a.strict:  # one line: the warnings are the error (report.json lists them one by one)
        print(f"organlab: error: --strict and {len(warnings)} warning{'s' if len(warnings) > 1 else ''}: "
              + " | ".join(printable(w) for w in warnings), file=sys.stderr)
        return 2
    for w in warnings:
        print(f"organlab: warning: {printable(w)}", file=sys.stderr)
    return 0


def _load_session(a):
    """The session, loaded while a thread loads the stages (:func:`_load_stages`); both done on return (the
    thread goes on with what the later stages import, beside the first ones)."""
    ready = threading.Event()
    loading = threading.Thread(target=_load_stages, args=(ready,), name="organlab-load", daemon=True)
    loading.start()  # the stages' modules and first kernels, while the session's images are decoded
    session = load_session(a.session, allow_outside_paths=bool(a.allow_outside_paths))
    ready.wait()
    return session


def _load_stages(ready):
    """Import the stages (numba, scipy, OpenCV: about 0.8 s CPU) and load the silhouettes' and the poses check's
    numba kernels from their cache (numba's own registries with the first one: 0.5 s), on a thread while
    ``reconstruct`` loads the session: Python holding the GIL here, decoding the images there (cv2 releases it).
    Then ``ready`` is set and, while the silhouettes run, the thread loads the hull field's kernels (0.2 s CPU
    that was the hull stage's), imports scipy.ndimage (the AAA measures': 0.15 s CPU, else imported on their
    thread beside the finishing, which it slowed) and loads the finishing's kernels (0.12 s CPU of its first call).
    A failure here is left to the run itself, which imports and calls the same things and says what went wrong."""
    try:
        reconstruct.resolve()
        warm_kernels()
        warm_pose_kernels()  # the poses check's edge coverage (45 ms CPU)
    except Exception:  # noqa: BLE001 (the run reports it)
        pass
    finally:
        ready.set()
    for step, parallel in ((warm_hull_kernels, True), (_import_ndimage, False), (warm_surface_kernels, True)):
        try:
            if not parallel or _parallel_beside():
                step()
        except Exception:  # noqa: BLE001 (the run reports it)
            pass


def _import_ndimage():
    import scipy.ndimage  # noqa: F401


def _parallel_beside():
    """Whether this thread may run parallel numba kernels beside the run's: numba's omp or tbb threading layer
    (two threads in parallel kernels abort the process under workqueue); False while no layer is chosen yet."""
    import numba

    try:
        return numba.threading_layer() in ("omp", "tbb")
    except ValueError:  # no layer chosen yet
        return False


def _run_reconstruct(a, session, max_memory):
    return reconstruct(
        session,
        voxel_size=a.voxel_size,
        threshold=a.threshold,
        method=a.method,
        hull=a.hull,
        color_threshold=a.color_threshold,
        tolerance=a.tolerance,
        calibration=a.calibration,
        recalibrate=a.recalibrate,
        progress=_bars(a.quiet),
        max_memory=max_memory,
        finish=not a.raw_surface,
        measure=True if a.measure else None,
        refine_poses=a.refine_poses,
        joint_silhouettes=a.joint_silhouettes,
    )


def _pictures(rec, folder, voxel_size):
    ref = rec.report.get("mesh_volume_error_pct")
    title = f"{rec.session.name}: {rec.report['mesh_volume_mm3'] / 1000:.1f} cm3 at {voxel_size:g} mm"
    title += f" ({ref:+.2f} % vs reference)" if ref is not None else ""
    out = {"picture": mesh_snapshot(rec.mesh, folder / "mesh.png", title=title)}
    if (rec.coloring or {}).get("depth_map") is not None:  # --method photo: the carved depth over the hull
        out["carved"] = carved_depth_picture(rec.coloring, folder / "carved.png",
                                             title=f"{rec.session.name}: carved below the hull (--method photo)")
    if rec.report.get("agreement"):
        out["agreement"] = agreement_chart(rec.report, folder / "agreement.png")
        worst = rec.agreement.worst  # the one ranking (organlab.engine.AgreementFigures)
        sil = rec.silhouettes[worst].coverage >= 0.5
        view = rec.session.views[worst]
        a = rec.report["views"][worst]["agreement"]
        out["worst_view"] = agreement_overlay(
            rec.session.read(view.image, key=f"views[{worst}].image"), sil,
            model_mask(rec.mesh, rec.cameras[worst], sil.shape), folder / "worst_view.png",
            title=f"{rec.session.relpath(view.image)}: IoU {a['iou']:.3f}, {100 * a['disagreement']:.2f} % unexplained "
                  "(red: silhouette only, blue: model only)",
        )
    return out


def _check_writable(folder):
    """Refuse, in one line, a folder that cannot take a file (made if missing)."""
    import tempfile

    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError as e:
        raise OrganlabError(f"{folder}: cannot write here ({e.strerror or e}); choose a writable folder") from None


def _calibrate(a):
    session = load_session(a.session)
    out = session.root if a.in_place else a.out
    if out.exists() and not out.is_dir():
        raise OrganlabError(f"{out}: exists and is not a folder; give --out a folder")
    if not a.in_place and (out / "calibration.json").exists() and not a.force:
        raise OrganlabError(f"{out / 'calibration.json'}: already exists; give --force to replace it, or another --out")
    _check_writable(out)  # before the fit, not after it
    bar = _bars(a.quiet)("calibration")
    cal = calibrate(session, progress=bar)
    bar.close()
    out.mkdir(parents=True, exist_ok=True)
    # the figures first, calibration.json last (atomically): a run killed before it ends leaves no calibration.json,
    # so the same command runs again (one killed after it finished left a complete result)
    figs = check_figures(session, cal, a.figures or out / "calibration_check")
    path = cal.save(out / "calibration.json")
    print(f"organlab calibrate: {session.name} -> {path}")
    for line in cal.summary():
        print(f"  {line}")
    for what, fit in (("intrinsic", cal.intrinsics), ("turntable", cal.turntable)):
        for name, why in (fit.rejected.items() if fit is not None else ()):
            print(f"  {what} image {printable(name)} not used: {printable(why)}")
    print(f"  {len(figs)} check figures in {Path(figs[0]).parent if figs else '-'}")
    for w in cal.warnings():
        print(f"organlab: warning: {w}", file=sys.stderr)
    return 0


def _capture(a):
    drive = {"steps_per_rev": a.steps_per_rev, "microsteps": a.microsteps, "gear_ratio": a.gear_ratio}
    if a.turntable != "sim":
        drive.update(baudrate=a.baud, device_name=a.device_name, home_switch=a.home_switch)
    try:
        w, h = (int(v) for v in a.sim_size.lower().split("x"))
    except ValueError:
        raise OrganlabError(f"--sim-size must be WIDTHxHEIGHT, e.g. 640x480, got {a.sim_size!r}") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise OrganlabError(f"--sim-size must be WIDTHxHEIGHT with each side in 16-8192 px, got {a.sim_size!r}")
    sim = {k: drive[k] for k in ("steps_per_rev", "microsteps", "gear_ratio")}
    sim["time_scale"] = 10.0  # simulated moves 10x faster than the real table
    viewer = _capture_viewer(a)
    try:
        bar = _bars(a.quiet)("capture")
        path = run_capture(
            a.out, turntable=a.turntable, camera=a.camera, step_deg=a.step, n_background=a.background,
            n_intrinsic=a.intrinsics, board=not a.no_board, intrinsics_file=a.camera_file, drive=drive,
            audit_limit_deg=a.audit_limit, stop_on_flag=not a.no_stop_on_flag, settle_frames=a.settle,
            average=a.average, rig=SimRig(**sim, image_size=(w, h)) if a.turntable == "sim" else None, progress=bar,
            on_view=None if viewer is None else viewer.on_view,
        )
        bar.close()
        print(f"organlab capture: {path} complete; next: organlab reconstruct {path} --out DIR")
        if viewer is not None:
            print(f"organlab capture: the viewer stays at {viewer.url}  (Ctrl-C stops)")
            _serve_until_interrupted(viewer)
    finally:
        if viewer is not None:
            viewer.stop()
    return 0


def _capture_viewer(a):
    """The live viewer of ``capture --view`` (its URL printed), or None."""
    if not a.view:
        return None
    if a.no_board:
        raise OrganlabError("--view needs the board images on the table (the views' camera poses come from them); "
                            "drop --no-board or --view")
    port = _check_listen(a.host, a.port)
    _warn_host(a.host)
    viewer = _start_server(lambda: CaptureViewer(a.out, voxel_size=a.view_voxel_size, host=a.host, port=port),
                           "organlab capture --view")
    print(f"organlab capture: live view at {viewer.url}  (the hull appears with the first view)")
    return viewer


def _serve_until_interrupted(viewer):
    """Keep the viewer's server up until Ctrl-C."""
    import time

    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass


def _synth(argv):
    return synth_main(argv)


# ---------------------------------------------------------------- sweep and batch (issue 23): organlab.batch on Dask
def _workers_arg(text):
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if n < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {n}")
    return n


def _dask_arguments(p):
    p.add_argument("--workers", type=_workers_arg, default=None, metavar="N",
                   help="worker processes of the local Dask cluster, one thread each (default: one per CPU core); "
                        "0 runs every task in this process, without Dask")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="a running Dask scheduler, e.g. tcp://10.0.0.5:8786 (default: $DASK_SCHEDULER_ADDRESS, else a "
                        "local cluster); its workers need organlab and read the session folder at the same path")
    p.add_argument("--raw-surface", action="store_true", help="keep the marching-cubes surface (no repair/remeshing)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _sweep_parsers(sub):
    w = sub.add_parser("sweep", help="reconstruct one session over ranges of settings on Dask: summary.csv, plots, "
                       "the recommended setting")
    w.add_argument("session", type=Path, help="session folder (holds session.json)")
    w.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="DIR/results/NAME per setting, DIR/summary.csv, DIR/recommended.json, DIR/plots; a re-run "
                        "skips the finished results")
    rng = " (a list A,B,C or an inclusive range START:STOP:STEP)"
    w.add_argument("--threshold", default="auto", metavar="VALUES",
                   help="silhouette thresholds in grey levels" + rng + "; auto: Li's threshold per view (default)")
    w.add_argument("--voxel-size", default="1", metavar="MM", help="voxel edges in mm" + rng + " (default 1)")
    w.add_argument("--method", default="hull", metavar="hull,coloring,...", help="methods, a list (default hull)")
    w.add_argument("--hull", default="subvoxel", metavar="subvoxel,thesis", help="hull tests, a list (default subvoxel)")
    w.add_argument("--color-threshold", default="auto", metavar="VALUES",
                   help="photo-consistency thresholds for coloring/space_carving" + rng + " (default auto)")
    w.add_argument("--tolerance", default="0", metavar="K", help="views allowed to disagree" + rng + " (default 0)")
    w.add_argument("--calibration", type=Path, default=None, metavar="PATH", help="use this calibration.json")
    w.add_argument("--recalibrate", action="store_true", help="calibrate from the board images (once, before the sweep)")
    w.add_argument("--no-plots", action="store_true", help="no PNG plots")
    _dask_arguments(w)

    b = sub.add_parser("batch", help="reconstruct many sessions at one setting on Dask; a bad session is one line")
    b.add_argument("sessions", type=Path, nargs="+", metavar="SESSION", help="session folders")
    b.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="DIR/results/SESSION_NAME per session and DIR/summary.csv; a re-run skips the finished ones")
    b.add_argument("--voxel-size", type=_positive_float, default=1.0, metavar="MM", help="voxel edge in mm (default 1)")
    b.add_argument("--threshold", type=_positive_float, default=None, metavar="T",
                   help="silhouette threshold in grey levels (default: automatic per view)")
    b.add_argument("--method", choices=["hull", "coloring", "space_carving", "photo"], default="hull",
                   help="hull: visual hull only (default); coloring / space_carving / photo: then photo-consistency")
    b.add_argument("--hull", choices=["subvoxel", "thesis"], default="subvoxel",
                   help="subvoxel: the sub-voxel hull field (default); thesis: the 8-corner bounding-box test")
    b.add_argument("--color-threshold", type=_positive_float, default=None, metavar="X",
                   help="photo-consistency threshold for coloring/space_carving (default: automatic)")
    b.add_argument("--tolerance", type=int, default=0, metavar="K",
                   help="views allowed to disagree before a voxel is carved (default 0)")
    _dask_arguments(b)


def _dask_options(a):
    if a.scheduler is not None and a.workers is not None:
        raise OrganlabError("--scheduler and --workers exclude each other (the scheduler's cluster has its own workers)")
    return {"scheduler": a.scheduler, "workers": a.workers}


def _batch_bar(a, label):
    return None if a.quiet else ProgressBar(label)


def _print_failures(df, what):
    """One line per failed result on stderr; exit status 2 when there is one."""
    bad = df[df["status"] == "error"]
    for _, r in bad.iterrows():
        print(f"organlab: error: {r['name']}: {r['error']}", file=sys.stderr)
    return 2 if len(bad) else 0


def _sweep(a):
    grid = {}
    for flag, name in (("threshold", "threshold"), ("voxel_size", "voxel_size"), ("method", "method"), ("hull", "hull"),
                       ("color_threshold", "color_threshold"), ("tolerance", "tolerance")):
        try:
            grid[name] = parse_values(getattr(a, flag), name=name)
        except ValueError as e:
            raise OrganlabError(f"--{flag.replace('_', '-')}: {str(e).split(': ', 1)[-1]}") from None
    try:
        df = sweep(a.session, grid, settings={"finish": not a.raw_surface}, out=a.out, calibration=a.calibration,
                   recalibrate=a.recalibrate, progress=_batch_bar(a, "sweep"), plots=not a.no_plots, **_dask_options(a))
    except ValueError as e:  # a value the settings refuse (names the setting)
        raise OrganlabError(f"{a.session}: {e}") from None
    ok = df[df["status"] != "error"]
    print(f"organlab sweep: {df['session'].iloc[0]}: {len(df)} settings ({(df['status'] == 'done').sum()} computed, "
          f"{(df['status'] == 'finished before').sum()} finished before, {(df['status'] == 'error').sum()} failed) "
          f"-> {a.out}")
    for _, r in ok.iterrows():
        ref = f" ({r['volume_error_pct']:+.2f} %)" if r["volume_error_pct"] == r["volume_error_pct"] else ""
        print(f"  {r['name']:<44} {r['volume_mm3'] / 1000:8.2f} cm3{ref}  agreement {r['agreement_mean_iou']:.4f} "
              f"(worst {r['agreement_worst_iou']:.4f})  {r['n_warnings']} warning(s)")
    rec = df.attrs.get("recommended")
    if rec:
        print(f"  recommended: {rec['name']}: {rec['reason']}")
    print(f"  wrote summary.csv, recommended.json{', plots/' if not a.no_plots else ''}, results/")
    return _print_failures(df, "settings")


def _batch(a):
    settings = {"voxel_size": a.voxel_size, "threshold": a.threshold, "method": a.method, "hull": a.hull,
                "color_threshold": a.color_threshold, "tolerance": a.tolerance, "finish": not a.raw_surface}
    try:
        df = batch(a.sessions, settings, out=a.out, progress=_batch_bar(a, "batch"), **_dask_options(a))
    except ValueError as e:
        raise OrganlabError(str(e)) from None
    print(f"organlab batch: {len(df)} sessions ({(df['status'] == 'done').sum()} computed, "
          f"{(df['status'] == 'finished before').sum()} finished before, {(df['status'] == 'error').sum()} failed) "
          f"-> {a.out}")
    for _, r in df[df["status"] != "error"].iterrows():
        ref = f" ({r['volume_error_pct']:+.2f} %)" if r["volume_error_pct"] == r["volume_error_pct"] else ""
        print(f"  {r['name']:<30} {r['volume_mm3'] / 1000:8.2f} cm3{ref}  agreement {r['agreement_mean_iou']:.4f}  "
              f"{r['n_warnings']} warning(s)")
    return _print_failures(df, "sessions")


def _exit_now(code):
    """End the process with ``code`` once the command is done, skipping the interpreter's teardown.

    The teardown (freeing every module, numba's and llvmlite's compiled code, the arrays still referenced)
    took 0.5 s of a 4.9 s ``organlab reconstruct`` at 1 mm idle, 1.1-1.3 s under load, and does nothing a
    user needs: the outputs are written and closed by then.  The ``atexit`` handlers still run (logging,
    temporary folders) and the standard streams are flushed; with a non-daemon thread still running, the
    ordinary exit (which waits for it) is kept.
    """
    import atexit
    import os
    import threading

    if any(t is not threading.main_thread() and not t.daemon and t.is_alive() for t in threading.enumerate()):
        return code
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # a closed pipe (organlab ... | head): nothing more can be said
            pass
    os._exit(code if isinstance(code, int) else (0 if code is None else 1))


def main(argv=None):
    """The ``organlab`` command; ``argv`` None is the program itself (``sys.argv``), which then exits at
    once when the command is done (:func:`_exit_now`); a list of arguments returns the exit status."""
    if argv is None:
        return _exit_now(_main(sys.argv[1:]))
    return _main(list(argv))


def _main(argv):
    if argv[:1] == ["synth"]:  # its own parser (python -m organlab.synthetic), options and --help included
        args, handler = argv[1:], _synth
    else:
        args = _parser().parse_args(argv)
        handler = {"reconstruct": _reconstruct, "calibrate": _calibrate, "capture": _capture, "view": _view,
                   "mesh": _mesh, "init": _init, "export-cameras": _export_cameras, "sweep": _sweep,
                   "batch": _batch}[args.command]
    try:
        return handler(args)
    except OrganlabError as e:  # one line: text from files (names, paths) with its control characters escaped
        print(f"organlab: error: {printable(e)}", file=sys.stderr)
        return 2
    except OSError as e:  # a full disk, a read-only folder, a device gone, on any path: one line naming the file
        where = f" ({printable(e.filename)})" if e.filename else ""
        print(f"organlab: error: {printable(e.strerror or e)}{where}; free some space or use a writable folder, "
              "and run the command again", file=sys.stderr)
        return 2
    except MemoryError:
        print("organlab: error: out of memory; give --max-memory, a larger --voxel-size or fewer views, or free "
              "memory", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("organlab: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
