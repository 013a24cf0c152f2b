"""KITTI raw as users have it: OXTS (GPS/IMU) camera motion, LiDAR depth (npz and depth-benchmark
PNG), frame times. Hand-made records on tiny files, plus the shared LiDAR drive where present."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from monostixels._checks import InputError
from monostixels.data.kitti_raw import (
    EARTH_RADIUS_M,
    KittiRawSource,
    oxts_poses,
    read_depth_png,
    read_lidar_npz,
    read_timestamps,
)

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
LIDAR_ROOT = SHARED / "kitti_raw_lidar"
needs_lidar = pytest.mark.skipif(not LIDAR_ROOT.is_dir(), reason=f"shared KITTI raw LiDAR drive not found at {LIDAR_ROOT}")

H, W = 8, 12
#: Rectified camera 2 of the tiny drive: fx != fy, cx != cy, a 6 cm baseline offset (P[0, 3] = fx * 0.06).
P02 = np.array([[500.0, 0, 6, 30.0], [0, 480, 4, 0], [0, 0, 1, 0]])
#: Camera axes from IMU axes (IMU x forward, y left, z up -> camera x right, y down, z forward).
R_CAM_IMU = np.array([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]])
LAT0, LON0 = 49.0, 8.4


def _record(lat: float, lon: float, yaw: float, vf: float, vl: float = 0.0) -> str:
    # lat lon alt roll pitch yaw vn ve vf vl vu, then 19 more values (unused).
    vals = [lat, lon, 100.0, 0.0, 0.0, yaw, 0.0, 0.0, vf, vl, 0.0] + [0.0] * 19
    return " ".join(f"{v:.15g}" for v in vals)


def _write_drive(tmp: Path, records: dict[int, str], times: list[str] | None = None) -> Path:
    date = tmp / "2011_01_02"
    drive = date / "2011_01_02_drive_0003_sync"
    (drive / "image_02" / "data").mkdir(parents=True)
    (drive / "oxts" / "data").mkdir(parents=True)
    for n, rec in records.items():
        cv2.imwrite(str(drive / "image_02" / "data" / f"{n:010d}.png"), np.full((H, W, 3), 10 * n, np.uint8))
        (drive / "oxts" / "data" / f"{n:010d}.txt").write_text(rec + "\n")
    if times is not None:
        (drive / "image_02" / "timestamps.txt").write_text("\n".join(times) + "\n")
    (date / "calib_cam_to_cam.txt").write_text(
        "calib_time: 09-Jan-2012 13:59:33\nR_rect_00: 1 0 0 0 1 0 0 0 1\nP_rect_02: "
        + " ".join(f"{v:.6e}" for v in P02.ravel()) + "\n")
    # IMU -> Velodyne: identity axes, Velodyne -> camera 0: the axis permutation; offsets cancel in
    # relative motion only up to the lever arm, which the hand computation includes.
    (date / "calib_imu_to_velo.txt").write_text("R: 1 0 0 0 1 0 0 0 1\nT: -0.8 0.3 -0.8\n")
    (date / "calib_velo_to_cam.txt").write_text(
        "R: " + " ".join(str(v) for v in R_CAM_IMU.ravel()) + "\nT: 0.0 -0.08 -0.27\n")
    return drive


def _expected_cam2_motion(R_imu: np.ndarray, t_imu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hand chain: IMU motion (prev <- cur, in the previous IMU frame) -> camera-2 motion.

    ``X_imu = R_CAM_IMU^T (X_cam0 - c)`` with ``c = R_CAM_IMU T_vi + T_cv`` the lever arm; camera 2 is
    camera 0 shifted by ``b = (0.06, 0, 0)``.
    """
    c = R_CAM_IMU @ np.array([-0.8, 0.3, -0.8]) + np.array([0.0, -0.08, -0.27])
    b = np.array([0.06, 0.0, 0.0])
    R = R_CAM_IMU @ R_imu @ R_CAM_IMU.T
    # X_cam_prev = A(R_imu A^-1(X_cur) + t_imu) with A(x) = R_CAM_IMU x + c + b.
    t = R_CAM_IMU @ t_imu + (c + b) - R @ (c + b)
    return R, t


