"""Synchronized multi-camera sequences, and our own folder format.

A :class:`Sequence` is a rig plus frames: ``seq[k]`` loads frame k lazily (one
image per camera, optional depth), so a long sequence never sits in memory.

Our folder format::

    rig.yaml                   the rig (mcgs_warp.rig)
    timestamps.txt             one timestamp per frame, seconds, increasing
    cam<i>/rgb/<index>.png     colour, index zero-padded to 6 digits (000000.png)
    cam<i>/depth/<index>.png   optional: 16-bit depth in millimetres (0 = none; at most 65.535 m)
    groundtruth.txt            optional: rig body poses T_w_b, TUM format
    metadata.yaml              ``depth: exact | mono | none``, required when cam<i>/depth
                               exists: whether it is exact sensor depth, an inexact
                               monocular-style prior (JDSA rescales it), or to be ignored
    gt/cam<i>/depth/<index>.png  optional: exact depth, read only for evaluation
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError, warn
from ..rig import Rig, load_rig, save_rig
from .trajectory import MAX_ASSOCIATION_DT, Trajectory, read_tum, write_tum

DEPTH_SCALE_MM = 1000.0  # our depth PNGs: uint16 millimetres
METADATA = "metadata.yaml"  # what the folder's depth is: exact | mono | none
DEPTH_KINDS = ("exact", "mono", "none")
MAX_SYNC_DT = 0.005  # s: images of two cameras this close are one rig frame (readers that pair streams)
MAX_UNMATCHED_FRACTION = 0.10  # readers: more frames than this without a partner is worth a word


@dataclass
class Frame:
    """One synchronized rig frame."""

    index: int
    timestamp: float  # s, rig clock
    images: list  # per camera: [H,W,3] float32 RGB in [0,1]
    depths: list  # per camera: [H,W] float32 m (0 = no depth), or None


class Sequence:
    """Base class of the readers: a rig, timestamps, lazily loaded frames, optional ground truth."""

    rig: Rig
    timestamps: np.ndarray  # [K] s
    groundtruth: Trajectory | None = None  # rig body poses T_w_b
    name: str = ""
    #: whether the frames' depth is exact sensor depth (else an inexact prior that JDSA rescales)
    depth_exact: bool = True
    #: [3] direction of gravity in the ground truth's world frame where the reader knows it (plots' top view)
    gravity = None

    def depth_cameras(self) -> list[bool]:
        """Per camera: does the sequence carry depth for it (on every frame; a frame may hold
        0 = unknown pixels)? Readers that read depth override this from their file lists, never
        from one decoded frame; depth on some frames only is an error or a documented
        dropout there, never a silent mode switch. The base class has none."""
        return [False] * len(self.rig)

    def gt_depths(self, k: int) -> list | None:
        """Exact depth of frame ``k`` per camera [H,W] (m), for evaluation and oracle
        correspondences only, or ``None`` where the sequence has none. Never used by
        tracking or mapping."""
        return None

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, k: int) -> Frame:
        if not -len(self) <= k < len(self):
            raise IndexError(f"frame {k} out of range for {len(self)} frames")
        k = k % len(self)
        return self.load_frame(k)

    def __iter__(self):
        for k in range(len(self)):
            yield self.load_frame(k)

    def load_frame(self, k: int) -> Frame:
        raise NotImplementedError


class CameraSubset(Sequence):
    """A sequence restricted to some of its rig's cameras (``--cameras 0,2``)."""

    def __init__(self, seq: Sequence, cameras):
        cameras = list(cameras)
        for c in cameras:
            if not 0 <= c < len(seq.rig):
                raise InputError(None, "--cameras", f"camera index {c} out of range: the rig has {len(seq.rig)} cameras (0-{len(seq.rig) - 1})")
        if len(set(cameras)) != len(cameras) or not cameras:
            raise InputError(None, "--cameras", f"expected distinct camera indices, got {cameras}")
        self.seq, self.cameras = seq, cameras
        self.rig = seq.rig.subset(cameras)
        self.timestamps, self.groundtruth, self.name = seq.timestamps, seq.groundtruth, seq.name
        self.depth_exact, self.gravity = seq.depth_exact, seq.gravity

    def load_frame(self, k: int) -> Frame:
        f = self.seq[k]
        return Frame(f.index, f.timestamp, [f.images[c] for c in self.cameras], [f.depths[c] for c in self.cameras])

    def depth_cameras(self) -> list[bool]:
        has = self.seq.depth_cameras()
        return [has[c] for c in self.cameras]

    def gt_depths(self, k: int) -> list | None:
        d = self.seq.gt_depths(k)
        return None if d is None else [d[c] for c in self.cameras]


