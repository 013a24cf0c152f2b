"""Data sources: loaders on the shared real samples and on tiny files written here, plus bad input."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from monostixels._checks import InputError
from monostixels.data._camera_files import read_distortion, read_intrinsics_file, read_poses_file
from monostixels.data.ddad import DDADSource, pose_matrix, project_points
from monostixels.data.frames import FramesSource
from monostixels.data.kitti2015 import KITTI_STEREO_BASELINE_M, Kitti2015Source
from monostixels.data.kitti_raw import KittiRawSource, read_stixel_bottoms
from monostixels.build import build_source

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
needs_shared = pytest.mark.skipif(not SHARED.is_dir(), reason=f"shared real-data samples not found at {SHARED}")

RAW_DRIVE = SHARED / "kitti_raw" / "2011_09_30" / "2011_09_30_drive_0028_sync"


def _is_rotation(R: torch.Tensor) -> bool:
    R = R.double()
    return bool(torch.allclose(R.T @ R, torch.eye(3, dtype=R.dtype), atol=1e-9)) and abs(float(torch.linalg.det(R)) - 1) < 1e-9


# ------------------------------------------------------------------------------------------------
# Shared real samples
# ------------------------------------------------------------------------------------------------
@needs_shared
def test_kitti_raw_sample_intrinsics_and_motion():
    src = KittiRawSource(SHARED / "kitti_raw")
    assert len(src) == 14  # 15 frames 1110..1124 -> 14 consecutive pairs
    pair = src[0]
    assert pair.size == (370, 1226)
    # K from P_rect_02 of calib_cam_to_cam.txt (2011_09_30).
    K = pair.camera.K
    assert torch.allclose(K, torch.tensor([[707.0912, 0, 601.8873], [0, 707.0912, 183.1104], [0, 0, 1]], dtype=K.dtype))
    assert pair.meta["frame"] == 1111 and pair.meta["frame_prev"] == 1110
    # Independent computation from the poses file: camera 2 = camera 0 shifted by b = K^-1 P[:, 3].
    P = np.array([7.070912e02, 0, 6.018873e02, 4.688783e01, 0, 7.070912e02, 1.831104e02, 1.178601e-01, 0, 0, 1, 6.203223e-03]).reshape(3, 4)
    b = np.linalg.solve(P[:, :3], P[:, 3])
    lines = {int(l.split()[0]): np.array(l.split()[1:], dtype=float).reshape(3, 4) for l in (RAW_DRIVE / "poses_cam0.txt").read_text().splitlines()}
    Tc, Tp = np.eye(4), np.eye(4)
    Tc[:3], Tp[:3] = lines[1111], lines[1110]
    S = np.eye(4)
    S[:3, 3] = b  # T_cam2_cam0
    T_expected = S @ np.linalg.inv(Tp) @ Tc @ np.linalg.inv(S)
    assert np.allclose(pair.motion.t.numpy(), T_expected[:3, 3], atol=1e-6)
    assert np.allclose(pair.motion.R.numpy(), T_expected[:3, :3], atol=1e-6)
    for p in src:
        t = p.motion.t
        assert _is_rotation(p.motion.R)
        # Forward driving: the previous camera is behind, so static points are farther there.
        assert float(t[2]) > 0.05
        # The car decelerates over the clip: 0.61 m (frame 1111) down to 0.22 m per frame (10 Hz).
        assert 0.2 < p.motion.translation_norm < 0.7
    assert src[0].motion.translation_norm > src[len(src) - 1].motion.translation_norm + 0.3


@needs_shared
def test_kitti_raw_step_composes_motion():
    one = KittiRawSource(SHARED / "kitti_raw", drive=28)
    two = KittiRawSource(SHARED / "kitti_raw", date="2011_09_30", drive="0028", step=2, frames=1)
    assert len(two) == 1 and two[0].meta["frame"] == 1112 and two[0].meta["frame_prev"] == 1110
    # T(1110<-1112) = T(1110<-1111) T(1111<-1112)
    m_a, m_b, m_ab = one[0].motion, one[1].motion, two[0].motion
    assert torch.allclose(m_ab.R, m_a.R @ m_b.R, atol=1e-6)
    assert torch.allclose(m_ab.t, m_a.R @ m_b.t + m_a.t, atol=1e-6)
    assert 0.9 < m_ab.translation_norm < 1.3


@needs_shared
def test_kitti_raw_sample_bottoms():
    src = KittiRawSource(SHARED / "kitti_raw", only_labelled=True)
    frames = [src[i].meta["frame"] for i in range(len(src))]
    assert frames == [1111, 1116, 1121]  # every 5th frame is labelled
    n_lines = {f: 0 for f in frames}
    for line in (RAW_DRIVE / "stixel_bottoms_bmvc15.txt").read_text().splitlines():
        n_lines[int(line.split()[2])] += 1
    for i in range(len(src)):
        p = src[i]
        bt = p.gt.bottoms
        H, W = p.size
        assert bt.shape == (n_lines[p.meta["frame"]], 2)
        assert bool((bt[:, 0] >= 0).all() and (bt[:, 0] < W).all())
        # Bottoms lie on the road: below the horizon (cy ~ 183) and inside the image.
        assert bool((bt[:, 1] > 150).all() and (bt[:, 1] < H).all())
        assert p.gt.depth is None and p.gt.flow is None  # nothing invented
    # Unlabelled frames carry no bottoms.
    assert KittiRawSource(SHARED / "kitti_raw", frames=2)[1].gt.bottoms is None


@needs_shared
def test_ddad_sample_depth_motion_moving():
    src = DDADSource(SHARED / "ddad_dgp")
    assert len(src) == 2  # three timesteps
    p = src[0]
    assert p.size == (1216, 1936)
    K = p.camera.K
    assert math.isclose(float(K[0, 0]), 2167.6926048451924) and math.isclose(float(K[1, 2]), 604.9892891421556)
    # The ego vehicle stands still: real (not faked) near-zero translation, no rotation.
    assert p.motion.translation_norm < 0.01
    assert float((p.motion.R - torch.eye(3, dtype=p.motion.R.dtype)).abs().max()) < 1e-3
    d = p.gt.depth
    valid = d > 0
    assert int(valid.sum()) > 3000
    assert float(d[valid].min()) > 3.0 and float(d[valid].max()) < 300.0
    assert 5.0 < float(d[valid].median()) < 40.0
    # The bottom image row sees the road at about h * fy / (H - cy) metres.
    h = p.camera.height
    assert 1.3 < h < 1.7
    bottom = d[-40:][d[-40:] > 0]
    expected = h * float(K[1, 1]) / (1216 - 20 - float(K[1, 2]))
    assert abs(float(bottom.median()) - expected) < 0.15 * expected
    # Moving pixels: a subset of the depth pixels, from boxes that moved > 0.2 m.
    mv = p.gt.moving
    assert mv is not None and int(mv.sum()) > 20 and bool((mv <= valid).all())
    assert len(p.meta["moving_instances"]) > 0


@needs_shared
def test_kitti2015_sample_direction():
    src = build_source({"name": "kitti2015", "root": str(SHARED / "kitti2015"), "fx": 721.5377, "cx": 609.5593, "cy": 172.854})
    assert len(src) == 1
    p = src[0]
    assert p.meta["previous"] == "11" and p.meta["time_reversed"] is True
    ref = cv2.imread(str(SHARED / "kitti2015/training/image_2/000000_10.png"))[:, :, ::-1]
    nxt = cv2.imread(str(SHARED / "kitti2015/training/image_2/000000_11.png"))[:, :, ::-1]
    assert torch.equal((p.image * 255).round().byte().permute(1, 2, 0), torch.from_numpy(ref.copy()))
    assert torch.equal((p.image_prev * 255).round().byte().permute(1, 2, 0), torch.from_numpy(nxt.copy()))
    assert float(p.camera.K[0, 0]) == 721.5377 and float(p.camera.K[1, 1]) == 721.5377
    assert p.motion is None and p.gt.depth is None  # the sample has no ground truth


# ------------------------------------------------------------------------------------------------
# Tiny layouts written here
# ------------------------------------------------------------------------------------------------
def _write_img(path: Path, h: int = 8, w: int = 12, value: int = 0) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.zeros((h, w, 3), np.uint8)
    img[..., 2] = value  # red in BGR
    img[0, 0] = (10, 20, 30)
    assert cv2.imwrite(str(path), img)


P02 = np.array([[500.0, 0, 6.0, 30.0], [0, 480.0, 4.0, 0.5], [0, 0, 1, 0.002]])


def _write_raw(tmp: Path, frames=(5, 6, 7), poses: dict[int, np.ndarray] | None = None, p02: str | None = None) -> Path:
    date = tmp / "2011_01_02"
    drive = date / "2011_01_02_drive_0003_sync"
    for n in frames:
        _write_img(drive / "image_02" / "data" / f"{n:010d}.png", value=n * 10)
    p02 = p02 if p02 is not None else " ".join(f"{v:.6e}" for v in P02.ravel())
    (date / "calib_cam_to_cam.txt").write_text(f"calib_time: 09-Jan-2012 13:59:33\nS_rect_02: 12 8\nP_rect_02: {p02}\n")
    if poses is not None:
        lines = [f"{n:010d} " + " ".join(f"{v:.12e}" for v in T[:3].ravel()) for n, T in poses.items()]
        (drive / "poses_cam0.txt").write_text("\n".join(lines) + "\n")
    return drive


def _yaw(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def test_kitti_raw_tiny_motion_recovered_exactly(tmp_path):
    T5 = np.eye(4)
    T5[:3, :3] = _yaw(0.1)
    T5[:3, 3] = [2.0, -0.3, 5.0]
    # Camera 0 of frame 6: moved 1.2 m forward and 0.1 m right in frame 5's camera, yawed by 0.05.
    T_5_6 = np.eye(4)
    T_5_6[:3, :3] = _yaw(0.05)
    T_5_6[:3, 3] = [0.1, 0.0, 1.2]
    T6 = T5 @ T_5_6
    _write_raw(tmp_path, frames=(5, 6), poses={5: T5, 6: T6})
    src = KittiRawSource(tmp_path)
    assert len(src) == 1
    p = src[0]
    assert torch.allclose(p.camera.K, torch.tensor([[500.0, 0, 6], [0, 480, 4], [0, 0, 1]], dtype=p.camera.K.dtype))
    # Camera 2: X2 = X0 + b, b = K^-1 P[:, 3]; motion X_prev = R X_cur + t with t = t0 + b - R b.
    b = np.linalg.solve(P02[:, :3], P02[:, 3])
    R_exp = _yaw(0.05)
    t_exp = T_5_6[:3, 3] + b - R_exp @ b
    assert np.allclose(p.motion.R.numpy(), R_exp, atol=1e-9)
    assert np.allclose(p.motion.t.numpy(), t_exp, atol=1e-9)
    # A static point: X_prev = R X_cur + t, checked via world coordinates of camera 2.
    X_cur = np.array([1.0, 0.5, 10.0])
    T_w_c2 = lambda T: T @ np.block([[np.eye(3), -b[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])  # noqa: E731
    Xw = T_w_c2(T6) @ np.r_[X_cur, 1]
    X_prev = np.linalg.solve(T_w_c2(T5), Xw)[:3]
    assert np.allclose(p.motion.R.numpy() @ X_cur + p.motion.t.numpy(), X_prev, atol=1e-9)
    # Image direction: current = frame 6 (red 60), previous = frame 5 (red 50).
    assert round(float(p.image[0, 4, 4]) * 255) == 60 and round(float(p.image_prev[0, 4, 4]) * 255) == 50


def test_read_stixel_bottoms_filters_drive(tmp_path):
    f = tmp_path / "b.txt"
    f.write_text("09_30\t28\t1111\t36\t277\tTrain\n09_30\t28\t1111\t41\t270\tTest\n09_30\t27\t1111\t5\t5\tTrain\n"
                 "10_03\t28\t1111\t5\t5\tTrain\n09_30\t28\t1116\t100\t200\tTrain\n")
    out = read_stixel_bottoms(f, "2011_09_30", 28)
    assert sorted(out) == [1111, 1116]
    assert out[1111][0].tolist() == [[36.0, 277.0], [41.0, 270.0]] and out[1111][1] == ["Train", "Test"]
    f.write_text("09_30 28 1111 x 277 Train\n")
    with pytest.raises(InputError, match="b.txt line 1"):
        read_stixel_bottoms(f, "2011_09_30", 28)


def test_kitti2015_tiny_ground_truth_decoding(tmp_path):
    split = tmp_path / "training"
    _write_img(split / "image_2" / "000003_10.png", value=100)
    _write_img(split / "image_2" / "000003_11.png", value=110)
    (split / "calib_cam_to_cam").mkdir()
    (split / "calib_cam_to_cam" / "000003.txt").write_text("P_rect_02: 700 0 5.5 40 0 690 3.5 0 0 0 1 0\n")
    disp = np.zeros((8, 12), np.uint16)
    disp[2, 3] = int(35.0 * 256)  # 35 px disparity
    (split / "disp_occ_0").mkdir()
    cv2.imwrite(str(split / "disp_occ_0" / "000003_10.png"), disp)
    flow = np.zeros((8, 12, 3), np.uint16)  # BGR = (valid, v, u)
    flow[1, 2] = (1, int(-2.5 * 64 + 2**15), int(3.25 * 64 + 2**15))
    (split / "flow_occ").mkdir()
    cv2.imwrite(str(split / "flow_occ" / "000003_10.png"), flow)
    obj = np.zeros((8, 12), np.uint8)
    obj[5:7, 8:10] = 2
    (split / "obj_map").mkdir()
    cv2.imwrite(str(split / "obj_map" / "000003_10.png"), obj)

    p = Kitti2015Source(tmp_path, fx=1.0, cx=1.0, cy=1.0)[0]  # config intrinsics ignored: calib exists
    assert float(p.camera.K[0, 0]) == 700 and float(p.camera.K[1, 1]) == 690 and float(p.camera.K[0, 2]) == 5.5
    assert math.isclose(float(p.gt.depth[2, 3]), 700 * KITTI_STEREO_BASELINE_M / 35.0, rel_tol=1e-6)
    assert int((p.gt.depth > 0).sum()) == 1
    assert p.gt.flow[:, 1, 2].tolist() == [3.25, -2.5]
    assert bool(p.gt.flow_valid[1, 2]) and int(p.gt.flow_valid.sum()) == 1
    assert int(p.gt.moving.sum()) == 4 and bool(p.gt.moving[5, 8]) and int(p.gt.instances[6, 9]) == 2
    assert round(float(p.image_prev[0, 4, 4]) * 255) == 110

    # With _09 present, auto uses it (true temporal order) and gives no flow ground truth.
    _write_img(split / "image_2" / "000003_09.png", value=90)
    q = Kitti2015Source(tmp_path)[0]
    assert q.meta["previous"] == "09" and q.meta["time_reversed"] is False and q.gt.flow is None
    assert round(float(q.image_prev[0, 4, 4]) * 255) == 90 and q.gt.depth is not None
    assert Kitti2015Source(tmp_path, previous="11")[0].gt.flow is not None


@pytest.mark.parametrize(
    "name,text",
    [
        ("intrinsics.yaml", "fx: 400.5\nfy: 410\ncx: 6.5\ncy: 3.5\n"),
        ("intrinsics.json", json.dumps({"K": [[400.5, 0, 6.5], [0, 410, 3.5], [0, 0, 1]]})),
        ("intrinsics.txt", "400.5 410 6.5 3.5\n"),
        ("cam.txt", "fx = 400.5\nfy = 410\ncx = 6.5\ncy = 3.5\n"),
    ],
)
def test_intrinsics_formats(tmp_path, name, text):
    (tmp_path / name).write_text(text)
    assert read_intrinsics_file(tmp_path / name) == (400.5, 410.0, 6.5, 3.5)


@pytest.mark.parametrize(
    "name,text,want",
    [
        ("k.yaml", "fx: 400.5\nfy: 410\ncx: 6.5\ncy: 3.5\ndistortion: [-0.25, 0.05, 0.001, -0.002, 0.01]\n",
         [-0.25, 0.05, 0.001, -0.002, 0.01]),
        ("k.json", json.dumps({"K": [[400.5, 0, 6.5], [0, 410, 3.5], [0, 0, 1]], "distortion": [-0.1, 0.02, 0, 0]}),
         [-0.1, 0.02, 0, 0]),
        ("k.txt", "fx = 400.5\nfy = 410\ncx = 6.5\ncy = 3.5\ndistortion = [[-0.2, 0.1, 0, 0, 0, 0.01, 0, 0]]\n",
         [-0.2, 0.1, 0, 0, 0, 0.01, 0, 0]),  # OpenCV's 1 x N print of the rational model
        ("k.yaml", "fx: 400.5\nfy: 410\ncx: 6.5\ncy: 3.5\n", None),
        ("k.yaml", "fx: 400.5\nfy: 410\ncx: 6.5\ncy: 3.5\ndistortion: null\n", None),
        ("k.txt", "400.5 410 6.5 3.5\n", None),
    ],
)
def test_intrinsics_distortion_key(tmp_path, name, text, want):
    (tmp_path / name).write_text(text)
    assert read_intrinsics_file(tmp_path / name) == (400.5, 410.0, 6.5, 3.5)
    d = read_distortion(tmp_path / name)
    assert (d is None) if want is None else (d.dtype == np.float64 and d.tolist() == want)


@pytest.mark.parametrize("value,want", [("[-0.2, 0.1, 0]", "holds 3 numbers"), ("[1, 2, 3, 4, 5, 6]", "holds 6 numbers"),
                                        ("-0.2", "must be a list"), ("[a, b, c, d, e]", "non-number"),
                                        ("[.nan, 0, 0, 0, 0]", "NaN")])
def test_intrinsics_bad_distortion_fails_naming_file_and_key(tmp_path, value, want):
    (tmp_path / "k.yaml").write_text(f"fx: 400\ncx: 6\ncy: 3\ndistortion: {value}\n")
    for read in (read_intrinsics_file, read_distortion):
        with pytest.raises(InputError, match=rf"intrinsics: .*k\.yaml key distortion .*{want}") as err:
            read(tmp_path / "k.yaml")
        assert "\n" not in str(err.value)


def test_frame_pair_checks_its_ignore_mask():
    from monostixels.data.base import FramePair
    from monostixels.data._camera_files import make_camera

    cam = make_camera(50.0, 50.0, 6.0, 4.0, 1.5)
    img = torch.zeros(3, 8, 12)
    ok = FramePair(img, img, cam, meta={"ignore_mask": torch.zeros(8, 12, dtype=torch.bool)})
    assert ok.meta["ignore_mask"].shape == (8, 12)
    with pytest.raises(InputError, match=r"ignore_mask.*expected shape \(8, 12\)"):
        FramePair(img, img, cam, meta={"ignore_mask": torch.zeros(12, 8, dtype=torch.bool)})
    with pytest.raises(InputError, match=r"ignore_mask.*bool"):
        FramePair(img, img, cam, meta={"ignore_mask": torch.zeros(8, 12)})


def test_intrinsics_bad_image_size_keys(tmp_path):
    (tmp_path / "k.yaml").write_text("fx: 400\ncx: 6\ncy: 3\nwidth: 1280\n")
    with pytest.raises(InputError, match=r"k\.yaml keys width, height must both be positive integers"):
        read_intrinsics_file(tmp_path / "k.yaml")


def test_frames_folder_undistorts_and_carries_the_mask(tmp_path):
    rng = np.random.default_rng(0)
    H, W = 48, 64
    img = cv2.GaussianBlur(rng.integers(0, 256, (H, W, 3)).astype(np.uint8), (5, 5), 1.5)
    for i in range(3):
        assert cv2.imwrite(str(tmp_path / f"{i:02d}.png"), img)
    K = np.array([[60.0, 0, 30.5], [0, 58.0, 24.0], [0, 0, 1]])
    d = np.array([-0.3, 0.08, 0.002, -0.001, 0.0])
    (tmp_path / "intrinsics.yaml").write_text("fx: 60\nfy: 58\ncx: 30.5\ncy: 24\ndistortion: [-0.3, 0.08, 0.002, -0.001, 0]\n")
    mask = np.zeros((H, W), np.uint8)
    mask[40:] = 255
    cv2.imwrite(str(tmp_path / "bonnet.png"), mask)
    src = build_source({"name": "frames", "root": str(tmp_path), "mask": str(tmp_path / "bonnet.png")})
    p = src[0]
    # OpenCV's own undistortion with the same camera matrix is the reference.
    want = cv2.cvtColor(cv2.undistort(img, K, d), cv2.COLOR_BGR2RGB).transpose(2, 0, 1) / 255.0
    got = p.image.double().numpy()
    assert np.abs(got - want)[:, 2:-2, 2:-2].max() < 3 / 255
    assert np.abs(got - img.transpose(2, 0, 1)[::-1] / 255.0).max() > 0.1  # it did change the image
    assert torch.allclose(p.camera.K, torch.from_numpy(K).to(p.camera.K.dtype))
    ignore = p.meta["ignore_mask"]
    assert ignore.dtype == torch.bool and tuple(ignore.shape) == (H, W)
    assert bool(ignore[-1].all()) and not bool(ignore[:30].any())
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((H // 2, W // 2), np.uint8))
    with pytest.raises(InputError, match=rf"data.mask: .*small\.png is {W // 2}x{H // 2} pixels, the frames are {W}x{H}"):
        build_source({"name": "frames", "root": str(tmp_path), "mask": str(tmp_path / "small.png")})
    # An intrinsics file for another image size is refused (also without distortion or mask).
    (tmp_path / "other.yaml").write_text("fx: 60\nfy: 58\ncx: 30.5\ncy: 24\nwidth: 128\nheight: 96\n")
    with pytest.raises(InputError, match=rf"other\.yaml holds for 128x96 images .* are {W}x{H}"):
        build_source({"name": "frames", "root": str(tmp_path), "intrinsics": str(tmp_path / "other.yaml")})
    (tmp_path / "other.yaml").write_text(f"fx: 60\nfy: 58\ncx: 30.5\ncy: 24\nwidth: {W}\nheight: {H}\n")
    assert "ignore_mask" not in build_source({"name": "frames", "root": str(tmp_path),
                                             "intrinsics": str(tmp_path / "other.yaml")})[0].meta
    # Every image must have the size the tables were set up for.
    assert cv2.imwrite(str(tmp_path / "01.png"), img[:40]) and cv2.imwrite(str(tmp_path / "02.png"), img[:40])
    with pytest.raises(InputError, match=r"02\.png is 64x40, the first image 00\.png 64x48"):
        src[1]


def test_frames_folder_pairs_intrinsics_and_poses(tmp_path):
    for i in range(4):
        _write_img(tmp_path / f"img_{i:02d}.png", value=10 * i)
    (tmp_path / "intrinsics.yaml").write_text("fx: 300\nfy: 310\ncx: 6\ncy: 4\n")
    cfg = {"data": {"name": "frames", "root": str(tmp_path), "frames": None}, "camera": {"height": 1.3, "pitch": 0.0}}
    src = build_source(cfg)
    assert len(src) == 3 and src[0].name == "img_01" and src[0].meta["path_prev"].endswith("img_00.png")
    assert src[0].motion is None and src[0].camera.height == 1.3
    assert torch.allclose(src[0].camera.K, torch.tensor([[300.0, 0, 6], [0, 310, 4], [0, 0, 1]], dtype=src[0].camera.K.dtype))
    # 4x4 poses, one line per image: camera i at z = 0.5 i (driving forward).
    lines = []
    for i in range(4):
        T = np.eye(4)
        T[2, 3] = 0.5 * i
        lines.append(" ".join(str(v) for v in T.ravel()))
    (tmp_path / "poses.txt").write_text("\n".join(lines))
    src = build_source({"name": "frames", "root": str(tmp_path), "poses": str(tmp_path / "poses.txt"),
                       "step": 2, "camera_height": 1.1}, {"height": 1.3})
    assert len(src) == 2 and src[0].camera.height == 1.1
    assert torch.allclose(src[0].motion.t, torch.tensor([0.0, 0.0, 1.0], dtype=src[0].motion.t.dtype))


def _grey_folder(root: Path, n: int, h: int, w: int) -> None:
    """``n`` images ``h x w`` with a horizontal ramp (so that a resize has something to average)."""
    root.mkdir(parents=True, exist_ok=True)
    ramp = np.tile(np.linspace(0, 250, w, dtype=np.float64)[None, :], (h, 1))
    for i in range(n):
        img = np.clip(ramp + 3 * i, 0, 255).astype(np.uint8)
        assert cv2.imwrite(str(root / f"{i:03d}.png"), np.dstack([img, img // 2, 255 - img]))


def test_frames_folder_field_of_view_frame_rate_and_resize(tmp_path):
    """data=frames without an intrinsics file: fx = fy = (W/2) / tan(hfov/2) at the image centre; dt = step / fps;
    a resize scales the images and the intrinsics (pixel centres at integers)."""
    root = tmp_path / "f"
    _grey_folder(root, 5, 40, 64)  # W != H
    src = build_source({"name": "frames", "root": str(root), "hfov_deg": 90.0, "fps": 20.0, "step": 2, "resize": None})
    K = src[0].camera.K.numpy()
    # tan(45 deg) = 1: fx = W / 2 = 32, principal point ((W-1)/2, (H-1)/2).
    assert np.allclose(K, [[32.0, 0, 31.5], [0, 32.0, 19.5], [0, 0, 1]])
    assert src[0].image.shape == (3, 40, 64) and src[0].meta["intrinsics"] == "hfov 90 deg (approximate)"
    assert src[0].meta["dt"] == pytest.approx(2 / 20.0)
    # Keyframe pairs reach back whole steps: 2 steps = 4 images = 0.2 s at 20 fps.
    assert [f.dt for f in src.previous_frames(len(src) - 1, 2)] == pytest.approx([0.1, 0.2])
    # A factor: the image as cv2's area resize makes it, the intrinsics with it.
    half = build_source({"name": "frames", "root": str(root), "hfov_deg": 90.0, "resize": 0.5})
    want = cv2.cvtColor(cv2.resize(cv2.imread(str(root / "001.png")), (32, 20), interpolation=cv2.INTER_AREA),
                        cv2.COLOR_BGR2RGB)
    got = (half[0].image.permute(1, 2, 0).numpy() * 255).round()
    assert half[0].image.shape == (3, 20, 32) and np.abs(got - want).max() <= 1
    assert np.allclose(half[0].camera.K.numpy(), [[16.0, 0, 15.5], [0, 16.0, 9.5], [0, 0, 1]])
    # The default frame rate is 10 fps; the default resize (auto) keeps a small folder as it is.
    plain = build_source({"name": "frames", "root": str(root), "hfov_deg": 90.0})
    assert plain[0].meta["dt"] == pytest.approx(0.1) and plain[0].image.shape == (3, 40, 64)


def test_frames_folder_auto_resize_of_a_720p_folder(tmp_path):
    root = tmp_path / "f"
    _grey_folder(root, 2, 720, 1280)
    src = build_source({"name": "frames", "root": str(root), "hfov_deg": 90.0})
    assert src[0].image.shape == (3, 530, 942)  # about 0.5 MP, as data=video's auto
    fx = 640.0 * 942 / 1280  # (W/2)/tan(45 deg) at the stored size, scaled with the width
    assert float(src[0].camera.K[0, 0]) == pytest.approx(fx)
    assert float(src[0].camera.K[0, 2]) == pytest.approx(639.5 * 942 / 1280 + 0.5 * 942 / 1280 - 0.5)


def test_frames_folder_intrinsics_file_wins_over_the_field_of_view(tmp_path, caplog):
    root = tmp_path / "f"
    _grey_folder(root, 2, 40, 64)
    (root / "intrinsics.yaml").write_text("fx: 50\nfy: 52\ncx: 30\ncy: 18\n")
    with caplog.at_level("WARNING"):
        src = FramesSource(root, hfov_deg=90.0)
    assert np.allclose(src[0].camera.K.numpy(), [[50.0, 0, 30], [0, 52.0, 18], [0, 0, 1]])
    assert src[0].meta["intrinsics"].endswith("intrinsics.yaml")
    said = [r.getMessage() for r in caplog.records if "hfov_deg" in r.getMessage()]
    assert len(said) == 1 and "not used" in said[0] and "intrinsics.yaml" in said[0]


@pytest.mark.parametrize("kwargs,want", [
    ({}, r"no intrinsics: set data\.intrinsics=FILE .* or data\.hfov_deg=DEGREES"),
    ({"hfov_deg": 180.0}, r"data\.hfov_deg: .*\(0, 180\)"),
    ({"hfov_deg": 90.0, "fps": 0.0}, r"data\.fps: .*positive"),
    ({"hfov_deg": 90.0, "resize": "big"}, r"data\.resize: expected auto"),
])
def test_frames_folder_bad_lens_settings_fail_in_one_line(tmp_path, kwargs, want):
    root = tmp_path / "f"
    _grey_folder(root, 2, 40, 64)
    with pytest.raises(InputError, match=want) as err:
        FramesSource(root, **kwargs)
    assert "\n" not in str(err.value)


def test_ddad_helpers_pose_and_zbuffer():
    # 90 degrees about z: x -> y.
    q = {"rotation": {"qw": math.cos(math.pi / 4), "qx": 0.0, "qy": 0.0, "qz": math.sin(math.pi / 4)},
         "translation": {"x": 1.0, "y": 2.0, "z": 3.0}}
    T = pose_matrix(q, "test")
    assert np.allclose(T @ [1, 0, 0, 1], [1, 3, 3, 1])
    with pytest.raises(InputError, match="norm"):
        pose_matrix({"rotation": {"qw": 2.0}, "translation": {}}, "test")
    K = np.array([[10.0, 0, 2], [0, 10, 1], [0, 0, 1]])
    X = np.array([[0.0, 0, 4], [0.0, 0, 2], [0.0, 0, -1], [10.0, 0, 1], [0.2, 0.1, 1]])
    rows, cols, idx = project_points(X, K, (3, 5))
    hits = {(int(r), int(c)): int(i) for r, c, i in zip(rows, cols, idx)}
    assert hits == {(1, 2): 1, (2, 4): 4}  # nearest of the two on the axis; behind / outside dropped


# ------------------------------------------------------------------------------------------------
# Bad input: InputError naming the file / input
# ------------------------------------------------------------------------------------------------
def test_missing_root_and_unknown_source(tmp_path):
    missing = tmp_path / "nope"
    for name in ("kitti2015", "kitti_raw", "ddad", "frames"):
        with pytest.raises(InputError, match="nope"):
            build_source({"name": name, "root": str(missing)})
        with pytest.raises(InputError, match="data.root"):
            build_source({"name": name, "root": None})
    with pytest.raises(InputError, match="unknown data source 'kitti'"):
        build_source({"name": "kitti"})


def test_empty_folder_and_missing_intrinsics(tmp_path):
    with pytest.raises(InputError, match="holds no image files"):
        FramesSource(tmp_path)
    _write_img(tmp_path / "a.png")
    _write_img(tmp_path / "b.png")
    with pytest.raises(InputError, match="intrinsics"):
        FramesSource(tmp_path)
    with pytest.raises(InputError, match="k.yaml"):
        FramesSource(tmp_path, intrinsics=tmp_path / "k.yaml")
    (tmp_path / "k.yaml").write_text("fx: 300\ncx: 6\n")
    with pytest.raises(InputError, match=r"k\.yaml lacks cy"):
        FramesSource(tmp_path, intrinsics=tmp_path / "k.yaml")
    (tmp_path / "k.yaml").write_text("fx: -3\ncx: 6\ncy: 2\n")
    with pytest.raises(InputError, match=r"k\.yaml.*fx, fy > 0"):
        FramesSource(tmp_path, intrinsics=tmp_path / "k.yaml")
    (tmp_path / "k.txt").write_text("1 2 3\n")
    with pytest.raises(InputError, match=r"k\.txt holds 3 numbers"):
        read_intrinsics_file(tmp_path / "k.txt")


def test_unreadable_image_and_size_mismatch(tmp_path):
    _write_img(tmp_path / "a.png")
    _write_img(tmp_path / "b.png", h=9)
    (tmp_path / "c.png").write_bytes(b"not an image at all")
    (tmp_path / "intrinsics.txt").write_text("300 300 6 4")
    src = FramesSource(tmp_path)
    assert len(src) == 2  # listing succeeds; reading fails loudly, never skipped
    with pytest.raises(InputError, match=r"b\.png \(current\).*a\.png \(previous\) differ in size"):
        src[0]
    with pytest.raises(InputError, match=r"c\.png"):
        src[1]


def test_kitti_raw_bad_calibration_and_poses(tmp_path):
    _write_raw(tmp_path, p02="1 2 3")
    with pytest.raises(InputError, match=r"calib_cam_to_cam\.txt entry P_rect_02 must hold 12"):
        KittiRawSource(tmp_path)
    (tmp_path / "2011_01_02" / "calib_cam_to_cam.txt").unlink()
    with pytest.raises(InputError, match=r"calib_cam_to_cam\.txt does not exist"):
        KittiRawSource(tmp_path)
    drive = _write_raw(tmp_path)
    (drive / "poses_cam0.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"poses_cam0\.txt must start each line with the raw frame number"):
        KittiRawSource(tmp_path)  # 12 values = no frame id: ambiguous for raw frames
    (drive / "poses_cam0.txt").write_text("0000000005 2 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"poses_cam0\.txt line 1: rotation"):
        KittiRawSource(tmp_path)
    with pytest.raises(InputError, match="no DATE_drive_NNNN_sync folders matching drive 9"):
        KittiRawSource(tmp_path, drive=9)


def test_kitti2015_missing_calibration_file(tmp_path):
    split = tmp_path / "training"
    _write_img(split / "image_2" / "000001_10.png")
    _write_img(split / "image_2" / "000001_11.png")
    (split / "calib_cam_to_cam").mkdir()
    with pytest.raises(InputError, match=r"000001\.txt does not exist"):
        Kitti2015Source(tmp_path)
    (split / "calib_cam_to_cam").rmdir()
    with pytest.raises(InputError, match="no calibration folder"):
        Kitti2015Source(tmp_path)
    with pytest.raises(InputError, match=r"000001_09\.png"):
        Kitti2015Source(tmp_path, previous="09", fx=700, cx=6, cy=4)


def test_poses_file_malformed(tmp_path):
    f = tmp_path / "p.txt"
    f.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0\n")
    with pytest.raises(InputError, match=r"p\.txt line 2 has 3 values"):
        read_poses_file(f)
    f.write_text("1 0 0 0 0 1 0 0 0 0 1 nan\n")
    with pytest.raises(InputError, match="NaN"):
        read_poses_file(f)


def test_ddad_missing_scene(tmp_path):
    with pytest.raises(InputError, match="no scene_"):
        DDADSource(tmp_path)
    (tmp_path / "s1").mkdir()
    (tmp_path / "s1" / "scene_x.json").write_text("{not json")
    with pytest.raises(InputError, match=r"scene_x\.json is not valid JSON"):
        DDADSource(tmp_path)


def test_make_source_synthetic_dispatch():
    src = build_source({"data": {"name": "synthetic", "frames": 3, "seed": 2, "scale": 0.25, "density": 1.0}})
    assert type(src).__name__ == "SyntheticSource" and len(src) == 3
    assert src.scene_seed(1) == 2 * 100_000 + 1


def test_every_source_of_the_package_has_the_source_attributes():
    """Every source class of monostixels.data states fps, step, skipped_frames and restarts (SourceAttributes)."""
    import importlib
    import inspect
    import pkgutil

    import monostixels.data as data
    from monostixels.data.base import SourceAttributes

    classes = set()
    for mod in pkgutil.iter_modules(data.__path__):
        module = importlib.import_module(f"monostixels.data.{mod.name}")
        classes |= {c for n, c in inspect.getmembers(module, inspect.isclass)
                    if n.endswith("Source") and c.__module__ == module.__name__ and not getattr(c, "_is_protocol", False)}
    assert {c.__name__ for c in classes} >= {"LazySource", "FramesSource", "VideoSource", "LiveVideoSource",
                                             "SyntheticSource", "SyntheticSequenceSource", "CamVidSource"}
    missing = sorted(c.__name__ for c in classes if not issubclass(c, SourceAttributes))
    assert not missing, f"sources without SourceAttributes: {missing}"


def test_a_source_of_ones_own_needs_only_len_and_getitem():
    """docs/usage.md, "A data source of your own": __len__ and __getitem__ suffice; the attributes it
    leaves out read as their defaults, those it has are read."""
    from monostixels.data.base import SequenceSource, SourceInfo, source_info
    from monostixels.data.synthetic import SyntheticSource, render_pair
    from monostixels.output.writers import video_fps

    pair = render_pair(0, scale=0.125)

    class Own:
        def __len__(self) -> int:
            return 1

        def __getitem__(self, index: int):
            return pair

    own = Own()
    assert isinstance(own, SequenceSource) and isinstance([pair], SequenceSource)
    assert source_info(own) == SourceInfo(fps=None, step=1, skipped_frames=[], restarts=[]) == source_info([pair])
    assert video_fps(own) == 5.0
    own.fps, own.step, own.skipped_frames = 30.0, 3, ("a.png",)
    assert source_info(own) == SourceInfo(fps=30.0, step=3, skipped_frames=["a.png"], restarts=[])
    assert video_fps(own) == pytest.approx(10.0)
    assert source_info(SyntheticSource(frames=1, scale=0.125)) == SourceInfo()


def test_frame_info_reads_the_keys_sources_write():
    """FrameInfo: a typed view of meta; a key a source does not write reads None."""
    from monostixels.data.base import FrameInfo

    meta = {"source": "video", "path": "clip.mp4", "frame": 7, "frame_prev": 6, "capture_time_s": 0.7,
            "capture_time_prev_s": 0.6, "dropped_before": 2, "realtime": True, "frame_index": 70,
            "frame_index_prev": 69, "motion_source": "poses", "nominal_camera": True, "anything": 1}
    info = FrameInfo.of(meta)
    assert (info.source, info.path, info.frame, info.frame_prev, info.capture_time_s, info.capture_time_prev_s,
            info.dropped_before, info.realtime, info.frame_index, info.frame_index_prev, info.motion_source,
            info.nominal_camera) == ("video", "clip.mp4", 7, 6, 0.7, 0.6, 2, True, 70, 69, "poses", True)
    assert info.dataset is None and info.path_prev is None and info.full_pair is None
