"""Camera calibration from chessboard views: a known synthetic lens recovered, the intrinsics file
round trip, the shared dashcam boards against OpenCV's own calibration, bad input."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from monostixels._checks import InputError
from monostixels.data._camera_files import check_intrinsics_size, read_distortion, read_intrinsics_file
from monostixels.data.calibration import MIN_BOARDS, calibrate_images, write_intrinsics_file
from tests._boards import write_board_views

#: The synthetic lens: fx != fy, an off-centre principal point, barrel distortion with a tangential part.
K_TRUE = np.array([[330.0, 0.0, 203.0], [0.0, 325.0, 148.0], [0.0, 0.0, 1.0]])
D_TRUE = np.array([-0.22, 0.04, 0.001, -0.0005, 0.0])
SIZE = (300, 400)  # (H, W)

CAMERA_CAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "dashcam" / "camera_cal"


@pytest.fixture(scope="module")
def views(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("boards")
    write_board_views(folder, K_TRUE, D_TRUE, SIZE, n=8)
    cv2.imwrite(str(folder / "view_99_blank.png"), np.full(SIZE, 128, np.uint8))  # no board in it
    return folder


def test_calibration_recovers_a_known_lens(views):
    cal = calibrate_images(str(views / "*.png"), board=(9, 6))
    assert cal.size == SIZE and cal.board == (9, 6)
    assert len(cal.images) == 9 and len(cal.boards) == 8 and [p.name for p in cal.no_board] == ["view_99_blank.png"]
    assert cal.fx == pytest.approx(K_TRUE[0, 0], rel=0.01) and cal.fy == pytest.approx(K_TRUE[1, 1], rel=0.01)
    assert cal.cx == pytest.approx(K_TRUE[0, 2], abs=3.0) and cal.cy == pytest.approx(K_TRUE[1, 2], abs=3.0)
    assert cal.distortion[0] == pytest.approx(D_TRUE[0], abs=0.02)
    assert len(cal.distortion) == 5 and cal.rms_px < 0.5
    # A folder works as the glob of its images.
    assert calibrate_images(views).fx == pytest.approx(cal.fx)


def test_intrinsics_file_round_trip(views, tmp_path):
    cal = calibrate_images(str(views / "view_0*.png"))
    path = write_intrinsics_file(cal, tmp_path / "sub" / "intrinsics.yaml")
    assert read_intrinsics_file(path) == (cal.fx, cal.fy, cal.cx, cal.cy)
    assert read_distortion(path).tolist() == list(cal.distortion)
    assert "RMS reprojection error" in path.read_text()
    # It says which image size it holds for: frames of another size are refused.
    check_intrinsics_size(path, SIZE, "the frames")
    with pytest.raises(InputError, match=r"holds for 400x300 images .*the frames are 800x600"):
        check_intrinsics_size(path, (600, 800), "the frames")


@pytest.mark.skipif(not CAMERA_CAL.is_dir(), reason="shared dashcam chessboards (../shared/data/dashcam/camera_cal) not present")
def test_dashcam_boards_match_opencvs_own_calibration():
    """The issue's acceptance: fx within 2 % and k1 within 0.03 of OpenCV's calibration of the same boards."""
    # Two of the 20 views are 1281x721: the default refuses mixed sizes and says how to choose one.
    with pytest.raises(InputError, match=r"different sizes.*1281x721.*calibrate\.size=\[1280,720\]"):
        calibrate_images(str(CAMERA_CAL / "*.jpg"))
    cal = calibrate_images(str(CAMERA_CAL / "*.jpg"), board=(9, 6), size=(1280, 720))
    assert cal.size == (720, 1280) and len(cal.other_size) == 2 and len(cal.boards) >= 10
    # The reference: OpenCV's tutorial recipe, directly, on the 1280x720 views.
    grid = np.zeros((54, 3), np.float32)
    grid[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2)
    corners = []
    for p in sorted(CAMERA_CAL.glob("*.jpg")):
        g = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if g.shape != (720, 1280):
            continue
        ok, c = cv2.findChessboardCorners(g, (9, 6), None)
        if ok:
            corners.append(cv2.cornerSubPix(g, c, (11, 11), (-1, -1),
                                            (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)))
    rms, K, d, _, _ = cv2.calibrateCamera([grid] * len(corners), corners, (1280, 720), None, None)
    assert len(corners) == len(cal.boards)
    assert cal.fx == pytest.approx(K[0, 0], rel=0.02) and cal.fy == pytest.approx(K[1, 1], rel=0.02)
    assert abs(cal.distortion[0] - d.ravel()[0]) < 0.03
    assert cal.distortion[0] < 0  # barrel
    assert cal.rms_px < 1.0


def test_bad_input_fails_clearly(tmp_path, views):
    with pytest.raises(InputError, match=r"no image file matches '.*nope/\*\.jpg'"):
        calibrate_images(str(tmp_path / "nope" / "*.jpg"))
    blank = tmp_path / "blank"
    blank.mkdir()
    for k in range(3):
        cv2.imwrite(str(blank / f"{k}.png"), np.full(SIZE, 40 * k, np.uint8))
    with pytest.raises(InputError, match=r"9x6 board .* found in 0 of the 3 images of '.*blank/\*\.png'"):
        calibrate_images(str(blank / "*.png"))
    few = sorted(views.glob("view_0*.png"))[: MIN_BOARDS - 1] + sorted(blank.glob("*.png"))
    with pytest.raises(InputError, match=rf"found in {MIN_BOARDS - 1} of the {MIN_BOARDS + 2} images.*at least {MIN_BOARDS}"):
        calibrate_images(few)
    cv2.imwrite(str(blank / "3.png"), np.zeros((61, 80), np.uint8))
    with pytest.raises(InputError, match=r"different sizes \(3 of 400x300, 1 of 80x61 \(3\.png\)\)"):
        calibrate_images(str(blank / "*.png"))
    with pytest.raises(InputError, match=r"no image of 640x480"):
        calibrate_images(str(blank / "*.png"), size=(640, 480))
    with pytest.raises(InputError, match="calibrate.board"):
        calibrate_images(str(views / "*.png"), board=(9,))
    (blank / "4.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match=r"cannot read .*4\.png"):
        calibrate_images(str(blank / "*.png"))


def _bend_px(gray: np.ndarray) -> float | None:
    """Largest distance (px) of a 9x6 board's corners from the straight line fitted through their row
    or column; None when the board is not found."""
    from monostixels.data.calibration import find_board

    c = find_board(gray, (9, 6))
    if c is None:
        return None
    grid = c.reshape(6, 9, 2)
    worst = 0.0
    for line in [*grid, *grid.transpose(1, 0, 2)]:
        centred = line - line.mean(0)
        normal = np.linalg.svd(centred)[2][1]
        worst = max(worst, float(np.abs(centred @ normal).max()))
    return worst


@pytest.mark.skipif(not CAMERA_CAL.is_dir(), reason="shared dashcam chessboards (../shared/data/dashcam/camera_cal) not present")
def test_dashcam_calibration_straightens_the_boards_in_data_frames(tmp_path):
    """The whole chain on the dashcam views: calibrate, write the file, data=frames undistorts with it:
    the board's rows and columns come out straighter than through a pinhole with the same K."""
    from monostixels.build import build_source

    cal = calibrate_images(str(CAMERA_CAL / "*.jpg"), size=(1280, 720))
    lens = write_intrinsics_file(cal, tmp_path / "cam.yaml")
    pinhole = tmp_path / "pinhole.yaml"
    pinhole.write_text(f"fx: {cal.fx}\nfy: {cal.fy}\ncx: {cal.cx}\ncy: {cal.cy}\n")
    frames = tmp_path / "frames"
    frames.mkdir()
    for p in cal.boards:  # links, not copies, of the shared views
        (frames / p.name).symlink_to(p)
    bends = {}
    for name, intr in (("lens", lens), ("pinhole", pinhole)):
        src = build_source({"name": "frames", "root": str(frames), "intrinsics": str(intr)})
        bends[name] = [_bend_px((src[i].image.mean(0).numpy() * 255).round().astype(np.uint8)) for i in range(len(src))]
    both = [(a, b) for a, b in zip(bends["lens"], bends["pinhole"]) if a is not None and b is not None]
    assert len(both) >= 10
    lens_px, pin_px = np.array(both).T
    assert np.median(lens_px) < 0.85 * np.median(pin_px) and lens_px.max() < 0.5 * pin_px.max()