class FrameSelection(Sequence):
    """Frames ``start, start + step, ...`` before ``stop`` of a sequence (``run --frames A:B``: a
    part of a sequence; ``run --every N``: a high-rate camera at a lower rate, or a drive with
    frames dropped, tracking under larger motion). Frame ``k`` here is frame ``start + k *
    step`` of ``seq``; the ground truth stays whole (evaluation matches by time)."""

    def __init__(self, seq: Sequence, step: int = 1, start: int = 0, stop: int | None = None):
        if isinstance(step, bool) or not isinstance(step, int) or step < 1:
            raise InputError(None, "--every", f"expected a whole number of frames of at least 1, got {step!r}")
        n = len(seq)
        stop = n if stop is None else stop
        if not 0 <= start < stop <= n:
            raise InputError(None, "--frames", f"expected A:B with 0 <= A < B <= {n} (the sequence's {n} frames), got {start}:{stop}")
        kept = (stop - start - 1) // step + 1
        if kept < 2:
            raise InputError(None, "--every" if step > 1 else "--frames", f"keeps only 1 of the {stop - start} frames {start}:{stop}: expected at least 2")
        self.seq, self.step, self.start = seq, step, start
        self.rig = seq.rig
        self.timestamps = np.asarray(seq.timestamps)[start:stop:step]
        self.groundtruth, self.name = seq.groundtruth, seq.name
        self.depth_exact, self.gravity = seq.depth_exact, seq.gravity

    def load_frame(self, k: int) -> Frame:
        f = self.seq[self.start + k * self.step]
        return Frame(k, f.timestamp, f.images, f.depths)

    def depth_cameras(self) -> list[bool]:
        return self.seq.depth_cameras()

    def gt_depths(self, k: int) -> list | None:
        return self.seq.gt_depths(self.start + k * self.step)


def parse_frames(text: str | None) -> tuple[int, int | None]:
    """``--frames A:B`` as ``(A, B)``: frames A up to B (exclusive, as a Python slice); either may
    be left out (``:B``, ``A:``); None gives ``(0, None)``, every frame."""
    if text is None:
        return 0, None
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        a = int(parts[0]) if parts[0].strip() else 0
        b = int(parts[1]) if parts[1].strip() else None
    except ValueError:
        raise InputError(None, "--frames", f"expected A:B (whole frame numbers, B exclusive, e.g. 0:50), got {text!r}") from None
    return a, b


