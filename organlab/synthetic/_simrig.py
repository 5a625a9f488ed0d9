"""A simulated rig: an MDrive controller on the far end of a real serial link, and a camera rendering the phantom.

The controller runs in a thread on the master side of a pseudo-terminal pair
(``os.openpty()``, both ends raw); the driver opens the slave side by its
name with pyserial, exactly as it opens ``/dev/ttyUSB0``.  Faults can be
injected: a dropped or garbled answer, a stall, lost steps, an unplugged
cable (the master side is closed, so the port fails as a pulled USB adapter
does).  The camera renders the synthetic scene (:mod:`organlab.synthetic`)
at the table's *physical* angle, so an angle the controller does not know
about (a slipping plate, :attr:`SimRig.slip_deg`) shows in the images only.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty

import numpy as np

from ..capture import CaptureCamera, MDriveTurntable
from ..errors import SettingsError
from ..session import DEFAULT_PATTERN
from . import _render
from ._boards import BOARD_MARGIN, default_camera, intrinsic_board_poses, turntable_board_pose
from ._specimens import make_specimen

__all__ = ["MDriveSimulator", "SimRig", "SimCamera"]

_FAULTS = ("drop", "garble", "stall", "lost_steps", "unplug")
#: Environment variable: every simulated move runs this many times faster again than its ``time_scale`` says
#: (default 1).  For test runs (tests/conftest.py sets it for the run and its subprocesses): a simulated
#: table's move is a real-time wait (``organlab capture --turntable sim`` at step 120: 2.1 s of its 8.7 s),
#: and no test asserts on how long a move takes.
SPEEDUP_ENV = "ORGANLAB_SIM_SPEEDUP"


def _speedup():
    text = os.environ.get(SPEEDUP_ENV, "").strip()
    try:
        value = float(text) if text else 1.0
    except ValueError:
        value = float("nan")
    if not value > 0 or value == float("inf"):
        # a SettingsError (a ValueError too): the command line says it in one line, exit status 2
        raise SettingsError(SPEEDUP_ENV, f"must be a positive number, got {text!r}; unset it for real-time moves")
    return value


class MDriveSimulator:
    """An MCode controller with an encoder, served on a pty; ``port`` is the name to open.

    Parameters
    ----------
    steps_per_deg : float
        Motor microsteps per table degree at the factory microstep setting
        (``MS`` changes the scale as on the real controller).
    microsteps : int
        Factory ``MS``.
    start_steps : int
        Physical motor position at power-up, microsteps from the home switch.
    time_scale : float
        Simulated moves run this many times faster than the real ones (times ``ORGANLAB_SIM_SPEEDUP``
        when set: test runs).
    party_name : str, optional
        Start in party mode (``PY=1``) with this device name.
    """

    def __init__(self, *, steps_per_deg, microsteps=256, start_steps=0, time_scale=1.0, party_name=None):
        self.steps_per_deg_factory = float(steps_per_deg)
        self.ms_factory = int(microsteps)
        self.vars = {"EM": 0, "MS": int(microsteps), "RC": 25, "HC": 5, "VM": 768000, "VI": 1000, "A": 1000000,
                     "D": 1000000, "ST": 0, "ER": 0, "PY": int(party_name is not None), "EE": 1}
        self.name = party_name
        self.time_scale = float(time_scale) * _speedup()
        self._origin = 0.0  # motor position (factory microsteps) where P = 0
        self._move = (float(start_steps), float(start_steps), 0.0, 0.0)  # m0, m1, t0, t1
        self.faults = []
        self.received = []
        self.unplugged = False
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)
        self._thread = threading.Thread(target=self._serve, name="mdrive-sim", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------ faults
    def inject(self, kind, *, on=None, after=0, count=1, steps=0, fraction=0.5):
        """Inject a fault.

        Parameters
        ----------
        kind : {"drop", "garble", "stall", "lost_steps", "unplug"}
            ``drop``: no answer; ``garble``: a corrupted answer; ``stall``: the
            move stops at ``fraction`` of its way and the stall flag ``ST`` is
            set; ``lost_steps``: the move ends ``steps`` microsteps short;
            ``unplug``: the link goes dead when the command arrives.
        on : str, optional
            Command prefix the fault waits for (``"MA"``, ``"PR P"``); any
            command when omitted (stall and lost steps: any move).
        after : int
            Matching commands let through before the fault strikes.
        count : int
            Matching commands the fault strikes.
        """
        if kind not in _FAULTS:
            raise ValueError(f"fault must be one of {_FAULTS}, got {kind!r}")
        with self._lock:
            self.faults.append({"kind": kind, "on": on, "after": int(after), "count": int(count), "steps": int(steps), "fraction": float(fraction)})

    def clear_faults(self):
        with self._lock:
            self.faults.clear()

    def _take_fault(self, cmd, kinds):
        for f in self.faults:
            if f["kind"] not in kinds or f["count"] <= 0:
                continue
            prefix = f["on"] or ("M" if f["kind"] in ("stall", "lost_steps") else "")
            if not cmd.upper().startswith(prefix):
                continue
            if f["after"] > 0:
                f["after"] -= 1
                continue
            f["count"] -= 1
            return f
        return None

    # ------------------------------------------------------------ motion
    def _scale(self):
        return self.vars["MS"] / self.ms_factory  # controller microsteps per factory microstep

    def motor_steps(self, now=None):
        """Physical motor position, factory microsteps from the home switch."""
        m0, m1, t0, t1 = self._move
        now = time.monotonic() if now is None else now
        if now >= t1 or t1 <= t0:
            return m1
        return m0 + (m1 - m0) * (now - t0) / (t1 - t0)

    def table_angle_deg(self):
        """The table's physical angle, degrees (0 at the home switch)."""
        with self._lock:
            return self.motor_steps() / self.steps_per_deg_factory

    def moving(self):
        return time.monotonic() < self._move[3]

    def _start_move(self, target_factory, fault):
        now = time.monotonic()
        m0 = self.motor_steps(now)
        m1 = float(target_factory)
        if fault is not None and fault["kind"] == "stall":
            m1 = m0 + (m1 - m0) * fault["fraction"]
            self.vars["ST"] = 1
            self.vars["ER"] = 86
        elif fault is not None and fault["kind"] == "lost_steps":
            m1 -= np.sign(m1 - m0) * fault["steps"] / self._scale()
        vm = max(self.vars["VM"], 1) / self._scale()
        duration = (abs(m1 - m0) / vm + 0.01) / self.time_scale
        self._move = (m0, m1, now, now + duration)

    def _position(self):
        return int(round((self.motor_steps() - self._origin) * self._scale()))

    # ---------------------------------------------------------- commands
    def _execute(self, cmd):
        """Run one command; return the answer text for PR commands, '' for others, None when unknown."""
        c = cmd.strip()
        u = c.upper()
        if u.startswith("PR "):
            key = u[3:].strip()
            if key == "MV":
                return str(int(self.moving()))
            if key == "P":
                return str(self._position())
            if key in self.vars:
                return str(self.vars[key])
            return None
        if u.startswith(("MA ", "MR ", "HM ", "SL ")):
            op, arg = u[:2], u[3:].strip()
            try:
                v = int(arg)
            except ValueError:
                return None
            fault = self._take_fault(u, ("stall", "lost_steps")) if op in ("MA", "MR") else None
            s = 1.0 / self._scale()
            if op == "MA":
                self._start_move(self._origin + v * s, fault)
            elif op == "MR":
                self._start_move(self.motor_steps() + v * s, fault)
            elif op == "HM":
                self._start_move(0.0, None)  # the switch is at the physical 0
            elif op == "SL" and v == 0:
                m = self.motor_steps()
                self._move = (m, m, 0.0, 0.0)
            return ""
        if "=" in u:
            key, _, value = u.partition("=")
            key = key.strip()
            if key == "P":
                self._origin = self.motor_steps() - int(value) / self._scale()
                return ""
            if key == "S1" or key == "DN":
                return ""
            try:
                self.vars[key] = int(value)
            except ValueError:
                return None
            return ""
        return None

    def _answer(self, cmd, result, fault):
        em = self.vars["EM"]
        if result is None:
            self.vars["ER"] = 20
        if em == 0:
            body = cmd + "\r\n" + ("" if not result else result + "\r\n") + ("?" if result is None else ">")
        elif em == 2 and not cmd.upper().startswith("PR"):
            return b""
        else:
            body = ("?" if result is None else result) + "\r\n"
        if fault is not None and fault["kind"] == "garble":
            return b"\x9c#" + body.encode("ascii")[::-1] + b"\r\n"
        return body.encode("ascii")

    def _handle_line(self, line):
        text = line.decode("ascii", "replace")
        if self.vars["PY"]:
            if not self.name or not text.startswith(self.name):
                return b""  # addressed to another device
            text = text[len(self.name):]
        if not text.strip():
            return b""
        with self._lock:
            self.received.append(text)
            fault = self._take_fault(text, ("drop", "garble", "unplug"))
            if fault is not None and fault["kind"] == "unplug":
                self.unplugged = True
                return None
            result = self._execute(text)
            if fault is not None and fault["kind"] == "drop":
                return b""
            return self._answer(text, result, fault)

    def _serve(self):
        buf = b""
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self.master], [], [], 0.05)
                if not ready:
                    continue
                data = os.read(self.master, 1024)
            except OSError:
                return
            if not data:
                return
            buf += data
            while True:
                cut = [i for i in (buf.find(b"\r"), buf.find(b"\n")) if i >= 0]
                if not cut:
                    break
                i = min(cut)
                line, buf = buf[:i], buf[i + 1:]
                out = self._handle_line(line)
                if out is None:
                    self._unplug()
                    return
                if out:
                    os.write(self.master, out)

    def _unplug(self):
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def close(self):
        """Stop the thread and close the pty (idempotent)."""
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)
        if not self.unplugged:
            self.unplugged = True
            self._unplug()


