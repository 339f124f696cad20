"""ROS bags as sequences: bags the tests write (ROS 1 and ROS 2, raw and compressed images)
read back as the frames they came from, cameras paired within the tolerance with every
dropped image counted, header stamps (not the recorder's clock) as the frame times, lazy
reading, and errors that name the topic or the rig field."""

import copy
import tracemalloc

import numpy as np
import pytest

from mcgs_warp.data import open_sequence
from mcgs_warp.data.rosbag import BagSequence, decode_image, write_bag
from mcgs_warp.data.synthetic import generate
from mcgs_warp.errors import InputError

N_FRAMES = 6


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    root = tmp_path_factory.mktemp("bags")
    return root, generate(root / "ours", n_frames=N_FRAMES, seed=5, progress=False, depth="none")


@pytest.mark.parametrize("ros, compressed", [(1, False), (1, True), (2, False), (2, True)], ids=["ros1", "ros1-compressed", "ros2", "ros2-compressed"])
def test_bag_reads_back_the_frames_it_was_written_from(source, ros, compressed):
    root, seq = source
    path, rig = write_bag(seq, root / f"rec_{ros}_{int(compressed)}{'.bag' if ros == 1 else ''}", ros=ros, compressed=compressed)
    assert [c.topic for c in rig.cameras] == [f"/{c.name}/image_raw" for c in seq.rig.cameras]
    got = open_sequence(path, rig=rig)
    assert isinstance(got, BagSequence) and len(got) == N_FRAMES
    np.testing.assert_allclose(got.timestamps, seq.timestamps, atol=1e-9)
    for k in (0, N_FRAMES - 1):
        f, g = got[k], seq[k]
        assert f.timestamp == pytest.approx(g.timestamp, abs=1e-9) and all(d is None for d in f.depths)
        for a, b in zip(f.images, g.images):
            assert a.dtype == np.float32 and a.shape == b.shape
            np.testing.assert_array_equal(a, b)  # 8-bit PNG in the folder, rgb8 or PNG in the bag: the same bytes


def _write_custom(path, ros, stamps_per_camera, size=(8, 6), bag_delay_ns=0, encoding="rgb8", topics=None):
    """A bag with given header stamps (ns) per camera; pixel value = frame number."""
    from rosbags.typesys import Stores, get_typestore

    if ros == 1:
        from rosbags.rosbag1 import Writer

        store, opts, ser = get_typestore(Stores.ROS1_NOETIC), {}, "serialize_ros1"
    else:
        from rosbags.rosbag2 import Writer

        store, opts, ser = get_typestore(Stores.ROS2_HUMBLE), {"version": 8}, "serialize_cdr"
    Header, Time, Image = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"], store.types["sensor_msgs/msg/Image"]
    w, h = size
    ch = {"rgb8": 3, "mono8": 1, "bayer_rggb8": 1}[encoding]
    with Writer(path, **opts) as writer:
        conns = [writer.add_connection(topics[i] if topics else f"/cam{i}/image", "sensor_msgs/msg/Image", typestore=store) for i in range(len(stamps_per_camera))]
        events = sorted((ns, i, k) for i, st in enumerate(stamps_per_camera) for k, ns in enumerate(st))
        for ns, i, k in events:
            extra = {"seq": k} if ros == 1 else {}
            header = Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=f"cam{i}", **extra)
            data = np.full(h * w * ch, (k * 10 + i) % 256, np.uint8)
            msg = Image(header=header, height=h, width=w, encoding=encoding, is_bigendian=0, step=w * ch, data=data)
            writer.write(conns[i], ns + bag_delay_ns, getattr(store, ser)(msg, "sensor_msgs/msg/Image"))
    return path


def _rig(n, size=(8, 6), topics=None):
    from mcgs_warp.rig import CameraSpec, Rig

    return Rig([CameraSpec(f"cam{i}", "pinhole", size[0], size[1], (5.0, 5.0, 4.0, 3.0), topic=(topics[i] if topics else f"/cam{i}/image")) for i in range(n)])


