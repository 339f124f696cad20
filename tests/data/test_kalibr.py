"""Kalibr camchains read as rigs: EuRoC's published camchain-imucam.yaml gives the rig of
EuRoC's own sensor.yaml files, and the rig projects world points as OpenCV does with the
camchain's parameters (radtan and equidistant models)."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import warp as wp
import yaml

from mcgs_warp.cli import main
from mcgs_warp.data.euroc import read_sensor
from mcgs_warp.data.kalibr import rig_from_kalibr
from mcgs_warp.errors import InputError
from mcgs_warp.kernels.camera import Camera, camera_project
from mcgs_warp.data.kalibr import load_any_rig
from mcgs_warp.rig import load_rig

CALIB = Path(__file__).parent / "calibrations"
RADTAN = CALIB / "euroc_camchain-imucam.yaml"
EQUI = CALIB / "euroc_equidistant_camchain.yaml"


@wp.kernel
def _project(cam: Camera, p: wp.array(dtype=wp.vec3), uv: wp.array(dtype=wp.vec2)):
    i = wp.tid()
    uv[i] = camera_project(cam, p[i])


def warp_project(spec, p_cam: np.ndarray) -> np.ndarray:
    uv = wp.zeros(len(p_cam), dtype=wp.vec2, device="cpu")
    wp.launch(_project, dim=len(p_cam), inputs=[spec.warp_camera(), wp.array(p_cam.astype(np.float32), dtype=wp.vec3, device="cpu"), uv], device="cpu")
    return uv.numpy()


def kalibr(path) -> dict:
    return yaml.safe_load(Path(path).read_text())


def write(tmp_path, data, name="camchain.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def test_euroc_camchain_gives_euroc_sensor_yaml_rig():
    rig = rig_from_kalibr(RADTAN)
    assert [c.name for c in rig.cameras] == ["cam0", "cam1"] and [c.topic for c in rig.cameras] == ["/cam0/image_raw", "/cam1/image_raw"]
    for i, cam in enumerate(rig.cameras):
        ref = read_sensor(CALIB / "euroc_sensor" / f"cam{i}" / "sensor.yaml", f"cam{i}")
        assert (cam.model, cam.width, cam.height) == (ref.model, ref.width, ref.height) == ("pinhole", 752, 480)
        assert cam.intrinsics == ref.intrinsics and cam.distortion == ref.distortion
        np.testing.assert_allclose(cam.T_b_c, ref.T_b_c, atol=1e-9)  # body = IMU, as EuRoC's T_BS
        assert cam.time_offset == 0.0
    # the stereo baseline EuRoC's users know: 11.0 cm
    assert np.linalg.norm(rig.cameras[1].T_b_c[:3, 3] - rig.cameras[0].T_b_c[:3, 3]) == pytest.approx(0.1101, abs=2e-4)


def test_chain_without_imu_and_the_chain_from_the_imu_agree(tmp_path):
    data = kalibr(RADTAN)
    full = rig_from_kalibr(RADTAN)
    # cam1 located through T_cn_cnm1 and cam0's T_cam_imu only: the same place
    chained = dict(data, cam1={k: v for k, v in data["cam1"].items() if k != "T_cam_imu"})
    np.testing.assert_allclose(rig_from_kalibr(write(tmp_path, chained)).cameras[1].T_b_c, full.cameras[1].T_b_c, atol=2e-6)
    # a camera-only camchain: the body is cam0
    cams_only = {n: {k: v for k, v in b.items() if k != "T_cam_imu"} for n, b in data.items()}
    rig = rig_from_kalibr(write(tmp_path, cams_only, "cams.yaml"))
    np.testing.assert_allclose(rig.cameras[0].T_b_c, np.eye(4), atol=0)
    T_c1_c0 = np.array(data["cam1"]["T_cn_cnm1"])
    np.testing.assert_allclose(rig.cameras[1].T_b_c, np.linalg.inv(T_c1_c0), atol=1e-12)
    np.testing.assert_allclose(rig.cameras[1].T_b_c, np.linalg.inv(full.cameras[0].T_b_c) @ full.cameras[1].T_b_c, atol=2e-6)


@pytest.mark.parametrize("path", [RADTAN, EQUI], ids=["pinhole-radtan", "pinhole-equi"])
def test_rig_projects_world_points_as_opencv(path):
    """World (IMU-frame) points through our rig's T_b_c and camera model against OpenCV's
    projectPoints with the camchain's T_cam_imu, intrinsics and distortion."""
    data = kalibr(path)
    rig = rig_from_kalibr(path)
    rng = np.random.default_rng(4)
    for name, cam in zip(("cam0", "cam1"), rig.cameras):
        d = data[name]
        fx, fy, cx, cy = d["intrinsics"]
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        T_cam_imu = np.array(d["T_cam_imu"])
        # points spread over the image (within 60 % of its half-size), 1-8 m away, in the IMU frame
        uv_n = (rng.uniform(-0.6, 0.6, (300, 2)) * [cx, cy]) / [fx, fy]
        z = rng.uniform(1.0, 8.0, 300)
        p_cam_true = np.column_stack([uv_n * z[:, None], z])
        p_imu = (np.linalg.inv(T_cam_imu) @ np.column_stack([p_cam_true, np.ones(300)]).T).T[:, :3]
        rvec, _ = cv2.Rodrigues(T_cam_imu[:3, :3])
        if cam.model == "fisheye":
            uv_cv, _ = cv2.fisheye.projectPoints(p_imu.reshape(-1, 1, 3), rvec, T_cam_imu[:3, 3], K, np.array(d["distortion_coeffs"]))
        else:
            uv_cv, _ = cv2.projectPoints(p_imu.reshape(-1, 1, 3), rvec, T_cam_imu[:3, 3], K, np.array(d["distortion_coeffs"]))
        T_c_b = np.linalg.inv(cam.T_b_c)
        p_cam = (T_c_b @ np.column_stack([p_imu, np.ones(300)]).T).T[:, :3]
        uv = warp_project(cam, p_cam)
        assert np.abs(uv - uv_cv.reshape(-1, 2)).max() < 2e-3, name  # float32 kernel, pixels of a 752x480 image