class SimRig:
    """A whole simulated rig: MDrive controller on a pty, table, specimen, board and camera.

    Parameters
    ----------
    specimen : {"aaa", "grooved"} or organlab.synthetic.Specimen
    image_size : (2,) int
        ``(width, height)`` of the simulated camera (intrinsics scale with it).
    supersample : int
        Sub-pixel samples per axis when rendering the specimen and the empty scene.
    board_supersample : int
        The same for the board images (corner detection needs less; rendering the board costs more).
    noise_sigma : float
        Pixel noise, grey levels, new in every frame.
    seed : int
        Seed of the noise and of the hand-held board poses.
    steps_per_rev, microsteps, gear_ratio : int, int, float
        The simulated drive (the driver must be given the same to turn true angles).
    start_deg : float
        Physical table angle at power-up (homing brings it to 0).
    time_scale : float
        Moves run this many times faster than on the real table.
    party_name : str, optional
        Controller in party mode with this name.
    """

    def __init__(self, *, specimen="aaa", image_size=(320, 240), supersample=2, board_supersample=None, noise_sigma=1.5, seed=0,
                 steps_per_rev=200, microsteps=256, gear_ratio=90.0, start_deg=7.3, time_scale=1.0, party_name=None):
        self.specimen = make_specimen(specimen)
        self.camera_model = default_camera(image_size)
        self.pattern = DEFAULT_PATTERN
        self.supersample = int(supersample)
        self.board_supersample = int(supersample if board_supersample is None else board_supersample)
        self.noise_sigma = float(noise_sigma)
        self.seed = int(seed)
        self.drive = {"steps_per_rev": int(steps_per_rev), "microsteps": int(microsteps), "gear_ratio": float(gear_ratio)}
        steps_per_deg = steps_per_rev * microsteps * gear_ratio / 360.0
        self.controller = MDriveSimulator(steps_per_deg=steps_per_deg, microsteps=microsteps,
                                          start_steps=int(round(start_deg * steps_per_deg)), time_scale=time_scale,
                                          party_name=party_name)
        self.party_name = party_name
        #: Angle by which the plate has slipped on the motor shaft, deg (seen by the camera, not by the controller).
        self.slip_deg = 0.0
        #: What stands on the table: "empty", "board", "specimen" or ("hand", k) for a hand-held board pose.
        self.scene = "empty"
        self._hand_poses = {}

    @property
    def port(self):
        return self.controller.port

    @property
    def volume_mm3(self):
        """The specimen's exact volume, mm^3."""
        return float(self.specimen.volume)

    def turntable(self, **kw):
        """An :class:`~organlab.capture.MDriveTurntable` on this rig's port, set up like the simulated drive."""
        opts = dict(self.drive, home_switch=True, device_name=self.party_name, timeout=0.3, poll_interval=0.01)
        opts.update(kw)
        return MDriveTurntable(self.port, **opts)

    def camera(self, **kw):
        return SimCamera(self, **kw)

    def prompt(self, stage, message, index=None):
        """Do what the capture asks a person to do (``stage``: "background", "intrinsics", "turntable", "views")."""
        self.scene = {"background": "empty", "turntable": "board", "views": "specimen"}.get(stage, self.scene)
        if stage == "intrinsics":
            self.scene = ("hand", int(index or 0))

    def hand_pose(self, k):
        if k not in self._hand_poses:
            n = max(16, k + 1)
            for i, pose in enumerate(intrinsic_board_poses(self.camera_model, n, pattern=self.pattern, seed=self.seed)):
                self._hand_poses.setdefault(i, pose)
        return self._hand_poses[k]

    def close(self):
        self.controller.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class SimCamera(CaptureCamera):
    """The rig's camera: renders what stands on the table at the table's physical angle."""

    def __init__(self, rig, *, settle_frames=2, average=1):
        super().__init__(settle_frames=settle_frames, average=average)
        self.rig = rig
        self.name = "sim"
        self._cache_key = None
        self._cache = None
        self._frame = 0

    @property
    def image_size(self):
        return self.rig.camera_model.image_size

    def _clean(self):
        rig = self.rig
        angle = round(rig.controller.table_angle_deg() + rig.slip_deg, 9)
        key = (rig.scene, angle)
        if key != self._cache_key:
            cam = rig.camera_model.at_table_angle(angle)
            ss = rig.supersample
            p = rig.pattern
            if rig.scene == "specimen":
                img = _render.render(cam, supersample=ss, specimen=rig.specimen)
            elif rig.scene == "board":
                Rb, tb = turntable_board_pose(p)
                img = _render.render(cam, supersample=rig.board_supersample, board=(Rb, tb, p.inner_corners, p.square_size, BOARD_MARGIN))
            elif isinstance(rig.scene, tuple):
                Rb, tb = rig.hand_pose(rig.scene[1])
                cam0 = rig.camera_model.with_pose(np.eye(3), np.zeros(3))
                img = _render.render(cam0, supersample=rig.board_supersample, board=(Rb, tb, p.inner_corners, p.square_size, BOARD_MARGIN), plate=False)
            else:
                img = _render.render(cam, supersample=ss)
            self._cache_key, self._cache = key, img
        return self._cache

    def _discard(self):
        self._frame += 1  # a frame passes (nothing to render: it is thrown away)

    def _read(self):
        self._frame += 1
        rng = np.random.default_rng([self.rig.seed, 99, self._frame])
        return _render.quantize(self._clean(), self.rig.noise_sigma, rng)
