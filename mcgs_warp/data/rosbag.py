"""ROS bags (ROS 1 ``.bag`` files, ROS 2 bag folders of ``.db3`` or ``.mcap``) as a :class:`Sequence`.

A bag carries images, not calibration: the rig file names each camera's ``topic:``
(``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage``). Read with ``rosbags`` (pure
Python, no ROS install). Opening a bag reads it once, one message at a time, to index the
images' header stamps; a frame's images are read again when the frame is loaded, so a long
bag never sits in memory. Frames are camera 0's images that every other camera has an image
for within ``sync_tolerance`` seconds (closest pairs first, on the rig clock: header stamp
minus the camera's ``time_offset``); images that do not pair are counted in one warning line.
The frame's timestamp is camera 0's. Bags carry no ground truth and no depth here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError, warn
from ..rig import Rig
from .sequence import MAX_SYNC_DT, Frame, Sequence

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
#: Image encodings we decode -> (channels, dtype, order of the colour channels)
ENCODINGS = {"rgb8": (3, np.uint8, "rgb"), "bgr8": (3, np.uint8, "bgr"), "rgba8": (4, np.uint8, "rgb"), "bgra8": (4, np.uint8, "bgr"),
             "mono8": (1, np.uint8, "grey"), "8UC1": (1, np.uint8, "grey"), "mono16": (1, np.uint16, "grey"), "16UC1": (1, np.uint16, "grey"), "8UC3": (3, np.uint8, "bgr")}


def bag_paths(path) -> Path | None:
    """The bag at ``path`` as ``rosbags`` opens it (a ROS 1 file or a ROS 2 folder), or None if
    ``path`` is not a bag."""
    path = Path(path)
    if path.is_file() and path.suffix == ".bag":
        return path
    if path.is_file() and path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    if path.is_dir() and (path / "metadata.yaml").is_file():
        if any(path.glob("*.db3")) or any(path.glob("*.mcap")):
            return path
        try:
            head = (path / "metadata.yaml").read_text(errors="replace")[:2000]
        except OSError:
            return None
        if "rosbag2_bagfile_information" in head:
            return path
    return None


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)  # for ROS 2 bags that do not embed their message definitions


def _stamp_ns(msg) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def decode_image(msg, msgtype: str, topic: str, size: tuple[int, int]) -> np.ndarray:
    """An Image or CompressedImage message as ``[H,W,3]`` float32 RGB in [0,1] (grey replicated);
    errors name the topic and what was expected."""
    import cv2

    if msgtype == COMPRESSED:
        data = np.asarray(msg.data, np.uint8)
        try:
            img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        except cv2.error:
            img = None
        if img is None:
            raise InputError(topic, "data", f"could not decode the CompressedImage (format {msg.format!r}; expected jpeg or png)")
        order = "grey" if img.ndim == 2 else "bgr"
        if img.ndim == 3 and img.shape[2] == 4:
            img = img[..., :3]
    else:
        enc = msg.encoding
        if enc not in ENCODINGS:
            raise InputError(topic, "encoding", f"expected one of {', '.join(ENCODINGS)}, got {enc!r} (debayer the images first)")
        ch, dtype, order = ENCODINGS[enc]
        h, w, step = int(msg.height), int(msg.width), int(msg.step)
        row = w * ch * np.dtype(dtype).itemsize
        data = np.asarray(msg.data, np.uint8)
        if step < row or len(data) < step * h:
            raise InputError(topic, "step", f"{w}x{h} {enc} needs {row} bytes per row and {row * h} in all; the message has step {step} and {len(data)} bytes")
        img = data[: step * h].reshape(h, step)[:, :row].copy().view(np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")).astype(dtype)
        img = img.reshape(h, w, ch)[..., :3] if ch > 1 else img.reshape(h, w)
    w, h = size
    if (img.shape[1], img.shape[0]) != (w, h):
        raise InputError(topic, None, f"expected image size {w}x{h} (the rig's resolution), got {img.shape[1]}x{img.shape[0]}")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    if order == "grey":
        img = np.repeat(img[..., None], 3, axis=2)
    elif order == "bgr":
        img = img[..., ::-1]
    return np.ascontiguousarray(img.astype(np.float32) / scale)


def pair_frames(t: list, tol: float) -> tuple[np.ndarray, list]:
    """Frames from per-camera times ``t`` (camera 0 first, each sorted, rig clock, s): each
    camera-0 image takes, in every other camera, the closest image within ``tol`` that no
    other frame took, and is a frame only if every camera has one. Images whose closest
    partners are nearest go first (a greedy matching), so a frame that cannot be completed
    never blocks one that can. Returns the kept camera-0 indices and per camera the index
    of its image in each kept frame."""
    t0, others = t[0], t[1:]
    lo = [np.searchsorted(tc, t0 - tol, "left") for tc in others]
    hi = [np.searchsorted(tc, t0 + tol, "right") for tc in others]
    worst = np.zeros(len(t0))
    for tc, a, b in zip(others, lo, hi):
        for k in range(len(t0)):
            worst[k] = max(worst[k], np.abs(tc[a[k] : b[k]] - t0[k]).min()) if b[k] > a[k] else np.inf
    used = [set() for _ in others]
    picks = {}
    for k in np.argsort(worst, kind="stable"):
        if not np.isfinite(worst[k]):
            break
        choice = []
        for c, (tc, a, b) in enumerate(zip(others, lo, hi)):
            free = [j for j in range(a[k], b[k]) if j not in used[c]]
            if not free:
                break
            choice.append(min(free, key=lambda j: abs(tc[j] - t0[k])))
        if len(choice) == len(others):
            for c, j in enumerate(choice):
                used[c].add(j)
            picks[int(k)] = choice
    kept = np.array(sorted(picks), dtype=int)
    return kept, [kept] + [np.array([picks[k][c] for k in kept], dtype=int) for c in range(len(others))]


class BagSequence(Sequence):
    """The rig's cameras' image topics in a ROS 1 or ROS 2 bag (see the module docstring)."""

    def __init__(self, path, rig: Rig, sync_tolerance: float = MAX_SYNC_DT, rig_source=None):
        from rosbags.highlevel import AnyReader

        self.path = Path(path)
        root = bag_paths(self.path)
        if root is None:
            raise InputError(self.path, None, "not a ROS bag (expected a ROS 1 .bag file or a ROS 2 bag folder with metadata.yaml)")
        self.name = self.path.stem
        self.rig = rig
        for i, c in enumerate(rig.cameras):
            if c.topic is None:
                raise InputError(rig_source, f"cameras[{i}].topic", f"missing field: camera {c.name!r} needs the image topic it is recorded on in the bag "
                                 f"(in a Kalibr camchain: cam{i}.rostopic)")
        topics = [c.topic for c in rig.cameras]
        for i, t in enumerate(topics):
            if topics.index(t) != i:
                raise InputError(rig_source, f"cameras[{i}].topic", f"topic {t!r} is already camera {rig.cameras[topics.index(t)].name!r}'s")
        try:
            self._reader = AnyReader([root], default_typestore=_typestore())
            self._reader.open()
        except Exception as e:  # rosbags raises its own error types for broken bags
            raise InputError(self.path, None, f"could not open the bag: {e}") from None
        try:
            self._open(rig, topics, sync_tolerance)
        except BaseException:
            self.close()
            raise

    def _open(self, rig: Rig, topics: list, sync_tolerance: float) -> None:
        by_topic: dict[str, list] = {}
        for conn in self._reader.connections:
            by_topic.setdefault(conn.topic, []).append(conn)
        self._conns = []
        for i, (c, t) in enumerate(zip(rig.cameras, topics)):
            conns = by_topic.get(t)
            if not conns:
                images = sorted(k for k, v in by_topic.items() if v[0].msgtype in (IMAGE, COMPRESSED))
                raise InputError(self.path, t, f"camera {c.name!r}'s topic is not in the bag (its image topics: {', '.join(images) or 'none'})")
            if conns[0].msgtype not in (IMAGE, COMPRESSED):
                raise InputError(self.path, t, f"expected sensor_msgs/Image or sensor_msgs/CompressedImage messages, got {conns[0].msgtype}")
            self._conns.append(conns)
        index = self._index()
        self._select(index, sync_tolerance)

    def _index(self) -> list[dict]:
        """Per camera: header stamp (ns) -> (connection, bag time ns), from one pass over the bag."""
        cam_of = {id(conn): i for i, conns in enumerate(self._conns) for conn in conns}
        index: list[dict] = [{} for _ in self._conns]
        duplicates = [0] * len(self._conns)
        conns = [conn for cs in self._conns for conn in cs]
        for conn, t_bag, raw in self._reader.messages(connections=conns):
            i = cam_of[id(conn)]
            stamp = _stamp_ns(self._reader.deserialize(raw, conn.msgtype))
            if stamp == 0:
                stamp = int(t_bag)  # an unset header: the time the recorder received it
            if stamp in index[i]:
                duplicates[i] += 1
                continue
            index[i][stamp] = (conn, int(t_bag), stamp)
        for i, n in enumerate(duplicates):
            if n:
                warn(self.path, f"{self.rig.cameras[i].topic}: skipped {n} images with a header stamp another image already has")
        for i, d in enumerate(index):
            if not d:
                raise InputError(self.path, self.rig.cameras[i].topic, "no images on this topic")
        return index

    def _select(self, index: list[dict], tol: float) -> None:
        stamps = [np.array(sorted(d), dtype=np.int64) for d in index]
        t0 = stamps[0][0]
        t = [(s - t0) * 1e-9 - c.time_offset for s, c in zip(stamps, self.rig.cameras)]  # rig clock, from camera 0's first image
        kept, partner = pair_frames(t, tol)
        total = sum(len(s) for s in stamps)
        dropped = [len(s) - len(kept) for s in stamps]
        if not len(kept):
            raise InputError(self.path, None, f"no frames: the cameras' images never fall within {tol * 1e3:g} ms of each other "
                             f"({', '.join(f'{c.topic}: {len(s)}' for c, s in zip(self.rig.cameras, stamps))} images)")
        if sum(dropped):
            per = ", ".join(f"{c.topic} {d}" for c, d in zip(self.rig.cameras, dropped) if d)
            warn(self.path, f"dropped {sum(dropped)} of {total} images without a partner within {tol * 1e3:g} ms in every camera ({per}); kept {len(kept)} frames")
        self._frames = [[index[c][int(stamps[c][partner[c][f]])] for c in range(len(stamps))] for f in range(len(kept))]
        self.timestamps = stamps[0][kept] * 1e-9 - self.rig.cameras[0].time_offset
        if len(self.timestamps) > 1 and np.any(np.diff(self.timestamps) <= 0):
            raise InputError(self.path, self.rig.cameras[0].topic, "frame timestamps must increase")

    def load_frame(self, k: int) -> Frame:
        images = []
        for c, (conn, t_bag, stamp) in zip(self.rig.cameras, self._frames[k]):
            msg = None
            for cn, t, raw in self._reader.messages(connections=[conn], start=t_bag, stop=t_bag + 1):
                m = self._reader.deserialize(raw, cn.msgtype)
                if (_stamp_ns(m) or int(t)) == stamp:  # recorded at the same instant as another: the one with this stamp
                    msg = m
                    break
            if msg is None:
                raise InputError(self.path, c.topic, f"image at bag time {t_bag} ns could not be read again")
            images.append(decode_image(msg, conn.msgtype, c.topic, (c.width, c.height)))
        return Frame(k, float(self.timestamps[k]), images, [None] * len(images))

    def close(self) -> None:
        reader = getattr(self, "_reader", None)
        if reader is not None:
            self._reader = None
            try:
                reader.close()
            except Exception:  # already closed, or never fully opened
                pass

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass


def write_bag(seq: Sequence, out, ros: int = 1, compressed: bool = False, topics=None) -> tuple[Path, Rig]:
    """Write ``seq``'s images as a ROS bag (``ros=1``: ``out`` is a ``.bag`` file; ``ros=2``: a
    bag folder) with one image topic per camera (default ``/<camera name>/image_raw``), stamped
    with the frames' timestamps (camera clock: rig time + the camera's ``time_offset``); returns
    the bag's path and the rig with each camera's ``topic``. The images go in as ``rgb8``
    ``Image`` messages, or PNG ``CompressedImage`` messages with ``compressed`` (lossless)."""
    import copy

    import cv2

    out = Path(out)
    if out.exists():
        raise InputError(out, None, "already exists: a bag is never overwritten")
    rig = copy.deepcopy(seq.rig)
    for c, name in zip(rig.cameras, topics or [f"/{c.name}/image_raw" for c in rig.cameras]):
        c.topic = name
    if ros == 1:
        from rosbags.rosbag1 import Writer
        from rosbags.typesys import Stores, get_typestore

        store = get_typestore(Stores.ROS1_NOETIC)
        serialize, options = store.serialize_ros1, {}
    elif ros == 2:
        from rosbags.rosbag2 import Writer

        store = _typestore()
        serialize, options = store.serialize_cdr, {"version": 8}
    else:
        raise InputError(None, "ros", f"expected 1 or 2, got {ros!r}")
    Header, Time = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    msgtype = COMPRESSED if compressed else IMAGE
    Msg = store.types[msgtype]
    import shutil

    if len(seq) and seq.timestamps[0] + min(c.time_offset for c in rig.cameras) < 0:
        raise InputError(None, "timestamps", f"ROS time cannot be negative; the first frame is at {seq.timestamps[0]:.6f} s")
    staging = out.parent / f".{out.name}.partial"  # the bag is written here under its final name, then moved
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    tmp = staging / out.name
    try:
        with Writer(tmp, **options) as writer:
            conns = [writer.add_connection(c.topic, msgtype, typestore=store) for c in rig.cameras]
            for k in range(len(seq)):
                f = seq[k]
                for i, (c, conn) in enumerate(zip(rig.cameras, conns)):
                    ns = int(round((f.timestamp + c.time_offset) * 1e9))
                    header = Header(stamp=Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000), frame_id=c.name, **({"seq": k} if ros == 1 else {}))
                    rgb = (np.clip(f.images[i], 0, 1) * 255 + 0.5).astype(np.uint8)
                    if compressed:
                        ok, buf = cv2.imencode(".png", rgb[..., ::-1])
                        msg = Msg(header=header, format="png", data=buf.reshape(-1))
                    else:
                        msg = Msg(header=header, height=rgb.shape[0], width=rgb.shape[1], encoding="rgb8", is_bigendian=0, step=rgb.shape[1] * 3, data=rgb.reshape(-1))
                    writer.write(conn, ns, serialize(msg, msgtype))
        tmp.rename(out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return out, rig