def test_oxts_velocity_and_position_give_the_hand_computed_camera_motion(tmp_path):
    # Frame 1 -> 2: heading east (yaw 0) at 10 m/s, turning left by 0.02 rad; 0.1 s apart.
    d = 0.02
    dlon = math.degrees(1.0 / (math.cos(math.radians(LAT0)) * EARTH_RADIUS_M))  # 1 m east at LAT0
    recs = {1: _record(LAT0, LON0, 0.0, 10.0), 2: _record(LAT0, LON0 + dlon, d, 10.0)}
    times = ["2011-01-02 10:00:00.000000000", "2011-01-02 10:00:00.100000000", "2011-01-02 10:00:00.200000000"]
    _write_drive(tmp_path, recs, times)
    R_imu = np.array([[math.cos(d), -math.sin(d), 0], [math.sin(d), math.cos(d), 0], [0, 0, 1]])
    # Trapezoid of the heading-frame velocities: 0.1 s x (10 (1, 0) + 10 (cos d, sin d)) / 2.
    t_vel = 0.5 * np.array([1 + math.cos(d), math.sin(d), 0.0])
    for mode, t_imu in (("velocity", t_vel), ("position", np.array([1.0, 0.0, 0.0]))):
        src = KittiRawSource(tmp_path, oxts=mode)
        assert len(src) == 1
        p = src[0]
        R_exp, t_exp = _expected_cam2_motion(R_imu, t_imu)
        assert np.allclose(p.motion.R.numpy(), R_exp, atol=1e-9), mode
        assert np.allclose(p.motion.t.numpy(), t_exp, atol=1e-6 if mode == "position" else 1e-9), mode
        assert p.meta["motion_source"] == f"oxts ({mode})"
        assert p.meta["dt"] == pytest.approx(0.1, abs=1e-9)
    # Driving forward: a static point is farther away in the previous frame (t_z > 0), and
    # turning left rotates the camera about its (downward) y axis.
    assert p.motion.t[2] > 0.9 and abs(float(p.motion.R[0, 2])) == pytest.approx(math.sin(d), abs=1e-9)


def test_oxts_poses_straight_line_and_bad_input(tmp_path):
    recs = {n: np.array([LAT0, LON0, 0, 0, 0, math.pi / 2, 0, 0, 5.0, 0, 0], dtype=float) for n in (0, 1, 2)}
    T = oxts_poses(recs, {0: 0.0, 1: 0.2, 2: 0.4}, mode="velocity")
    # Heading north (yaw pi/2) at 5 m/s: 1 m north per 0.2 s.
    assert np.allclose(T[2][:3, 3], [0.0, 2.0, 0.0], atol=1e-12)
    with pytest.raises(InputError, match="data.oxts"):
        oxts_poses(recs, None, mode="imu")
    drive = _write_drive(tmp_path, {1: _record(LAT0, LON0, 0, 1), 2: "1 2 3"})
    with pytest.raises(InputError, match=r"0000000002\.txt has 3 values"):
        KittiRawSource(tmp_path)
    (drive / "oxts" / "data" / "0000000002.txt").write_text(_record(LAT0, LON0, 0, 1))
    (drive.parent / "calib_imu_to_velo.txt").unlink()
    with pytest.raises(InputError, match=r"calib_imu_to_velo\.txt does not exist"):
        KittiRawSource(tmp_path)


def test_timestamps_and_missing_times(tmp_path):
    f = tmp_path / "t.txt"
    f.write_text("2011-09-26 23:59:59.950000000\n2011-09-27 00:00:00.050000000\n")
    assert np.allclose(read_timestamps(f), [0.0, 0.1])  # across midnight
    f.write_text("2011-09-26 13:17:59.2\nnot a time\n")
    with pytest.raises(InputError, match="t.txt line 2"):
        read_timestamps(f)


def test_lidar_npz_and_depth_png_readers(tmp_path):
    depth = np.zeros((H, W), np.float32)
    depth[2, 3], depth[5, 7] = 12.25, 40.5
    np.savez(tmp_path / "d.npz", velodyne_depth=depth)
    assert np.array_equal(read_lidar_npz(tmp_path / "d.npz"), depth)
    np.savez(tmp_path / "bad.npz", depth=depth)
    with pytest.raises(InputError, match="no 'velodyne_depth'"):
        read_lidar_npz(tmp_path / "bad.npz")
    np.savez(tmp_path / "neg.npz", velodyne_depth=-depth)
    with pytest.raises(InputError, match="negative"):
        read_lidar_npz(tmp_path / "neg.npz")
    # KITTI depth benchmark: uint16 = metres x 256, 0 = none.
    cv2.imwrite(str(tmp_path / "d.png"), np.round(depth * 256).astype(np.uint16))
    assert np.array_equal(read_depth_png(tmp_path / "d.png"), depth)
    cv2.imwrite(str(tmp_path / "u8.png"), np.zeros((H, W), np.uint8))
    with pytest.raises(InputError, match="uint16"):
        read_depth_png(tmp_path / "u8.png")