def test_cameras_pair_within_the_tolerance_and_drops_are_counted_once(tmp_path, capsys):
    base = 1_700_000_000 * 10**9
    t0 = [base + k * 100_000_000 for k in range(10)]  # 10 Hz
    t1 = [t + 2_000_000 for k, t in enumerate(t0) if k != 4]  # 2 ms late; frame 4 lost
    t2 = [t - 1_000_000 + (30_000_000 if k == 7 else 0) for k, t in enumerate(t0)]  # frame 7 31 ms late: no partner
    path = _write_custom(tmp_path / "sync.bag", 1, [t0, t1, t2], bag_delay_ns=50_000_000)
    seq = BagSequence(path, _rig(3))
    err = capsys.readouterr().err
    assert len(seq) == 8
    assert err.count("warning") == 1 and "dropped 5 of 29 images" in err and "kept 8 frames" in err, err
    # header stamps, not the recorder's 50 ms later clock: cam0's, from its first image
    expect = np.array([t for k, t in enumerate(t0) if k not in (4, 7)]) * 1e-9
    np.testing.assert_allclose(seq.timestamps, expect, atol=1e-6)
    f = seq[5]  # frame 6 of the recording: cam0 image 6, cam1 image 5 (one lost before), cam2 image 6
    assert [float(im[0, 0, 0]) * 255 for im in f.images] == pytest.approx([60, 51, 62])
    # a tighter tolerance drops the 2 ms pairs too
    with pytest.raises(InputError, match="never fall within 1 ms"):
        BagSequence(path, _rig(3), sync_tolerance=0.001)


def test_pairing_tries_the_next_closest_image_when_the_closest_is_taken(tmp_path):
    """cam0 at 0 and 6 ms, cam1 at 2.5 ms, cam2 at 6 ms, 5 ms tolerance: cam0's first image is
    closest to cam1's but has no cam2 partner; its second image pairs with both (6 / 2.5 / 6)."""
    from mcgs_warp.data.rosbag import pair_frames

    b = 10**9
    path = _write_custom(tmp_path / "next.bag", 1, [[b, b + 6_000_000], [b + 2_500_000], [b + 6_000_000]])
    seq = BagSequence(path, _rig(3))
    assert len(seq) == 1 and seq.timestamps[0] == pytest.approx((b + 6_000_000) * 1e-9)
    assert [float(im[0, 0, 0]) * 255 for im in seq[0].images] == pytest.approx([10, 1, 2])  # images 1, 0, 0
    # closest pairs first, each camera image used once: 1.0 takes 1.05, 0.9 is left for 0.8
    kept, partner = pair_frames([np.array([0.8, 1.0, 2.0]), np.array([0.9, 1.05, 2.5])], 0.2)
    np.testing.assert_array_equal(kept, [0, 1])
    np.testing.assert_array_equal(partner[1], [0, 1])


def test_time_offset_moves_a_camera_onto_the_rig_clock(tmp_path):
    t0 = [k * 100_000_000 + 10**9 for k in range(5)]
    t1 = [t + 40_000_000 for t in t0]  # cam1's clock runs 40 ms ahead
    path = _write_custom(tmp_path / "offset", 2, [t0, t1])
    with pytest.raises(InputError, match="never fall within 5 ms"):
        BagSequence(path, _rig(2))
    rig = _rig(2)
    rig.cameras[1].time_offset = 0.040
    assert len(BagSequence(path, rig)) == 5


@pytest.mark.parametrize("ros", [1, 2])
def test_opening_a_bag_keeps_no_images_in_memory(tmp_path, ros):
    size, n = (320, 240), 60
    t = [10**9 + k * 10**8 for k in range(n)]
    path = _write_custom(tmp_path / ("big.bag" if ros == 1 else "big"), ros, [t, t], size=size)
    BagSequence(path, _rig(2, size))  # first use builds the message types: not counted
    tracemalloc.start()
    bag = BagSequence(path, _rig(2, size))
    current, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    total = size[0] * size[1] * 3 * n * 2  # 27.6 MB of images
    # the index and at most a chunk of the bag (ROS 1 reads ~1-3 MB chunks), not the images
    assert current < 0.1 * total and peak < 0.15 * total, (current, peak, total)
    assert float(bag[37].images[1][0, 0, 0]) * 255 == pytest.approx((37 * 10 + 1) % 256)


