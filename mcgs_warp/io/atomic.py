"""Atomic file output and image I/O.

Every file a run writes goes to a temporary name beside its final one and is
renamed into place (``os.replace``, then the folder is fsynced), so an interrupted run
or a power loss never leaves a truncated file under a final name, and a rename is on disk
before whatever follows it (a checkpoint before the segments it replaced are deleted). The file gets the mode a plain ``open()`` would
give it (``0o666`` less the umask), not the private ``0o600`` of a temporary file.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import numpy as np

from ..errors import InputError


def _umask() -> int:
    """The process umask, read without changing it where the OS allows (Linux)."""
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    mask = os.umask(0o077)  # elsewhere set-and-restore; restrictive in between
    os.umask(mask)
    return mask


def _fsync_dir(folder: Path) -> None:
    """Flush a folder's entries (a rename into it) to disk; a no-op where folders cannot be opened."""
    with contextlib.suppress(OSError, AttributeError):
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def atomic_write(path, mode: str = "w", **kwargs):
    """Open a temporary file beside ``path``; rename it to ``path`` when the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
        _fsync_dir(path.parent)  # the rename itself reaches the disk before anything that relies on it
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_image(path, image: np.ndarray) -> None:
    """Write an image atomically: ``[H,W,3]`` float RGB in [0,1] (8-bit) or ``[H,W]`` uint16;
    PNG, or JPEG (quality 90) where ``path`` ends in ``.jpg``."""
    import cv2

    jpeg = Path(path).suffix.lower() in (".jpg", ".jpeg")
    if image.dtype == np.uint16:
        data = image
    else:
        data = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        if data.ndim == 3:
            data = np.ascontiguousarray(data[..., ::-1])  # RGB -> BGR for OpenCV
    ok, buf = cv2.imencode(".jpg", data, [cv2.IMWRITE_JPEG_QUALITY, 90]) if jpeg else cv2.imencode(".png", data)
    if not ok:
        raise OSError(f"{path}: could not encode {'JPEG' if jpeg else 'PNG'}")
    with atomic_write(path, "wb") as f:
        f.write(buf.tobytes())


def read_image(path, expected_size: tuple[int, int] | None = None, depth: bool = False) -> np.ndarray:
    """Read an image file.

    ``depth=False``: colour (or grey, replicated) as ``[H,W,3]`` float32 RGB in [0,1].
    ``depth=True``: a 16-bit PNG as ``[H,W]`` uint16 (scale it yourself).
    ``expected_size`` ``(width, height)`` is checked; errors name the file."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "image file is missing")
    flags = cv2.IMREAD_UNCHANGED if depth else cv2.IMREAD_COLOR
    img = cv2.imread(str(path), flags)
    if img is None:
        raise InputError(path, None, "could not read image (unreadable or not an image)")
    if depth:
        if img.dtype != np.uint16 or img.ndim != 2:
            raise InputError(path, None, f"expected a single-channel 16-bit depth PNG, got {img.dtype} with shape {img.shape}")
    else:
        img = img[..., ::-1].astype(np.float32) / 255.0
    if expected_size is not None and (img.shape[1], img.shape[0]) != tuple(expected_size):
        w, h = expected_size
        raise InputError(path, None, f"expected image size {w}x{h}, got {img.shape[1]}x{img.shape[0]}")
    return np.ascontiguousarray(img)