def test_source_reads_lidar_depth_npz_first_then_png(tmp_path):
    drive = _write_drive(tmp_path, {1: _record(LAT0, LON0, 0, 10), 2: _record(LAT0, LON0, 0, 10),
                                    3: _record(LAT0, LON0, 0, 10)})
    npz_dir = drive / "proj_depth" / "velodyne" / "image_02"
    png_dir = drive / "proj_depth" / "groundtruth" / "image_02"
    npz_dir.mkdir(parents=True)
    png_dir.mkdir(parents=True)
    d_npz = np.zeros((H, W), np.float32)
    d_npz[1, 1] = 7.0
    d_png = np.zeros((H, W), np.float32)
    d_png[3, 4] = 9.5
    np.savez(npz_dir / "0000000002.npz", velodyne_depth=d_npz)
    cv2.imwrite(str(png_dir / "0000000002.png"), np.round(d_png * 256).astype(np.uint16))
    cv2.imwrite(str(png_dir / "0000000003.png"), np.round(d_png * 256).astype(np.uint16))
    src = KittiRawSource(tmp_path)
    p2, p3 = src[0], src[1]
    assert torch.equal(p2.gt.depth, torch.from_numpy(d_npz))  # npz wins where both exist
    assert torch.equal(p3.gt.depth, torch.from_numpy(d_png))
    assert p2.gt.moving is None  # KITTI raw has no moving-object mask: not invented
    # No timestamps file: 10 Hz.
    assert p2.meta["dt"] == pytest.approx(0.1)
    np.savez(npz_dir / "0000000002.npz", velodyne_depth=np.zeros((H + 1, W), np.float32))
    with pytest.raises(InputError, match=r"depth .*0000000002\.npz is 12x9"):
        KittiRawSource(tmp_path)[0]


@needs_lidar
def test_shared_lidar_drive_depth_and_oxts_motion():
    src = KittiRawSource(LIDAR_ROOT)
    assert len(src) == 6
    for p in src:
        d = p.gt.depth
        assert d is not None and d.shape == (375, 1242)
        cover = float((d > 0).float().mean())
        assert 0.02 < cover < 0.08  # ~4 % of pixels have a LiDAR return
        assert 3.0 < float(d[d > 0].min()) and float(d.max()) < 90.0
        # ~8.8 m/s forward at 10 Hz: ~0.9 m per frame along the optical axis, little rotation.
        t = p.motion.t.numpy()
        assert 0.85 < np.linalg.norm(t) < 0.95 and t[2] > 0.85
        assert p.meta["motion_source"] == "oxts (velocity)"
        assert 0.1 < p.meta["dt"] < 0.11


# ------------------------------------------------------------------------------------------------
# Raw Velodyne scans, the depth benchmark's PNGs, drives named by a label
def test_project_velodyne_rounds_as_the_devkit_and_keeps_the_nearest_return():
    from monostixels.data.kitti_raw import project_velodyne

    # Velodyne = camera axes here; P with fx != fy, cx != cy.
    P = np.array([[128.0, 0, 20, 0], [0, 80.0, 10, 0], [0, 0, 1, 0]])  # fx a power of 2: u = 20.5 exactly
    pts = np.array([
        [0.0, 0.0, 5.0, 0.3],      # u = 20, v = 10 -> pixel (row 9, col 19)
        [0.0, 0.0, 2.0, 0.3],      # the same pixel, nearer: kept
        [0.0, 0.0, 8.0, 0.3],      # the same pixel, farther: dropped
        [0.5 * 4 / 128, 0, 4, 0],  # u = 20.5 -> rounds up to 21 -> col 20 (MATLAB's round: half away from 0)
        [-0.6 * 4 / 128, 0, 4, 0],  # u = 19.4 -> 19 -> col 18
        [0.0, 0.0, -3.0, 0.0],     # behind the camera (would land at u = 20): dropped
        [5.0, 0.0, 1.0, 0.0],      # u = 520: outside
    ], np.float32)
    d = project_velodyne(pts, P, (16, 24))
    assert d.shape == (16, 24) and d.dtype == np.float32
    want = np.zeros((16, 24), np.float32)
    want[9, 19], want[9, 20], want[9, 18] = 2.0, 4.0, 4.0
    assert np.array_equal(d, want)