def read_timestamps(path) -> np.ndarray:
    """One timestamp per line (extra columns ignored), strictly increasing."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "file not found")
    stamps = []
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            t = float(line.split()[0])
        except ValueError:
            raise InputError(path, f"line {lineno}", f"expected a timestamp in seconds, got {line!r}") from None
        if not np.isfinite(t):
            raise InputError(path, f"line {lineno}", "timestamp is NaN or Inf")
        if stamps and t <= stamps[-1]:
            raise InputError(path, f"line {lineno}", f"timestamps must increase, got {t} after {stamps[-1]}")
        stamps.append(t)
    if not stamps:
        raise InputError(path, None, "no timestamps")
    return np.array(stamps)


def frame_name(index: int) -> str:
    return f"{index:06d}.png"


class FolderSequence(Sequence):
    """Reader of our folder format (see module docstring)."""

    def __init__(self, root):
        from ..io import read_image  # noqa: F401  (fail early if OpenCV is missing)

        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError(self.root, None, "sequence folder not found")
        self.name = self.root.name
        self.rig = load_rig(self.root / "rig.yaml")
        offsets = [c.name for c in self.rig.cameras if c.time_offset != 0]
        if offsets:
            warn(self.root / "rig.yaml", f"time_offset of {', '.join(offsets)} is not used: timestamps.txt stamps synchronized frames on the rig clock")
        self.has_gt_depth = all((self.root / "gt" / f"cam{i}" / "depth").is_dir() for i in range(len(self.rig)))
        self.timestamps = read_timestamps(self.root / "timestamps.txt")
        self.has_depth = []
        for i in range(len(self.rig)):
            rgb = self.root / f"cam{i}" / "rgb"
            if not rgb.is_dir():
                raise InputError(rgb, None, f"missing image folder for camera {i} ({self.rig.cameras[i].name})")
            self._check_frame_files(rgb)
            self.has_depth.append((self.root / f"cam{i}" / "depth").is_dir())
        self._read_depth_kind()
        for i, has in enumerate(self.has_depth):
            if has:
                self._check_frame_files(self.root / f"cam{i}" / "depth")
        gt = self.root / "groundtruth.txt"
        self.groundtruth = read_tum(gt) if gt.is_file() else None
        if self.groundtruth is not None:
            self._warn_groundtruth_outside(gt)

    def _read_depth_kind(self) -> None:
        """What ``cam<i>/depth`` is, from ``metadata.yaml``: required beside depth folders
        (exact and inexact depth run differently, and neither is a safe guess); ``depth:
        none`` ignores them (one warning); ``exact`` or ``mono`` without them is an error."""
        meta, folders = self.root / METADATA, [f"cam{i}/depth" for i, h in enumerate(self.has_depth) if h]
        if not meta.is_file():
            if folders:
                raise InputError(meta, None, f"missing: {', '.join(folders)} hold depth; write 'depth: exact' (sensor depth, used as is) or 'depth: mono' (an inexact prior that JDSA rescales) or 'depth: none' (ignore it)")
            kind = "none"
        else:
            kind = read_metadata(self.root)
        if kind == "none" and folders:
            warn(meta, f"says depth: none, so {', '.join(folders)} {'is' if len(folders) == 1 else 'are'} not used")
            self.has_depth = [False] * len(self.has_depth)
        elif kind != "none" and not folders:
            raise InputError(meta, "depth", f"says {kind}, but no cam<i>/depth folder holds depth; say 'depth: none' or add the depth")
        self.depth_exact = kind != "mono"

    def _check_frame_files(self, folder: Path) -> None:
        """Frames 0..K-1 are all in ``folder`` (a gap is a missing frame) and it holds no
        other PNGs (more images than timestamps): a cheap listing now, decoding later."""
        names = {p.name for p in folder.glob("*.png")}
        n, label = len(self), folder.relative_to(self.root).as_posix()
        counts = f"{n} timestamps but {label} holds {len(names)} images"
        for k in range(n):
            if frame_name(k) not in names:
                raise InputError(folder / frame_name(k), None, f"missing frame {k} of {n} (timestamps.txt lists {counts})")
        if len(names) != n:
            raise InputError(self.root / "timestamps.txt", None, f"lists {counts}")

    def _warn_groundtruth_outside(self, path: Path) -> None:
        """One warning when ground-truth poses lie outside the frames' time range by more than
        the association tolerance (another clock, or a file from another sequence)."""

        t0, t1 = float(self.timestamps[0]), float(self.timestamps[-1])
        t = self.groundtruth.timestamps
        outside = int(np.count_nonzero((t < t0 - MAX_ASSOCIATION_DT) | (t > t1 + MAX_ASSOCIATION_DT)))
        if outside:
            warn(
                path,
                f"{outside} of {len(t)} entries lie outside the frames' time range [{t0:.3f}, {t1:.3f}] s "
                f"(timestamps.txt) by more than {MAX_ASSOCIATION_DT} s; they are not used for evaluation",
            )

    def load_frame(self, k: int) -> Frame:
        from ..io import read_image

        images, depths = [], []
        for i, cam in enumerate(self.rig.cameras):
            size = (cam.width, cam.height)
            images.append(read_image(self.root / f"cam{i}" / "rgb" / frame_name(k), size))
            if self.has_depth[i]:
                raw = read_image(self.root / f"cam{i}" / "depth" / frame_name(k), size, depth=True)
                depths.append(raw.astype(np.float32) / DEPTH_SCALE_MM)
            else:
                depths.append(None)
        return Frame(k, float(self.timestamps[k]), images, depths)

    def depth_cameras(self) -> list[bool]:
        return list(self.has_depth)

    def gt_depths(self, k: int) -> list | None:
        """``gt/cam<i>/depth`` when present, else the frame's depth where it is exact."""
        from ..io import read_image

        if self.has_gt_depth:
            return [read_image(self.root / "gt" / f"cam{i}" / "depth" / frame_name(k), (c.width, c.height), depth=True).astype(np.float32) / DEPTH_SCALE_MM for i, c in enumerate(self.rig.cameras)]
        if self.depth_exact and all(self.has_depth):
            return list(self.load_frame(k).depths)
        return None