def test_timeshift_topic_and_model_names(tmp_path):
    data = kalibr(EQUI)
    data["cam1"]["timeshift_cam_imu"] = 0.0042  # t_imu = t_cam + 4.2 ms
    rig = rig_from_kalibr(write(tmp_path, data))
    assert [c.model for c in rig.cameras] == ["fisheye", "fisheye"]
    assert rig.cameras[1].time_offset == pytest.approx(-0.0042) and rig.cameras[0].time_offset == 0.0
    assert len(rig.cameras[0].distortion) == 4 and rig.cameras[1].distortion[3] == pytest.approx(-0.010717188529046507)


@pytest.mark.parametrize(
    "edit, field, words",
    [
        (lambda d: d["cam1"].update(camera_model="omni", intrinsics=[0.9, 460.0, 460.0, 370.0, 250.0]), "cam1.camera_model", "omni-radtan is not supported"),
        (lambda d: d["cam0"].update(camera_model="ds"), "cam0.camera_model", "ds-radtan"),
        (lambda d: d["cam1"].update(distortion_model="fov"), "cam1.distortion_model", "pinhole-fov"),
        (lambda d: d["cam1"].update(camera_model=["pinhole"]), "cam1.camera_model", "expected a model name"),
        (lambda d: d.update(cam2=d.pop("cam1")), "cam1", "missing camera block"),
        (lambda d: d["cam1"].pop("T_cam_imu") and d["cam1"].pop("T_cn_cnm1"), "cam1.T_cn_cnm1", "missing field"),
        (lambda d: d["cam0"].update(T_cam_imu=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]]), "cam0.T_cam_imu", "rotation"),
        (lambda d: d["cam0"].update(intrinsics=[458.0, 457.0, 367.0]), "cam0.intrinsics", "expected 4 numbers"),
        (lambda d: d["cam1"].update(distortion_model="equidistant", distortion_coeffs=[0.1, 0.2, 0.3, 0.4, 0.5]), "cam1.distortion_coeffs", "at most 4"),
        (lambda d: d["cam0"].update(timeshift_cam_imu="soon"), "cam0.timeshift_cam_imu", "seconds"),
    ],
)
def test_bad_camchains_name_the_field(tmp_path, edit, field, words):
    data = kalibr(RADTAN)
    edit(data)
    path = write(tmp_path, data)
    with pytest.raises(InputError) as e:
        rig_from_kalibr(path)
    assert str(path) in str(e.value) and field in str(e.value) and words in str(e.value), str(e.value)


def test_inconsistent_chain_is_reported(tmp_path, capsys):
    data = kalibr(RADTAN)
    data["cam1"]["T_cn_cnm1"][0][3] += 0.01  # the chain says 1 cm more baseline than T_cam_imu
    rig = rig_from_kalibr(write(tmp_path, data))
    err = capsys.readouterr().err
    assert "cam1: T_cam_imu and T_cn_cnm1" in err and "10.00 mm" in err
    np.testing.assert_allclose(rig.cameras[1].T_b_c, rig_from_kalibr(RADTAN).cameras[1].T_b_c, atol=1e-12)  # T_cam_imu wins


def test_cli_rig_from_kalibr_writes_a_rig_file(tmp_path, capsys):
    out = tmp_path / "rig.yaml"
    assert main(["rig", "--from-kalibr", str(RADTAN), "--out", str(out)]) == 0
    assert "cam1" in capsys.readouterr().out
    a, b = load_rig(out), rig_from_kalibr(RADTAN)
    for x, y in zip(a.cameras, b.cameras):
        assert (x.name, x.model, x.intrinsics, x.distortion, x.topic) == (y.name, y.model, y.intrinsics, y.distortion, y.topic)
        np.testing.assert_allclose(x.T_b_c, y.T_b_c, atol=1e-12)
    # a run's --rig takes either file
    np.testing.assert_allclose(load_any_rig(RADTAN).cameras[1].T_b_c, b.cameras[1].T_b_c, atol=0)
    assert main(["rig", "--from-kalibr", str(CALIB / "euroc_sensor" / "cam0" / "sensor.yaml"), "--out", str(tmp_path / "x.yaml")]) == 2
    assert "not a Kalibr camchain" in capsys.readouterr().err and not (tmp_path / "x.yaml").exists()