def _velo_drive(tmp: Path, R_rect: np.ndarray, label: str = "0003") -> Path:
    """The tiny OXTS drive with a rotated R_rect_00 and a Velodyne folder."""
    drive = _write_drive(tmp, {1: _record(LAT0, LON0, 0, 10), 2: _record(LAT0, LON0, 0, 10),
                               3: _record(LAT0, LON0, 0, 10)})
    (drive.parent / "calib_cam_to_cam.txt").write_text(
        "R_rect_00: " + " ".join(f"{v:.12e}" for v in R_rect.ravel()) + "\nP_rect_02: "
        + " ".join(f"{v:.6e}" for v in P02.ravel()) + "\n")
    if label != "0003":
        drive = drive.rename(drive.parent / f"2011_01_02_drive_{label}_sync")
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    return drive


def test_source_projects_raw_velodyne_scans_with_the_drive_calibration(tmp_path):
    c, s = math.cos(0.02), math.sin(0.02)
    R_rect = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    drive = _velo_drive(tmp_path, R_rect)
    rng = np.random.default_rng(3)
    # Points ahead of the car (Velodyne x forward, y left, z up), some behind it.
    pts = np.column_stack([rng.uniform(-5, 40, 300), rng.uniform(-0.3, 0.3, 300), rng.uniform(-0.2, 0.2, 300),
                           rng.uniform(0, 1, 300)]).astype(np.float32)
    pts.tofile(drive / "velodyne_points" / "data" / "0000000002.bin")
    # Expected, point by point: X_cam0 = R_rect (R X + T); x = P02 [X_cam0; 1]; pixel round(x/z) - 1; nearest.
    T = np.array([0.0, -0.08, -0.27])
    want = np.zeros((H, W), np.float32)
    for X in pts[:, :3].astype(np.float64):
        x = P02 @ np.r_[R_rect @ (R_CAM_IMU @ X + T), 1.0]
        if x[2] <= 0:
            continue
        col, row = math.floor(x[0] / x[2] + 0.5) - 1, math.floor(x[1] / x[2] + 0.5) - 1
        if 0 <= col < W and 0 <= row < H and (want[row, col] == 0 or x[2] < want[row, col]):
            want[row, col] = x[2]
    assert (want > 0).sum() >= 5
    p = KittiRawSource(tmp_path)[0]
    assert p.meta["depth_from"] == "velodyne_points/data"
    assert np.allclose(p.gt.depth.numpy(), want, atol=1e-4) and np.array_equal(p.gt.depth.numpy() > 0, want > 0)
    # A scan of a size that is not whole returns: one line naming the file.
    (drive / "velodyne_points" / "data" / "0000000002.bin").write_bytes(b"\0" * 10)
    with pytest.raises(InputError, match=r"0000000002\.bin holds .* not a multiple of 4"):
        KittiRawSource(tmp_path)[0]
    # Without the Velodyne calibration the scans cannot be projected: said when the drive is opened.
    (drive.parent / "calib_velo_to_cam.txt").unlink()
    (drive / "oxts").rename(drive / "oxts_off")
    with pytest.raises(InputError, match=r"calib_velo_to_cam\.txt does not exist"):
        KittiRawSource(tmp_path)


def test_depth_sources_in_their_order_of_preference(tmp_path):
    """npz > the benchmark's groundtruth PNG > its velodyne_raw PNG > the raw scan, frame by frame."""
    drive = _velo_drive(tmp_path, np.eye(3))
    dirs = {k: drive / "proj_depth" / k / "image_02" for k in ("velodyne", "groundtruth", "velodyne_raw")}
    for d in dirs.values():
        d.mkdir(parents=True)
    depth = {k: np.zeros((H, W), np.float32) for k in dirs}
    for i, k in enumerate(dirs):
        depth[k][1 + i, 2] = 5.0 + i
    np.savez(dirs["velodyne"] / "0000000002.npz", velodyne_depth=depth["velodyne"])
    for k in ("groundtruth", "velodyne_raw"):
        for n in (2, 3):
            cv2.imwrite(str(dirs[k] / f"{n:010d}.png"), np.round(depth[k] * 256).astype(np.uint16))
    cv2.imwrite(str(dirs["velodyne_raw"] / "0000000001.png"), np.round(depth["velodyne_raw"] * 256).astype(np.uint16))
    np.zeros((0, 4), np.float32).tofile(drive / "velodyne_points" / "data" / "0000000003.bin")
    src = KittiRawSource(tmp_path)  # pairs: frames 2 and 3
    p2, p3 = src[0], src[1]
    assert p2.meta["depth_from"] == "proj_depth/velodyne/image_02" and torch.equal(p2.gt.depth, torch.from_numpy(depth["velodyne"]))
    assert p3.meta["depth_from"] == "proj_depth/groundtruth/image_02" and torch.equal(p3.gt.depth, torch.from_numpy(depth["groundtruth"]))
    for n in (2, 3):
        (dirs["groundtruth"] / f"{n:010d}.png").unlink()
    (dirs["velodyne"] / "0000000002.npz").unlink()
    p2, p3 = KittiRawSource(tmp_path)
    assert p2.meta["depth_from"] == p3.meta["depth_from"] == "proj_depth/velodyne_raw/image_02"
    assert torch.equal(p3.gt.depth, torch.from_numpy(depth["velodyne_raw"]))


