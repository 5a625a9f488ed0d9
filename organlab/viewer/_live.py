"""LiveView: a viser scene that carving and capture stream partial results to.

Every method may be called from any thread; scene updates are serialised by a
lock.  viser's rules are followed: arrays are always new arrays assigned to a
handle (never changed in place), positions are float32 (viser's float16
default would round millimetres away from the origin), and the scene is in mm
with the initial camera placed so a specimen of the roi's size is in view.
"""

from __future__ import annotations

import threading

import numpy as np

from ..camera import Camera
from ..engine import LiveHull
from . import _scene
from ._access import is_loopback, new_token, start_viser


class LiveView:
    """A live 3D scene in the browser (viser) for one specimen.

    Parameters
    ----------
    roi : ((3,), (3,)) float, mm, world frame, optional
        ``(roi_min, roi_max)``: frames the initial camera and sizes the
        turntable plate.  Default: a 140 x 140 x 200 mm box on the table.
    grid : VoxelGrid, optional
        When given, :meth:`add_view` with a silhouette carves the hull view by
        view (:class:`organlab.carving.ProgressiveCarver`) and streams it.
    tolerance : int
        Tolerance of that progressive carving.
    host : str
        Interface to bind; ``'127.0.0.1'`` (default) keeps the viewer local.  Any other
        address requires a token in the URL (:mod:`organlab.viewer._access`).
    port : int
        TCP port (0: any free port; viser tries the next ports when taken).
    label : str
        Title of the GUI panel.
    token : str, optional
        Every request must carry it (``?token=`` in the URL, then a cookie).  Default: a new
        random token when ``host`` is not a loopback address, none on loopback.

    Attributes
    ----------
    server : viser.ViserServer
    cameras, images, masks : lists, one entry per view added
    updates : int
        Number of voxel/mesh updates sent.
    token : str or None
        The token :attr:`url` carries (None: loopback, no token needed).
    """

    def __init__(self, *, roi=None, grid=None, tolerance=0, host="127.0.0.1", port=8080, label="organlab", verbose=False,
                 token=None):
        if token is None and not is_loopback(host):
            token = new_token()
        self.token = token
        self.server = start_viser(host=host, port=port, label=label, verbose=verbose, token=token)
        self.server.scene.set_up_direction("+z")
        self._lock = threading.RLock()
        self.cameras, self.images, self.masks = [], [], []
        self._thumbs, self._frustums = [], []
        self._handles = {}
        self._carved = None
        self.selected = None
        self.updates = 0
        self._click_callbacks = []
        self._aaa_handles = []
        self._views_visible = True
        self._looking = None
        self._grid = grid
        self._carver = None
        if grid is not None:
            self._carver = LiveHull(grid, tolerance=tolerance)
        if roi is None:
            roi = grid.bounds if grid is not None else ((-70.0, -70.0, 0.0), (70.0, 70.0, 200.0))
        self.frame(*roi)

    # ------------------------------------------------------------ basics
    @property
    def port(self):
        return self.server.get_port()

    @property
    def url(self):
        host = self.server.get_host()
        host = "127.0.0.1" if host in ("0.0.0.0", "") else host
        if ":" in host:  # an IPv6 address
            host = f"[{host}]"
        return f"http://{host}:{self.port}" + (f"/?token={self.token}" if self.token else "")

    def iframe(self, *, width="100%", height=520):
        """The viewer embedded in a notebook cell (``IPython.display.IFrame``)."""
        from IPython.display import IFrame

        return IFrame(self.url, width=width, height=height)

    def _repr_html_(self):
        return f'<iframe src="{self.url}" width="100%" height="520" style="border:0"></iframe>'

    def stop(self):
        """Stop the server and free its port."""
        self.server.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()

    def on_view_click(self, func):
        """Register ``func(index, client)`` called when a view's frustum is clicked."""
        self._click_callbacks.append(func)
        return func

    # ------------------------------------------------------------ turntable
    def frame(self, roi_min, roi_max):
        """Draw turntable frame, axis and plate, and aim the initial camera at the roi (mm)."""
        lo = np.asarray(roi_min, np.float64)
        hi = np.asarray(roi_max, np.float64)
        size = float(np.linalg.norm(hi - lo))
        self._roi = (lo, hi)
        self._scale = size
        sc = self.server.scene
        with self._lock:
            sc.add_frame("/turntable", axes_length=0.2 * size, axes_radius=0.006 * size)
            axis = np.array([[[0, 0, lo[2] - 0.1 * size], [0, 0, hi[2] + 0.15 * size]]], np.float32)
            sc.add_line_segments("/turntable/axis", axis, (60, 60, 60), thickness=0.004 * size)
            r = 0.5 * float(np.linalg.norm((hi - lo)[:2]))
            ang = np.linspace(0, 2 * np.pi, 65)[:-1]
            ring = np.stack([r * np.cos(ang), r * np.sin(ang), np.full_like(ang, lo[2] - 0.5)], 1)
            verts = np.vstack([[0.0, 0.0, lo[2] - 0.5], ring]).astype(np.float32)
            faces = np.array([[0, 1 + i, 1 + (i + 1) % 64] for i in range(64)], np.uint32)
            sc.add_mesh_simple("/turntable/plate", verts, faces, color=(205, 200, 190), side="double",
                               opacity=0.6, cast_shadow=False, receive_shadow=False)
        self.aim()

    def aim(self, *, move_clients=False):
        """Point the initial camera at the roi from outside the ring of cameras (mm scene)."""
        lo, hi = self._roi
        centre = (lo + hi) / 2
        reach = max([1.5 * self._scale] + [0.8 * float(np.linalg.norm(c.center - centre)) for c in self.cameras])
        cam = self.server.initial_camera
        cam.fov = np.deg2rad(50.0)
        cam.near = 0.01 * self._scale
        cam.far = 20.0 * reach
        cam.look_at = centre
        d = np.array([0.45, -0.6, 0.75])
        cam.position = centre + reach * d / np.linalg.norm(d)
        if move_clients:
            for client in self.server.get_clients().values():
                with client.atomic():
                    client.camera.position = cam.position
                    client.camera.look_at = centre
                    client.camera.fov = cam.fov

    # ------------------------------------------------------------ views
    def add_view(self, image, camera, silhouette=None):
        """Show one more view: its frustum and photo; carve with it when a grid was given.

        Parameters
        ----------
        image : (H, W) or (H, W, 3) uint8
        camera : Camera
        silhouette : (H, W) bool, or organlab.silhouette.Silhouette, optional

        Returns
        -------
        int : the view's index
        """
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be an organlab.camera.Camera, got {type(camera).__name__}")
        img = np.asarray(image)
        w, h = camera.image_size
        if img.shape[:2] != (h, w) or img.ndim not in (2, 3) or img.dtype != np.uint8:
            raise ValueError(f"image must be (H, W) or (H, W, 3) uint8 with (H, W) = {(h, w)} (the camera's image_size), "
                             f"got {img.shape} {img.dtype}")
        mask = getattr(silhouette, "mask", silhouette)
        mask = None if mask is None else np.asarray(mask, bool)
        if mask is not None and mask.shape != (h, w):
            raise ValueError(f"silhouette must be (H, W) = {(h, w)} (the camera's image_size), got {mask.shape}")
        with self._lock:
            i = len(self.cameras)
            self.cameras.append(camera)
            self.images.append(image)
            self.masks.append(mask)
            self._thumbs.append(_scene.thumbnail(image))
            self._add_frustum(i)
            if i == 0:
                self.aim()
        if self._carver is not None and mask is not None:
            occ = self._carver.add(mask, camera)
            self.set_voxels(occ, self._grid)
        return i

    def set_grid(self, grid, *, tolerance=0):
        """Carve from now on in ``grid`` (a new, empty progressive hull) and frame its roi.

        Parameters
        ----------
        grid : VoxelGrid
        tolerance : int
            Tolerance of the progressive carving.
        """
        with self._lock:
            self._grid = grid
            self._carver = LiveHull(grid, tolerance=tolerance)
        self.frame(*grid.bounds)

    def capture_listener(self, camera0, *, background=None, threshold=None, floor=0.0, noise=0.0):
        """A callback for ``organlab.capture``'s ``on_view(index, angle_deg, image)``.

        Each captured image is shown at its camera ``camera0.at_table_angle(angle)``;
        with a background model its silhouette is found
        (:func:`organlab.silhouette.silhouette`) and, when this view was made with
        a ``grid``, the hull is carved and streamed as the table turns.

        Parameters
        ----------
        camera0 : Camera
            The calibrated camera at table angle 0 (``R_cam``, ``t_cam``).
        background : (H, W, 3) float, optional
            :func:`organlab.silhouette.background_model` of the empty scene.
        threshold : float, optional
            Grey levels (automatic per view when omitted).
        floor : float
            Lowest automatic threshold, grey levels (e.g. 5 x the background
            noise, as :class:`organlab.silhouette.SilhouetteModel` uses).
        noise : float
            The frames' :func:`organlab.silhouette.background_noise`, grey levels:
            > 0 keeps each view's dim rim at the automatic threshold
            (:func:`organlab.silhouette.grow_rim`), as ``organlab reconstruct`` does.

        Returns
        -------
        callable(index, angle_deg, image)
        """
        find = None if background is None else LiveHull.by_subtraction(background, threshold=threshold,
                                                                        floor=floor, noise=noise)

        def on_view(index, angle_deg, image):
            self.add_view(image, camera0.at_table_angle(angle_deg), None if find is None else find(image))

        return on_view

    def _add_frustum(self, i):
        cam = self.cameras[i]
        wxyz, pos, fov, aspect = _scene.camera_pose(cam)
        dist = float(np.linalg.norm(pos - np.mean(self._roi, axis=0)))
        h = self.server.scene.add_camera_frustum(
            f"/views/{i:03d}", fov=fov, aspect=aspect, scale=_scene.frustum_scale(fov, aspect, 0.09 * dist),
            thickness=0.002 * dist,
            color=(90, 90, 90), image=self._thumbs[i], format="jpeg", wxyz=wxyz, position=pos,
        )

        @h.on_click
        def _(event, i=i):
            for f in list(self._click_callbacks):
                f(i, event.client)

        if i < len(self._frustums):
            self._frustums[i] = h
        else:
            self._frustums.append(h)

    def select_view(self, index, hull=None):
        """Highlight a view: its photo with the silhouette tinted (and the hull's outline) on its frustum.

        Parameters
        ----------
        index : int
        hull : (H, W) bool, optional
            The hull projected into this view.

        Returns
        -------
        (H, W, 3) uint8 : the overlay shown
        """
        with self._lock:
            prev, self.selected = self.selected, int(index)
            if prev is not None and prev != index and prev < len(self._frustums):
                self._frustums[prev].image = self._thumbs[prev]
                self._frustums[prev].color = (90, 90, 90)
            img = _scene.overlay(self.images[index], self.masks[index], hull)
            self._frustums[index].image = _scene.thumbnail(img)
            self._frustums[index].color = (230, 120, 0)
        return img

    def look_through(self, index, client=None, image=None):
        """Move the browser's camera to a view's pose and show its photo behind the model.

        Parameters
        ----------
        index : int
        client : viser.ClientHandle, optional
            Default: every connected client.
        image : (H, W, 3) uint8, optional
            The picture shown (default the photo); e.g. :func:`_scene.overlay`.
        """
        cam = self.cameras[index]
        wxyz, pos, fov, aspect = _scene.camera_pose(cam)
        centre = np.mean(self._roi, axis=0)
        depth = float((cam.R @ centre + cam.t)[2]) + 0.6 * self._scale
        # the browser draws a pinhole camera: undistort the photo, and shift its
        # plane by the principal point's offset from the image centre
        import cv2

        photo = np.asarray(image if image is not None else self.images[index])
        photo = cv2.undistort(np.ascontiguousarray(photo[..., :3]), cam.K, cam.dist)
        w, h = cam.image_size
        fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
        offset = np.array([(w / 2 - 0.5 - cx) * depth / fx, (h / 2 - 0.5 - cy) * depth / fy, depth])
        with self._lock:
            self._unhide_looked()
            self._frustums[index].visible = False  # its own photo would cover the view
            self._looking = index
            self._handles["look"] = self.server.scene.add_image(
                "/look", photo, render_width=w * depth / fx, render_height=h * depth / fy, format="jpeg",
                wxyz=wxyz, position=pos + cam.R.T @ offset, cast_shadow=False, receive_shadow=False,
            )
            clients = [client] if client is not None else list(self.server.get_clients().values())
            for c in clients:
                with c.atomic():
                    c.camera.position = pos
                    c.camera.wxyz = wxyz
                    c.camera.fov = fov

    def hide_look(self):
        """Remove the photo plane of :meth:`look_through`."""
        with self._lock:
            self._unhide_looked()
            h = self._handles.pop("look", None)
            if h is not None:
                h.remove()

    def _unhide_looked(self):
        j = getattr(self, "_looking", None)
        if j is not None:
            self._frustums[j].visible = self._views_visible
            self._looking = None

    # ------------------------------------------------------------ model
    def set_voxels(self, occupancy, grid, colors=None, *, visible=True):
        """Show the surface voxels of a voxel model as square points, one voxel wide.

        Parameters
        ----------
        occupancy : grid.shape bool
        grid : VoxelGrid
        colors : grid.shape + (3,) uint8, optional
            Voxel colours (voxel colouring); else shaded by height.
        """
        if np.shape(occupancy) != tuple(grid.shape):
            raise ValueError(f"occupancy has shape {np.shape(occupancy)} but the grid is {grid.shape}")
        surf = _scene.surface_voxels(occupancy)
        idx = np.argwhere(surf)
        pts = grid.centers(idx).astype(np.float32)
        if colors is not None:
            cols = np.asarray(colors)[surf].astype(np.uint8)
        else:
            lo, hi = grid.bounds
            cols = _scene.height_colors(pts, lo[2], hi[2])
        self._points("voxels", pts, cols, grid.voxel_size, visible=visible)
        return len(pts)

    def _points(self, key, pts, cols, size, visible=True):
        with self._lock:
            h = self._handles.get(key)
            if h is not None and h.point_size == size and len(pts):
                h.points = pts  # new arrays each time: viser sends what is assigned
                h.colors = cols
                h.visible = visible
            else:
                if h is not None:
                    h.remove()
                if not len(pts):
                    pts, cols = np.zeros((1, 3), np.float32), np.zeros((1, 3), np.uint8)
                    visible = False
                self._handles[key] = self.server.scene.add_point_cloud(
                    f"/{key}", pts, cols, point_size=float(size), point_shape="square", precision="float32",
                    point_shading="flat", visible=visible,
                )
            self.updates += 1

    def set_mesh(self, mesh, *, visible=True, opacity=None):
        """Show a triangle mesh (organlab.surface.Mesh), with its vertex colours when it has them.

        ``opacity`` (0-1, meshes without vertex colours): e.g. 0.5 to see an AAA centreline inside.
        """
        v = np.asarray(mesh.vertices, np.float32)
        f = np.asarray(mesh.faces, np.uint32)
        with self._lock:
            h = self._handles.pop("mesh", None)
            if h is not None:
                h.remove()
            sc = self.server.scene
            if mesh.vertex_colors is not None:
                import trimesh

                tm = trimesh.Trimesh(v, f, vertex_colors=np.asarray(mesh.vertex_colors, np.uint8), process=False)
                self._handles["mesh"] = sc.add_mesh_trimesh("/mesh", tm, visible=visible)
            else:
                self._handles["mesh"] = sc.add_mesh_simple("/mesh", v, f, color=(215, 150, 130), visible=visible,
                                                           opacity=opacity, side="front" if opacity is None else "double")
            self.updates += 1

    def set_aaa(self, measures, *, visible=True):
        """Show AAA measures: the centreline, the maximum-diameter section (ring and disc), its diameter.

        Parameters
        ----------
        measures : organlab.surface.AAAMeasures or None
            None removes what an earlier call showed.

        Returns
        -------
        dict or None : the arrays drawn (:func:`._scene.aaa_geometry`)
        """
        with self._lock:
            for h in self._aaa_handles:
                h.remove()
            self._aaa_handles = []
            self._handles.pop("aaa", None)
            if measures is None:
                return None
            g = _scene.aaa_geometry(measures)
            sc, t = self.server.scene, 0.004 * self._scale
            frame = sc.add_frame("/aaa", show_axes=False, visible=visible)
            self._aaa_handles = [
                sc.add_line_segments("/aaa/centreline", g["centreline"], (30, 80, 230), thickness=t),
                sc.add_line_segments("/aaa/max_section", g["ring"], (230, 30, 30), thickness=t),
                sc.add_mesh_simple("/aaa/max_disc", g["disc_vertices"], g["disc_faces"], color=(230, 60, 60),
                                   opacity=0.35, side="double", cast_shadow=False, receive_shadow=False),
                sc.add_line_segments("/aaa/max_diameter", g["diameter"], (250, 200, 0), thickness=t),
                sc.add_label("/aaa/label", f"max diameter {measures.max_diameter_mm:.1f} mm",
                             position=tuple(g["label_at"]), anchor="bottom-left"),
                frame,
            ]
            self._handles["aaa"] = frame
            self.updates += 1
        return g

    def set_visible(self, key, visible):
        """Show or hide ``'voxels'``, ``'mesh'``, ``'carved'``, ``'aaa'`` or ``'views'``."""
        with self._lock:
            if key == "views":
                self._views_visible = bool(visible)
                for j, h in enumerate(self._frustums):
                    h.visible = visible and j != getattr(self, "_looking", None)
            elif key in self._handles:
                self._handles[key].visible = visible

    # ------------------------------------------------------------ carve by view
    def set_carved_by_view(self, views, occupancy, grid, *, shell=2):
        """Colour the carved-away space near the hull by the view that removed it.

        Parameters
        ----------
        views : grid.shape int16
            From :func:`organlab.carving.carving_views` (-1 = kept).
        occupancy : grid.shape bool
        grid : VoxelGrid
        shell : int
            Carved voxels within this many voxels of the hull are shown.
        """
        near = _scene.near_hull(views, occupancy, shell)
        idx = np.argwhere(near)
        which = views[near]
        pts = grid.centers(idx).astype(np.float32)
        with self._lock:
            self._carved = (pts, which, grid.voxel_size)
        self.show_carve_step(None)

    def show_carve_step(self, view=None, *, visible=True):
        """Show the carved voxels of one view (``None``: of all views, each in its colour)."""
        with self._lock:
            if self._carved is None:
                return 0
            pts, which, size = self._carved
            pal = _scene.view_palette(max(len(self.cameras), int(which.max(initial=0)) + 1))
            if view is not None:
                sel = which == int(view)
                pts, which = pts[sel], which[sel]
            self._points("carved", pts, pal[which], size * 0.6, visible=visible)
            return len(pts)
