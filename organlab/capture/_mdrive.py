"""Turntable drivers: the :class:`Turntable` interface and an MDrive (MCode) driver over pyserial.

MCode as the MDrive Plus / MForce manuals describe it: one ASCII command per
line, ended by CR (or, in party mode, prefixed with the device name ``DN``
and ended by LF).  The driver puts the controller in echo mode 1 (``EM=1``,
half duplex: no echo, no prompt), where every command is answered by one
line ended by CR LF: empty for a set-up or motion command, the value for a
``PR`` (print) command; a line starting with ``?`` is an error.

Every command the driver sends is idempotent (set-ups, absolute moves ``MA``,
prints), so a dropped or garbled answer is simply asked again; relative moves
(``MR``, :meth:`MDriveTurntable.move_by`) are not, and are checked against
the position read back instead of being repeated.
"""

from __future__ import annotations

import re
import time
from abc import ABC, abstractmethod
from datetime import datetime, timezone
from pathlib import Path
from threading import Lock

from ._errors import (
    DisconnectedError,
    GarbledReplyError,
    NoReplyError,
    PositionError,
    StallError,
    TurntableError,
)

__all__ = ["Turntable", "MDriveTurntable", "SerialLog"]

_INT = re.compile(r"^-?\d+$")


class Turntable(ABC):
    """What the capture needs from a rotary table; other controllers (GRBL, ...) implement the same.

    Angles are degrees, right-handed about the table axis (+Z, up), 0 at the
    home position (or where :meth:`zero` was called).
    """

    #: The table has a home switch (:meth:`home` works).
    has_home_switch = False

    def __init__(self) -> None:
        #: Notable things that happened (retries, corrected lost steps): dicts with ``kind`` and ``message``.
        self.events = []

    @abstractmethod
    def move_to(self, angle_deg: float) -> float:
        """Move to ``angle_deg``, wait until the table stands still, verify; return the angle read back (deg)."""

    @abstractmethod
    def angle(self) -> float:
        """The table's current angle, degrees, as the controller reports it."""

    @abstractmethod
    def home(self) -> float:
        """Find the home switch and make that angle 0."""

    @abstractmethod
    def zero(self) -> None:
        """Take the current position as angle 0 (tables without a home switch)."""

    @abstractmethod
    def close(self) -> None:
        """Release the port."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class SerialLog:
    """Log of every serial exchange, one line each: time, direction, text.

    ``>`` is what the host sent, ``<`` what it received, ``!`` the driver's
    remarks (timeouts, retries).  ``path=None`` keeps the lines in memory only.
    """

    def __init__(self, path: str | Path | None = None) -> None:
        self.path = None if path is None else Path(path)
        self.lines = []
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)

    def __call__(self, direction, text):
        stamp = datetime.now(timezone.utc).strftime("%H:%M:%S.%f")[:-3]
        line = f"{stamp} {direction} {text}"
        self.lines.append(line)
        if self.path is not None:
            with open(self.path, "a", encoding="utf-8") as f:
                f.write(line + "\n")


class MDriveTurntable(Turntable):
    """An MDrive-style stepper controller (MCode) turning a rotary table, over a serial port.

    Parameters
    ----------
    port : str
        Serial port name (``/dev/ttyUSB0``, ``COM3``, a pty's name) or a
        pyserial URL.
    baudrate : int
        9600 is the MDrive's factory setting.
    steps_per_rev : int
        Full steps per motor revolution (200 for a 1.8 deg motor).
    microsteps : int
        Microstep resolution sent as ``MS``.
    gear_ratio : float
        Motor revolutions per table revolution (90 for a 90:1 worm table).
        A wrong value gives a twisted model: check it with the angle audit.
    run_current, hold_current : int
        Percent of the rated current (``RC``, ``HC``).
    speed_deg_s, accel_deg_s2 : float
        Table speed and acceleration (``VM``, and ``A`` = ``D``), deg/s and deg/s^2.
    device_name : str, optional
        Party mode: every command is prefixed by this one-character name and
        ended by LF (the controller must have ``PY=1`` and ``DN`` set).
    home_switch : bool
        A home switch is wired to input 1 (set up as ``S1=1,0,0``); :meth:`home`
        runs ``HM 1``.
    timeout : float, s
        Time allowed for one answer.
    retries : int
        Times a command is sent again after no answer or a garbled one.
    move_timeout : float, s
        Time allowed for a move (or homing) to end.
    poll_interval : float, s
        Time between two ``PR MV`` while waiting for a move to end.
    tolerance_deg : float
        Largest difference between the commanded and the read-back position.
    corrections : int
        Moves sent again when the read-back shows lost steps before
        :class:`PositionError` is raised.
    log : SerialLog or str or Path, optional
        Where every exchange is logged.
    """

    has_home_switch = False

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 9600,
        steps_per_rev: int = 200,
        microsteps: int = 256,
        gear_ratio: float = 90.0,
        run_current: int = 75,
        hold_current: int = 25,
        speed_deg_s: float = 30.0,
        accel_deg_s2: float = 120.0,
        device_name: str | None = None,
        home_switch: bool = False,
        timeout: float = 1.0,
        retries: int = 2,
        move_timeout: float = 60.0,
        poll_interval: float = 0.02,
        tolerance_deg: float = 0.01,
        corrections: int = 1,
        log: SerialLog | None = None,
    ) -> None:
        import serial

        super().__init__()
        for label, v in (("steps_per_rev", steps_per_rev), ("microsteps", microsteps), ("gear_ratio", gear_ratio)):
            if not v > 0:
                raise TurntableError(f"{port}: {label} must be > 0, got {v}")
        if device_name is not None and (len(str(device_name)) != 1 or not str(device_name).isalnum()):
            raise TurntableError(f"{port}: device_name must be one letter or digit (MCode DN), got {device_name!r}")
        self.port = str(port)
        self.microsteps = int(microsteps)
        self.steps_per_deg = steps_per_rev * microsteps * gear_ratio / 360.0
        self.device_name = None if device_name is None else str(device_name)
        self.has_home_switch = bool(home_switch)
        self.timeout = float(timeout)
        self.retries = int(retries)
        self.move_timeout = float(move_timeout)
        self.poll_interval = float(poll_interval)
        self.tolerance_steps = max(1, int(round(tolerance_deg * self.steps_per_deg)))
        self.corrections = int(corrections)
        self.log = log if isinstance(log, SerialLog) else SerialLog(log)
        self._lock = Lock()
        self._serial_exc = serial.SerialException
        try:
            self._ser = serial.serial_for_url(self.port, baudrate=baudrate, timeout=self.timeout, write_timeout=self.timeout)
        except (serial.SerialException, OSError) as e:
            raise DisconnectedError(f"{self.port}: cannot open the serial port ({e}); is the controller plugged in and the port right?") from None
        self.log("!", f"opened {self.port} at {baudrate} baud")
        try:
            self._setup(run_current, hold_current, speed_deg_s, accel_deg_s2)
        except Exception:
            self.close()
            raise

    # ----------------------------------------------------------- set-up
    def _setup(self, run_current, hold_current, speed_deg_s, accel_deg_s2):
        # The controller may still be in echo mode 0 (echo and prompt): switch, then drop what it said.
        self._write("EM=1")
        time.sleep(min(0.2, self.timeout))
        self._ser.reset_input_buffer()
        try:
            em = self.query("PR EM")
        except NoReplyError:
            raise NoReplyError(f"{self.port}: no answer to 'PR EM'; check the power, the cable, the baud rate and "
                               f"party mode (a controller with PY=1 needs its device name)") from None
        if em != 1:
            raise TurntableError(f"{self.port}: the controller did not switch to echo mode 1 (EM=1); check the baud rate and party mode")
        vm = int(round(speed_deg_s * self.steps_per_deg))
        acc = int(round(accel_deg_s2 * self.steps_per_deg))
        for cmd in (f"MS={self.microsteps}", f"RC={int(run_current)}", f"HC={int(hold_current)}", f"VM={vm}", f"A={acc}", f"D={acc}"):
            self.command(cmd)
        if self.has_home_switch:
            self.command("S1=1,0,0")  # input 1: home switch, active low
        if self.query("PR ST"):
            self.command("ST=0")  # clear a stall flag left from before

    # ------------------------------------------------------- exchanges
    def _write(self, cmd):
        line = f"{self.device_name}{cmd}\n" if self.device_name else f"{cmd}\r"
        self.log(">", cmd if not self.device_name else self.device_name + cmd)
        try:
            self._ser.write(line.encode("ascii"))
        except (self._serial_exc, OSError) as e:
            raise DisconnectedError(f"{self.port}: serial port lost while sending {cmd!r} ({e}); is the controller still plugged in?") from None

    def _read_line(self):
        try:
            raw = self._ser.read_until(b"\n")
        except (self._serial_exc, OSError) as e:
            raise DisconnectedError(f"{self.port}: serial port lost ({e}); is the controller still plugged in?") from None
        return raw

    def _exchange(self, cmd, parse, *, retry=True, skip_blank=False):
        """Send ``cmd``, read one answer line, ``parse(text)`` it; retries on no/garbled answer."""
        tries = 1 + (self.retries if retry else 0)
        last = None
        with self._lock:
            for attempt in range(tries):
                self._ser.reset_input_buffer()  # a late answer to an earlier command must not be taken for this one
                self._write(cmd)
                raw = self._read_line()
                if skip_blank and raw.strip() == b"" and raw.endswith(b"\n"):
                    raw = self._read_line()  # a controller may end the command with CR LF before a printed value
                if not raw.endswith(b"\n"):
                    self.log("!", f"no reply within {self.timeout:g} s" + (f"; retry {attempt + 1}/{tries - 1}" if attempt < tries - 1 else ""))
                    last = "none"
                    continue
                self.log("<", repr(raw.decode("ascii", "replace").rstrip("\r\n"))[1:-1])
                try:
                    text = raw.decode("ascii").strip()
                except UnicodeDecodeError:
                    text = None
                if text is not None and text.startswith("?"):
                    raise TurntableError(f"{self.port}: the controller rejected {cmd!r} (answer {text!r}); see 'PR ER' in the MCode manual")
                value = parse(text) if text is not None and text.isprintable() else _BAD
                if value is not _BAD:
                    if attempt:
                        self.events.append({"kind": "retry", "message": f"{cmd!r} answered after {attempt} retr{'y' if attempt == 1 else 'ies'} ({last} reply before)"})
                    return value
                self.log("!", "garbled reply" + (f"; retry {attempt + 1}/{tries - 1}" if attempt < tries - 1 else ""))
                last = "garbled"
        if last == "none":
            raise NoReplyError(f"{self.port}: no reply to {cmd!r} after {tries} tries ({self.timeout:g} s each); is the controller powered and the baud rate right?")
        raise GarbledReplyError(f"{self.port}: garbled reply to {cmd!r} after {tries} tries; check the baud rate, cable and party mode")

    def command(self, cmd: str, *, retry: bool = True) -> None:
        """Send a set-up or motion command and wait for its (empty) answer."""
        self._exchange(cmd, lambda t: None if t == "" else _BAD, retry=retry)

    def query(self, cmd: str) -> int:
        """Send a ``PR`` command and return its integer answer."""
        return self._exchange(cmd, lambda t: int(t) if _INT.match(t) else _BAD, skip_blank=True)

    # ---------------------------------------------------------- motion
    def _wait_stopped(self, what):
        t_end = time.monotonic() + self.move_timeout
        while self.query("PR MV"):
            if time.monotonic() > t_end:
                self.command("SL 0")
                raise TurntableError(f"{self.port}: {what} did not end within {self.move_timeout:g} s; stopped it (SL 0); check the table")
            time.sleep(self.poll_interval)

    def _verify(self, target, what):
        """Read the position back after a move; raise on a stall; return the difference in steps."""
        pos = self.query("PR P")
        diff = pos - target
        if abs(diff) <= self.tolerance_steps:
            return pos, 0
        if self.query("PR ST"):
            self.command("ST=0")
            raise StallError(f"{self.port}: the motor stalled during {what}: at {pos / self.steps_per_deg:.3f} deg, "
                             f"{abs(diff)} steps short of {target / self.steps_per_deg:.3f} deg; free the table or raise the run current (RC)")
        return pos, diff

    def move_to(self, angle_deg: float) -> float:
        target = int(round(float(angle_deg) * self.steps_per_deg))
        what = f"the move to {angle_deg:g} deg"
        for attempt in range(self.corrections + 1):
            self.command(f"MA {target}")
            self._wait_stopped(what)
            pos, diff = self._verify(target, what)
            if diff == 0:
                return pos / self.steps_per_deg
            msg = (f"lost steps: {what} ended at {pos / self.steps_per_deg:.3f} deg ({diff:+d} steps)")
            self.events.append({"kind": "lost_steps", "message": msg, "angle_deg": float(angle_deg), "steps": int(diff)})
            self.log("!", msg + ("; moving again" if attempt < self.corrections else ""))
        raise PositionError(f"{self.port}: {msg} after {self.corrections} correction(s); check the load, the current and the coupling")

    def move_by(self, delta_deg: float) -> float:
        """Relative move (``MR``); not repeated blindly, the read-back decides whether it ran. Returns the angle."""
        start = self.query("PR P")
        steps = int(round(float(delta_deg) * self.steps_per_deg))
        try:
            self.command(f"MR {steps}", retry=False)
        except DisconnectedError:
            raise
        except NoReplyError:
            self._wait_stopped("a relative move")
            if self.query("PR P") == start:  # the command was lost, not only its answer
                self.command(f"MR {steps}", retry=False)
        what = f"the move by {delta_deg:g} deg"
        self._wait_stopped(what)
        pos, diff = self._verify(start + steps, what)
        if diff:
            raise PositionError(f"{self.port}: lost steps: {what} ended {diff:+d} steps from its target; check the load and the current")
        return pos / self.steps_per_deg

    def angle(self) -> float:
        return self.query("PR P") / self.steps_per_deg

    def home(self) -> float:
        if not self.has_home_switch:
            raise TurntableError(f"{self.port}: no home switch configured (home_switch=False); use zero() at a marked position instead")
        self.command("HM 1")
        self._wait_stopped("homing")
        self.command("P=0")
        if self.query("PR P") != 0:
            raise PositionError(f"{self.port}: position is not 0 after homing (P=0); check the controller")
        return 0.0

    def zero(self) -> None:
        self.command("P=0")

    def close(self) -> None:
        ser = getattr(self, "_ser", None)
        if ser is not None:
            try:
                ser.close()
            except (self._serial_exc, OSError):
                pass
            self._ser = None
            self.log("!", f"closed {self.port}")

    def __repr__(self):
        return f"MDriveTurntable({self.port!r}, {self.steps_per_deg:g} steps/deg)"


class _Bad:
    pass


_BAD = _Bad()
