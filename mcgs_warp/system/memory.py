"""Host memory of a long run: give freed heap memory back to the operating system.

glibc's ``malloc`` keeps freed blocks inside its heap for reuse, and after a large block
(above its 128 KiB mmap threshold) is freed once, it raises that threshold and serves later
blocks of that size from the heap too. A run allocates and frees images, flow fields, depth
maps and correspondence arrays of 0.1-10 MB at every keyframe between arrays that stay (the
map, the keyframe buffer), so the heap's free space grows with the run: on a 30-frame
synthetic street drive (3 cameras, RGB only, every frame a keyframe) the resident memory was
1.19 GB at the end of tracking, 0.83 GB with that free space returned after each keyframe
(docs/results.md, scaling). :func:`release_freed_memory` returns it (``malloc_trim``: free
pages inside the heap too, not only at its top); the system calls it after every keyframe
and each offline stage. It costs a walk over the free lists (about a millisecond).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

_trim = None


def release_freed_memory() -> bool:
    """Return the heap's free pages to the operating system (glibc; elsewhere nothing to do).
    True where it ran."""
    global _trim
    if _trim is None:
        _trim = False
        if sys.platform.startswith("linux"):
            try:
                libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
                _trim = libc.malloc_trim  # glibc only: musl has none
                _trim.argtypes, _trim.restype = [ctypes.c_size_t], ctypes.c_int
            except (OSError, AttributeError):
                _trim = False
    if not _trim:
        return False
    _trim(0)
    return True