class FolderWriter:
    """Writes frames in our folder format (atomically, file by file).

    ``depth_kind`` says what ``cam<i>/depth`` holds (written to ``metadata.yaml``):
    ``exact`` (sensor depth, used as is), ``mono`` (an inexact monocular-style prior that
    JDSA rescales) or ``none`` (no depth folder). Exact depth for evaluation only goes to
    ``gt/cam<i>/depth``."""

    def __init__(self, root, rig: Rig, depth_kind: str = "exact"):
        if depth_kind not in DEPTH_KINDS:
            raise ValueError(f"depth_kind: expected one of {DEPTH_KINDS}, got {depth_kind!r}")
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.rig = rig
        self.depth_kind = depth_kind
        self.wrote_depth = False
        save_rig(rig, self.root / "rig.yaml")

    def write_frame(self, k: int, images, depths=None, gt_depths=None) -> None:
        from ..io import write_image

        for i, img in enumerate(images):
            write_image(self.root / f"cam{i}" / "rgb" / frame_name(k), img)
            if depths is not None and depths[i] is not None and self.depth_kind != "none":
                write_image(self.root / f"cam{i}" / "depth" / frame_name(k), depth_to_mm(depths[i]))
                self.wrote_depth = True
            if gt_depths is not None and gt_depths[i] is not None:
                write_image(self.root / "gt" / f"cam{i}" / "depth" / frame_name(k), depth_to_mm(gt_depths[i]))

    def finish(self, timestamps, groundtruth: Trajectory | None = None) -> None:
        from ..io import atomic_write

        with atomic_write(self.root / "timestamps.txt") as f:
            f.writelines(f"{t:.9f}\n" for t in timestamps)
        if groundtruth is not None:
            write_tum(self.root / "groundtruth.txt", groundtruth)
        with atomic_write(self.root / METADATA) as f:
            f.write(f"# What this folder's depth is (mcgs_warp.data.sequence). exact: sensor depth, used as is;\n"
                    f"# mono: an inexact monocular-style prior that JDSA rescales; none: no depth.\n"
                    f"# gt/cam<i>/depth (if present) holds exact depth for evaluation only.\ndepth: {self.depth_kind if self.wrote_depth else 'none'}\n")


def depth_to_mm(depth) -> np.ndarray:
    """Depth [H,W] in m as our uint16 millimetre PNG values (0 = none). Beyond the 65.535 m
    the format holds there is no depth (0), not a saturated wrong one."""
    mm = np.round(np.asarray(depth) * DEPTH_SCALE_MM)  # in the input's precision, as it always was
    return np.where((mm > 0) & (mm <= 65535), mm, 0).astype(np.uint16)


def read_metadata(root: Path) -> str:
    """The folder's depth kind from ``metadata.yaml``."""
    from ..rig import load_yaml

    path = Path(root) / METADATA
    data = load_yaml(path) or {}
    if not isinstance(data, dict):
        raise InputError(path, None, f"expected a mapping, got {type(data).__name__}")
    unknown = sorted(set(data) - {"depth"})
    if unknown:
        raise InputError(path, unknown[0], "unknown key (expected: depth)")
    if "depth" not in data:
        raise InputError(path, "depth", f"missing (expected one of {' | '.join(DEPTH_KINDS)})")
    kind = data["depth"]
    if kind not in DEPTH_KINDS:
        raise InputError(path, "depth", f"expected one of {' | '.join(DEPTH_KINDS)}, got {kind!r}")
    return kind
