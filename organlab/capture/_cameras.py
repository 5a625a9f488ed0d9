"""Cameras for the capture: a common interface, OpenCV ``VideoCapture`` and a folder replay.

Every camera returns RGB ``(H, W, 3)`` uint8 images.  :meth:`CaptureCamera.grab`
first discards ``settle_frames`` frames (a webcam's driver buffers a few
frames taken while the table still moved, and its auto exposure needs a
moment), then averages ``average`` frames (pixel noise down by sqrt(average)).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path

import numpy as np

from ..session import read_image
from ._errors import CameraError

__all__ = ["CaptureCamera", "OpenCVCamera", "FolderCamera"]

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class CaptureCamera(ABC):
    """A camera the capture can trigger.

    Parameters
    ----------
    settle_frames : int
        Frames read and thrown away before each image.
    average : int
        Frames averaged into each image.
    """

    name = "camera"

    def __init__(self, *, settle_frames: int = 2, average: int = 1) -> None:
        if int(settle_frames) < 0 or int(average) < 1:
            raise CameraError(f"settle_frames must be >= 0 and average >= 1, got {settle_frames} and {average}")
        self.settle_frames = int(settle_frames)
        self.average = int(average)

    @abstractmethod
    def _read(self):
        """One frame, RGB (H, W, 3) uint8; raise CameraError when there is none."""

    def _discard(self):
        """Read one frame and throw it away."""
        self._read()

    def grab(self, *, settle_frames: int | None = None, average: int | None = None) -> np.ndarray:
        """Settle, then take one image.

        Returns
        -------
        (H, W, 3) uint8
            RGB; the mean of ``average`` frames, rounded.
        """
        for _ in range(self.settle_frames if settle_frames is None else int(settle_frames)):
            self._discard()
        n = self.average if average is None else int(average)
        if n == 1:
            return self._read()
        acc = None
        for _ in range(n):
            f = self._read().astype(np.float64)
            acc = f if acc is None else acc + f
        return np.clip(np.rint(acc / n), 0, 255).astype(np.uint8)

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class OpenCVCamera(CaptureCamera):
    """A camera opened by OpenCV's ``VideoCapture``: a device index (``0``) or a URL (RTSP/HTTP stream, file).

    Parameters
    ----------
    source : int or str
        Device index, or a string OpenCV understands (a digit string is an index).
    image_size : (2,) int, optional
        ``(width, height)`` asked of the driver; checked on the first frame.
    settle_frames, average : int
        See :class:`CaptureCamera`.
    """

    def __init__(self, source: int | str = 0, *, image_size: tuple[int, int] | None = None, settle_frames: int = 5,
                 average: int = 1) -> None:
        import cv2

        super().__init__(settle_frames=settle_frames, average=average)
        if isinstance(source, str) and source.isdigit():
            source = int(source)
        self.source = source
        self.name = f"opencv:{source}"
        self._cv2 = cv2
        self._cap = cv2.VideoCapture(source)
        if not self._cap.isOpened():
            self._cap.release()
            raise CameraError(f"camera {source!r}: cannot be opened; is it plugged in and not used by another program "
                              f"(list the devices with 'v4l2-ctl --list-devices')?")
        if image_size is not None:
            self._cap.set(cv2.CAP_PROP_FRAME_WIDTH, int(image_size[0]))
            self._cap.set(cv2.CAP_PROP_FRAME_HEIGHT, int(image_size[1]))
        self.wanted_size = None if image_size is None else (int(image_size[0]), int(image_size[1]))

    def _read(self):
        if self._cap is None:
            raise CameraError(f"camera {self.source!r}: already closed")
        ok, frame = self._cap.read()
        if not ok or frame is None:
            raise CameraError(f"camera {self.source!r}: returned no frame; was it unplugged?")
        if self.wanted_size is not None and (frame.shape[1], frame.shape[0]) != self.wanted_size:
            raise CameraError(f"camera {self.source!r}: gives {frame.shape[1]}x{frame.shape[0]} images, not the "
                              f"{self.wanted_size[0]}x{self.wanted_size[1]} asked for; choose a size it supports")
        if frame.ndim == 2:
            frame = np.repeat(frame[:, :, None], 3, axis=2)
        return np.ascontiguousarray(frame[:, :, 2::-1])

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class FolderCamera(CaptureCamera):
    """Replays the images of a folder in name order, one per :meth:`grab` (settling and averaging do not apply).

    Useful to test a capture set-up, or to re-file images taken by another program.
    """

    def __init__(self, folder: str | Path) -> None:
        super().__init__(settle_frames=0, average=1)
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise CameraError(f"{self.folder}: folder to replay does not exist")
        self.files = sorted(p for p in self.folder.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES)
        if not self.files:
            raise CameraError(f"{self.folder}: no images (png, jpg, bmp, tif) to replay")
        self.name = f"folder:{self.folder}"
        self._next = 0

    def grab(self, *, settle_frames: int | None = None, average: int | None = None) -> np.ndarray:
        return self._read()

    def _read(self):
        if self._next >= len(self.files):
            raise CameraError(f"{self.folder}: all {len(self.files)} images replayed; the capture needs more")
        path = self.files[self._next]
        self._next += 1
        img = read_image(path)
        return img if img.ndim == 3 else np.repeat(img[:, :, None], 3, axis=2)