def test_decode_encodings():
    class Msg:
        pass

    def msg(enc, arr, big=0):
        m = Msg()
        m.encoding, m.height, m.width, m.is_bigendian = enc, arr.shape[0], arr.shape[1], big
        raw = arr.astype(arr.dtype.newbyteorder(">" if big else "<")).tobytes()
        m.step = len(raw) // arr.shape[0] + 2  # padded rows
        rows = [raw[r * (len(raw) // arr.shape[0]) : (r + 1) * (len(raw) // arr.shape[0])] + b"\0\0" for r in range(arr.shape[0])]
        m.data = np.frombuffer(b"".join(rows), np.uint8)
        return m

    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (4, 5, 3), dtype=np.uint8)
    np.testing.assert_array_equal(decode_image(msg("rgb8", rgb), "sensor_msgs/msg/Image", "/t", (5, 4)), rgb / np.float32(255))
    np.testing.assert_array_equal(decode_image(msg("bgr8", rgb[..., ::-1].copy()), "sensor_msgs/msg/Image", "/t", (5, 4)), rgb / np.float32(255))
    grey = rng.integers(0, 256, (4, 5), dtype=np.uint8)
    out = decode_image(msg("mono8", grey), "sensor_msgs/msg/Image", "/t", (5, 4))
    assert out.shape == (4, 5, 3) and np.array_equal(out[..., 2], grey / np.float32(255))
    g16 = rng.integers(0, 65536, (4, 5), dtype=np.uint16)
    for big in (0, 1):
        np.testing.assert_allclose(decode_image(msg("mono16", g16, big), "sensor_msgs/msg/Image", "/t", (5, 4))[..., 0], g16 / 65535.0, rtol=1e-6)
    with pytest.raises(InputError, match="/t: encoding: .*got 'bayer_rggb8'"):
        decode_image(msg("bayer_rggb8", grey), "sensor_msgs/msg/Image", "/t", (5, 4))
    with pytest.raises(InputError, match="/t: expected image size 6x4"):
        decode_image(msg("rgb8", rgb), "sensor_msgs/msg/Image", "/t", (6, 4))


def test_bad_bags_and_rigs_name_the_topic_or_field(tmp_path):
    t = [10**9 + k * 10**8 for k in range(3)]
    path = _write_custom(tmp_path / "two.bag", 1, [t, t])
    with pytest.raises(InputError, match="no calibration: pass --rig"):
        open_sequence(path)
    rig = _rig(2)
    rig.cameras[1].topic = None
    with pytest.raises(InputError, match=r"rig.yaml: cameras\[1\].topic: missing field"):
        BagSequence(path, rig, rig_source="rig.yaml")
    with pytest.raises(InputError, match=r"/cam5/image: camera 'cam1'.s topic is not in the bag \(its image topics: /cam0/image, /cam1/image\)"):
        BagSequence(path, _rig(2, topics=["/cam0/image", "/cam5/image"]))
    with pytest.raises(InputError, match="expected image size 9x6"):
        BagSequence(path, _rig(2, size=(9, 6)))[0]
    with pytest.raises(InputError, match="already camera 'cam0'"):
        BagSequence(path, _rig(2, topics=["/cam0/image", "/cam0/image"]))
    bayer = _write_custom(tmp_path / "bayer.bag", 1, [t], encoding="bayer_rggb8")
    with pytest.raises(InputError, match="bayer_rggb8"):
        BagSequence(bayer, _rig(1))[0]
    from mcgs_warp.data.rosbag import COMPRESSED

    class Empty:
        format, data = "jpeg", np.zeros(0, np.uint8)

    with pytest.raises(InputError, match="could not decode the CompressedImage"):
        decode_image(Empty(), COMPRESSED, "/t", (5, 4))
    broken = tmp_path / "broken.bag"
    broken.write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 64)
    with pytest.raises(InputError, match="could not open the bag"):
        BagSequence(broken, _rig(1))
    with pytest.raises(InputError, match="a bag is never overwritten"):
        write_bag(open_sequence(tmp_path / ".." / tmp_path.name / "two.bag", rig=_rig(2)), path)


def test_cli_bag_writes_a_recording_and_its_rig(source, tmp_path, capsys):
    from mcgs_warp.cli import main
    from mcgs_warp.rig import load_rig

    root, seq = source
    assert main(["bag", "--data", str(root / "ours"), "--out", str(tmp_path / "b"), "--ros2", "--compressed"]) == 0
    assert "mcgs-slam run --data" in capsys.readouterr().out
    rig = load_rig(tmp_path / "b" / "rig.yaml")
    got = open_sequence(tmp_path / "b" / "recording", rig=rig)
    np.testing.assert_array_equal(got[1].images[2], seq[1].images[2])
    assert (tmp_path / "b" / "groundtruth.txt").is_file()
    assert main(["bag", "--data", str(root / "ours"), "--out", str(tmp_path / "b"), "--ros2"]) == 2
    assert "never overwritten" in capsys.readouterr().err
    other = copy.deepcopy(rig)
    other.cameras = other.cameras[:2]
    with pytest.raises(InputError, match="expected 3 cameras"):
        open_sequence(root / "ours", rig=other)