def test_a_drive_named_by_a_label_loads_and_numbered_drives_keep_their_names(tmp_path):
    numbered = KittiRawSource(_write_drive(tmp_path / "a", {1: _record(LAT0, LON0, 0, 10),
                                                            2: _record(LAT0, LON0, 0, 10)}).parents[1])
    assert numbered[0].name == "2011_01_02_drive_0003_0000000002" and numbered[0].meta["drive"] == 3
    assert numbered.sequence_key(0) == "kitti_raw/2011_01_02_drive_0003"
    _velo_drive(tmp_path / "b", np.eye(3), label="traffic")
    for drive in (None, "traffic", "2011_01_02_drive_traffic_sync"):
        src = KittiRawSource(tmp_path / "b", drive=drive)
        assert len(src) == 2 and src[0].name == "2011_01_02_drive_traffic_0000000002"
        assert src[0].meta["name_prev"] == "2011_01_02_drive_traffic_0000000001"
        assert src.sequence_key(0) == "kitti_raw/2011_01_02_drive_traffic" and src[0].meta["drive"] == "traffic"
    with pytest.raises(InputError, match="matching drive 3"):
        KittiRawSource(tmp_path / "b", drive=3)
    # Stixel-bottom labels name drives by number: a labelled drive cannot have them.
    (tmp_path / "b" / "2011_01_02" / "2011_01_02_drive_traffic_sync" / "stixel_bottoms_bmvc15.txt").write_text("")
    with pytest.raises(InputError, match="names drives by number"):
        KittiRawSource(tmp_path / "b")


TRAFFIC = SHARED / "kitti_raw_traffic" / "2011_09_26"


@pytest.mark.skipif(not TRAFFIC.is_dir(), reason=f"shared KITTI raw traffic drive not found at {TRAFFIC}")
def test_raw_scan_projection_reproduces_the_shared_velodyne_raw_png(tmp_path):
    """The shared drive's velodyne_raw PNG of frame 1, lifted back to Velodyne points (each return at its pixel's
    devkit coordinate, its depth) and written as a scan: projected with the drive's calibration it gives the PNG."""
    from monostixels.data._camera_files import read_kitti_calib
    from monostixels.data.kitti_raw import velo_to_cam0_rect

    src_drive = TRAFFIC / "2011_09_26_drive_traffic_sync"
    date = tmp_path / "2011_09_26"
    drive = date / "2011_09_26_drive_traffic_sync"
    (drive / "image_02" / "data").mkdir(parents=True)
    (drive / "velodyne_points" / "data").mkdir(parents=True)
    for f in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
        (date / f).write_bytes((TRAFFIC / f).read_bytes())
    for n in (0, 1):
        name = f"{n:010d}.png"
        (drive / "image_02" / "data" / name).symlink_to(src_drive / "image_02" / "data" / name)
    png = read_depth_png(src_drive / "proj_depth" / "velodyne_raw" / "image_02" / "0000000001.png")
    rows, cols = np.nonzero(png)
    z = png[rows, cols].astype(np.float64)
    P = read_kitti_calib(date / "calib_cam_to_cam.txt")["P_rect_02"].reshape(3, 4)
    # P [X_rect; 1] = z [col + 1, row + 1, 1]  ->  X_rect = P[:, :3]^-1 (z [u, v, 1] - P[:, 3]).
    uv1 = np.vstack([(cols + 1) * z, (rows + 1) * z, z])
    X_rect = np.linalg.solve(P[:, :3], uv1 - P[:, 3:4])
    X_velo = np.linalg.inv(velo_to_cam0_rect(date, "the test")) @ np.vstack([X_rect, np.ones(len(z))])
    np.column_stack([X_velo[:3].T, np.zeros(len(z))]).astype(np.float32).tofile(
        drive / "velodyne_points" / "data" / "0000000001.bin")
    depth = KittiRawSource(tmp_path)[0].gt.depth.numpy()
    assert np.array_equal(depth > 0, png > 0) and len(z) > 10000
    assert np.abs(depth - png).max() < 2e-3  # float32 coordinates of points up to ~80 m
