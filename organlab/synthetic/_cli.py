"""``python -m organlab.synthetic``: the generator's command line."""

from __future__ import annotations

from pathlib import Path

from ..cliparser import OneLineParser
from ..session import load_session
from ._session import make_session


def parser():
    """The generator's argument parser (``organlab synth``)."""

    ap = OneLineParser(prog="organlab synth", description="Write a synthetic organlab session folder.")
    ap.add_argument("out", help="session folder to write")
    ap.add_argument("--seed", type=int, default=0, help="random seed of the generated session (default 0)")
    ap.add_argument("--specimen", choices=["aaa", "grooved", "dented"], default="aaa",
                    help="aaa: the aneurysm phantom (default); grooved, dented: specimens with concavities no "
                    "silhouette shows (for voxel colouring)")
    ap.add_argument(
        "--hard", action="store_true", help="hard lighting: a lamp with cast shadows, highlights, +-10 %% exposure, JPEG views"
    )
    ap.add_argument("--small", action="store_true", help="320x240, 12 views, few calibration images (fast)")
    ap.add_argument("--noise", type=float, default=None,
                    help="pixel noise sigma, grey levels (default 1.0; 1.5 with --small)")
    ap.add_argument(
        "--png",
        action="store_true",
        help="write views and background frames as PNG (default for full-size sessions: JPEG quality 98, 4:4:4, "
        "to keep the folder under 15 MB; calibration images are always grey PNG)",
    )
    ap.add_argument("--no-camera", action="store_true", help="do not put the true intrinsics in session.json")
    ap.add_argument("--no-poses", action="store_true", help="do not put the true view poses in session.json")
    ap.add_argument("--preview", default=None, help="also write a half-size PNG of view 0 here")
    ap.add_argument(
        "--force", action="store_true", help="write into a folder that is not empty (images a previous run listed are replaced)"
    )
    return ap


def main(argv=None):
    """``python -m organlab.synthetic OUT [--seed N] [--specimen aaa|grooved|dented] [--small] [--hard] [--force]``."""
    import time

    ap = parser()
    args = ap.parse_args(argv)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        ap.error(f"{out} is a file, not a folder: give a new folder for the session")
    if out.is_dir() and any(out.iterdir()) and not args.force:
        ap.error(f"{out} is not empty: give a new or empty folder, or --force to write over it")
    kw = {}
    if args.small:
        kw = dict(image_size=(320, 240), n_views=12, n_intrinsic=8, n_turntable=6, n_background=5)
    if args.noise is not None:
        kw["noise_sigma"] = args.noise
    elif not args.small:
        kw["noise_sigma"] = 1.0
    if not args.png and not args.small:
        kw.update(view_format="jpg", background_format="jpg", jpeg_quality=98)
    t0 = time.perf_counter()
    truth = make_session(
        args.out, seed=args.seed, specimen=args.specimen, include_camera=not args.no_camera, include_poses=not args.no_poses, hard=args.hard, **kw
    )
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    print(
        f"wrote {out}: {len(truth['views'])} views, {truth['specimen']} volume {truth['volume_mm3']:.1f} mm^3, "
        f"{size / 1e6:.2f} MB, {time.perf_counter() - t0:.1f} s"
    )
    if args.preview:
        import cv2

        s = load_session(out, check_images=False)
        img = s.read(s.views[0].image)
        small = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
        Path(args.preview).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(args.preview), small[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return 0
