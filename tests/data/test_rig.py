"""Rig YAML: round trip, the packaged synthetic rig, and one clear error per bad field."""

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from mcgs_warp.errors import InputError
from mcgs_warp.rig import load_rig, save_rig

GOOD = {
    "cameras": [
        {
            "name": "front",
            "model": "pinhole",
            "resolution": [320, 240],
            "intrinsics": [180.0, 181.0, 159.5, 119.5],
            "distortion": [-0.05, 0.01, 0.001, 0.0, 0.0],
            "T_b_c": {"translation": [0.2, 0.0, 0.1], "quaternion": [-0.5, 0.5, -0.5, 0.5]},
            "time_offset": 0.001,
        },
        {
            "name": "left",
            "model": "fisheye",
            "resolution": [320, 240],
            "intrinsics": [150.0, 150.0, 160.0, 120.0],
            "distortion": [0.02, -0.01, 0.0, 0.0],
            "T_b_c": [[0, 0, 1, 0.1], [-1, 0, 0, 0.2], [0, -1, 0, 0.0], [0, 0, 0, 1]],
        },
        {"model": "equirectangular", "resolution": [64, 32]},
    ]
}


def write(tmp_path, data, name="rig.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data) if not isinstance(data, str) else data)
    return path


def test_load_save_round_trip(tmp_path):
    rig = load_rig(write(tmp_path, GOOD))
    assert [c.name for c in rig.cameras] == ["front", "left", "cam2"]
    front = rig.cameras[0]
    np.testing.assert_allclose(front.T_b_c[:3, :3], Rotation.from_quat([-0.5, 0.5, -0.5, 0.5]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(front.T_b_c[:3, 3], [0.2, 0.0, 0.1])
    assert front.time_offset == 0.001 and rig.cameras[2].intrinsics is None
    save_rig(rig, tmp_path / "again.yaml")
    again = load_rig(tmp_path / "again.yaml")
    for a, b in zip(rig.cameras, again.cameras):
        assert (a.name, a.model, a.width, a.height, a.intrinsics, a.distortion) == (b.name, b.model, b.width, b.height, b.intrinsics, b.distortion)
        np.testing.assert_allclose(a.T_b_c, b.T_b_c, atol=1e-9)
    cams = rig.warp_cameras()
    assert cams[1].model == 1 and abs(cams[2].fx - 64 / (2 * np.pi)) < 1e-5
    T_w_c = rig.camera_poses(np.eye(4))
    np.testing.assert_allclose(T_w_c[1], rig.cameras[1].T_b_c)


def test_packaged_synthetic_rig_loads():
    from mcgs_warp.data.synthetic import synthetic_rig

    rig = synthetic_rig(4)
    assert [c.model for c in rig.cameras] == ["pinhole", "fisheye", "pinhole", "pinhole"]
    # the front camera looks along body +x
    np.testing.assert_allclose(rig.cameras[0].T_b_c[:3, 2], [1, 0, 0], atol=1e-9)


@pytest.mark.parametrize("name, stereo", [("rig_synthetic.yaml", True), ("rig_wide_fisheye.yaml", True), ("rig_front_back.yaml", False)])
def test_bundled_rigs_load_and_overlap_as_their_comments_say(name, stereo):
    """Each rig YAML under configs/ loads, and the rig stereo (cross-view pairs, what
    measures metric depth without a prior) exists exactly where the file says the cameras
    overlap: configs/rig_front_back.yaml is the rig whose scale only a prior carries."""
    from mcgs_warp.ba.edges import camera_overlap
    from mcgs_warp.frontend.stereo import RigStereo
    from mcgs_warp.system.config import packaged_config

    rig = load_rig(packaged_config(name))
    assert len(rig) >= 2
    assert bool(RigStereo(rig, camera_overlap(rig, stride=8)).pairs) == stereo


def broken(path_fn, value):
    data = yaml.safe_load(yaml.safe_dump(GOOD))
    path_fn(data, value)
    return data


def set_field(cam, field):
    def f(data, value):
        if value is None:
            del data["cameras"][cam][field]
        else:
            data["cameras"][cam][field] = value

    return f


@pytest.mark.parametrize(
    "mutate, value, expected",
    [
        (set_field(1, "intrinsics"), [150.0, 150.0, 160.0], "cameras[1].intrinsics: expected 4 numbers, got 3"),
        (set_field(0, "intrinsics"), [150.0, "x", 1.0, 1.0], "cameras[0].intrinsics: expected finite numbers, got 'x'"),
        (set_field(0, "intrinsics"), [-150.0, 150.0, 1.0, 1.0], "cameras[0].intrinsics: expected positive focal lengths"),
        (set_field(0, "model"), "kannala", "cameras[0].model: expected one of pinhole, fisheye, equirectangular, got 'kannala'"),
        (set_field(0, "resolution"), None, "cameras[0].resolution: missing field"),
        (set_field(0, "resolution"), [320.5, 240], "cameras[0].resolution: expected integers"),
        (set_field(0, "resolution"), [0, 240], "cameras[0].resolution: expected positive width and height"),
        (set_field(1, "distortion"), [0.1, 0.0, 0.0, 0.0, 0.2], "cameras[1].distortion: expected at most 4 numbers, got 5"),
        (set_field(0, "colour"), "red", "cameras[0].colour: unexpected field"),
        (set_field(0, "time_offset"), "soon", "cameras[0].time_offset: expected a finite number"),
        (set_field(1, "T_b_c"), [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]], "cameras[1].T_b_c: rotation part is not orthonormal"),
        (set_field(1, "T_b_c"), [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]], "cameras[1].T_b_c: rotation part is a reflection"),
        (set_field(1, "T_b_c"), [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "cameras[1].T_b_c: expected a 4x4 matrix"),
        (set_field(1, "T_b_c"), [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], "cameras[1].T_b_c[3]: expected last row [0, 0, 0, 1]"),
        (set_field(0, "T_b_c"), {"translation": [0, 0, 0], "quaternion": [0, 0, 0, 2]}, "cameras[0].T_b_c.quaternion: expected a unit quaternion"),
        (set_field(0, "T_b_c"), {"translation": [0, 0], "quaternion": [0, 0, 0, 1]}, "cameras[0].T_b_c.translation: expected 3 numbers, got 2"),
        (set_field(2, "name"), "front", "cameras[2].name: duplicate camera name 'front'"),
        (lambda d, v: d.update(cameras=[]), None, "cameras: expected a non-empty list of cameras"),
        (lambda d, v: d.update(extra=1), None, "extra: unexpected field"),
    ],
)
def test_bad_field_names_file_camera_and_field(tmp_path, mutate, value, expected):
    path = write(tmp_path, broken(mutate, value))
    with pytest.raises(InputError) as err:
        load_rig(path)
    assert str(err.value).startswith(f"{path}: ")
    assert expected in str(err.value)


def test_yaml_syntax_error_names_the_line(tmp_path):
    path = write(tmp_path, "cameras:\n  - model: pinhole\n    resolution: [320, 240\n")
    with pytest.raises(InputError, match=r"rig.yaml: YAML syntax error: line \d+"):
        load_rig(path)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="nope.yaml: file not found"):
        load_rig(tmp_path / "nope.yaml")
