"""The `video` data source: frame selection, intrinsics from a file or a field of view, resize, bad input."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from monostixels._checks import InputError
from monostixels.build import build_source
from monostixels.data._lens import working_size
from monostixels.data.video import VideoSource, intrinsics_from_hfov

H, W = 48, 80


def write_video(path: Path, n: int, size: tuple[int, int] = (H, W), fps: float = 10.0) -> Path:
    """An mp4 of ``n`` frames; frame ``k`` is uniformly grey at ``20 + 20 k`` (readable back despite the codec)."""
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (size[1], size[0]))
    assert vw.isOpened(), "OpenCV has no mp4v encoder"
    for k in range(n):
        vw.write(np.full((size[0], size[1], 3), 20 + 20 * k, np.uint8))
    vw.release()
    return path


def _grey(img) -> float:
    return float(img.mean()) * 255


def test_frame_selection_order_and_interval(tmp_path):
    v = write_video(tmp_path / "c.mp4", 9)
    src = VideoSource(v, hfov_deg=90.0, step=2, start=1, end=8)
    # Used frames 1, 3, 5, 7 -> pairs (3 <- 1), (5 <- 3), (7 <- 5).
    assert len(src) == 3
    for k, p in enumerate(src):
        cur, prev = 3 + 2 * k, 1 + 2 * k
        assert (p.meta["frame"], p.meta["frame_prev"]) == (cur, prev)
        assert _grey(p.image) == pytest.approx(20 + 20 * cur, abs=3)
        assert _grey(p.image_prev) == pytest.approx(20 + 20 * prev, abs=3)
        assert p.meta["dt"] == pytest.approx(0.2)  # step 2 at 10 fps
    # Random access (a backwards seek) gives the same frames.
    assert _grey(src[0].image) == pytest.approx(80, abs=3)
    assert len(VideoSource(v, hfov_deg=90.0, frames=2)) == 2


def test_intrinsics_from_hfov_file_and_resize(tmp_path):
    fx, fy, cx, cy = intrinsics_from_hfov(80, 48, 90.0)
    assert fx == pytest.approx(40.0) and fy == fx and (cx, cy) == (39.5, 23.5)
    v = write_video(tmp_path / "c.mp4", 3)
    K = VideoSource(v, hfov_deg=60.0).camera.K
    assert float(K[0, 0]) == pytest.approx(40.0 / math.tan(math.radians(30.0)))
    (tmp_path / "k.yaml").write_text("fx: 70\nfy: 66\ncx: 41\ncy: 22\n")
    src = VideoSource(v, intrinsics=tmp_path / "k.yaml", resize=0.5, hfov_deg=60.0)  # the file wins
    p = src[0]
    assert p.size == (24, 40)
    K = p.camera.K
    # Half size: focal lengths halve, pixel centres map as u' + 0.5 = (u + 0.5) / 2.
    assert [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])] == pytest.approx([35, 33, 20.25, 10.75])
    assert VideoSource(v, hfov_deg=60.0, resize=[40, 30])[0].size == (30, 40)


@pytest.mark.parametrize("case", ["missing", "unreadable", "one_frame", "no_intrinsics", "range", "bad_hfov"])
def test_bad_input_fails_clearly(tmp_path, case):
    v = write_video(tmp_path / "c.mp4", 1 if case == "one_frame" else 3)
    kw: dict = {"hfov_deg": 90.0}
    if case == "missing":
        v = tmp_path / "nope.mp4"
    if case == "unreadable":
        v = tmp_path / "junk.mp4"
        v.write_bytes(b"this is not a video" * 100)
    if case == "no_intrinsics":
        kw = {}
    if case == "range":
        kw["start"] = 2
    if case == "bad_hfov":
        kw["hfov_deg"] = 180.0
    want = {"missing": "nope.mp4 does not exist", "unreadable": "cannot decode", "one_frame": "at least two",
            "no_intrinsics": "data.hfov_deg", "range": "at least two", "bad_hfov": "field of view"}[case]
    with pytest.raises(InputError, match=want):
        VideoSource(v, **kw)


def test_make_source_video(tmp_path):
    v = write_video(tmp_path / "c.mp4", 4)
    src = build_source({"name": "video", "path": str(v), "hfov_deg": 90, "step": 1, "resize": [40, 24]})
    assert len(src) == 3 and src[0].size == (24, 40)
    with pytest.raises(InputError, match="no video file given"):
        build_source({"name": "video", "hfov_deg": 90})


# ------------------------------------------------------------------------------------------------
# Lens distortion, data.mask, data.resize=auto
# ------------------------------------------------------------------------------------------------
#: A barrel-distorted lens (fx != fy, off-centre principal point) for 480 x 640 frames.
K_LENS = np.array([[420.0, 0.0, 331.0], [0.0, 414.0, 236.0], [0.0, 0.0, 1.0]])
D_LENS = np.array([-0.28, 0.07, 0.0008, -0.0006, 0.0])
LENS_SIZE = (480, 640)


@pytest.fixture(scope="module")
def board_clip(tmp_path_factory):
    """A 2-frame video of one chessboard view through the lens, its intrinsics file and the board pose."""
    from tests._boards import board_poses, pixel_rays, render_board

    d = tmp_path_factory.mktemp("lens")
    # A large board in the middle (the last pose): its outer corners lie where the barrel bends visibly.
    R, t = board_poses(3, (9, 6), K_LENS, LENS_SIZE, seed=0, fill=0.6)[2]
    view = render_board(pixel_rays(K_LENS, D_LENS, LENS_SIZE), LENS_SIZE, R, t, (9, 6))
    bgr = cv2.cvtColor(view, cv2.COLOR_GRAY2BGR)
    path = d / "board.mp4"
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (LENS_SIZE[1], LENS_SIZE[0]))
    for _ in range(2):
        vw.write(bgr)
    vw.release()
    fx, fy, cx, cy = K_LENS[0, 0], K_LENS[1, 1], K_LENS[0, 2], K_LENS[1, 2]
    intr = d / "lens.yaml"
    intr.write_text(f"fx: {fx}\nfy: {fy}\ncx: {cx}\ncy: {cy}\ndistortion: [{', '.join(str(v) for v in D_LENS)}]\n")
    pinhole = d / "pinhole.yaml"
    pinhole.write_text(f"fx: {fx}\nfy: {fy}\ncx: {cx}\ncy: {cy}\n")
    return path, intr, pinhole, R, t


def _corner_error(src, R, t) -> float:
    """Largest distance (px) between the board corners found in the source's first frame and the corners
    projected through a pinhole with the source's own camera matrix (no distortion)."""
    from monostixels.data.calibration import find_board

    p = src[0]
    grey = (p.image.mean(0).numpy() * 255).round().astype(np.uint8)
    found = find_board(grey, (9, 6))
    assert found is not None
    grid = np.zeros((54, 3))
    grid[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2)
    want = cv2.projectPoints(grid, cv2.Rodrigues(R)[0], t, p.camera.K.double().numpy(), None)[0].reshape(-1, 2)
    # The detector may number the corners from either end of the board.
    return float(min(np.linalg.norm(found - want, axis=1).max(), np.linalg.norm(found[::-1] - want, axis=1).max()))


@pytest.mark.parametrize("resize", [None, 0.75])
def test_undistorted_frames_are_pinhole_images_of_their_camera(board_clip, resize):
    """With distortion in the intrinsics file the frames the pipeline sees obey a pinhole camera with
    ``pair.camera.K`` (straight lines straight), also after a resize; without it they do not."""
    path, intr, pinhole, R, t = board_clip
    src = VideoSource(path, intrinsics=intr, resize=resize)
    if resize is not None:
        assert src[0].size == (360, 480)
    # The camera matrix is kept (scaled with the resize): the file's numbers are the undistorted image's.
    s = 1.0 if resize is None else resize
    K = src.camera.K.double().numpy()
    assert [K[0, 0], K[1, 1], K[0, 2], K[1, 2]] == pytest.approx(
        [K_LENS[0, 0] * s, K_LENS[1, 1] * s, (K_LENS[0, 2] + 0.5) * s - 0.5, (K_LENS[1, 2] + 0.5) * s - 0.5])
    assert _corner_error(src, R, t) < 1.0
    assert _corner_error(VideoSource(path, intrinsics=pinhole, resize=resize), R, t) > 4.0 * s
    # A barrel lens with the camera matrix kept: every pixel has a source, so nothing to ignore.
    assert "ignore_mask" not in src[0].meta


def test_live_source_undistorts_like_the_file_source(board_clip):
    from monostixels.data.live_video import LiveVideoSource

    path, intr, _, _, _ = board_clip
    live = LiveVideoSource(path, intrinsics=intr, resize=0.5)
    offline = VideoSource(path, intrinsics=intr, resize=0.5)
    (i,) = list(live.indices())
    assert torch.equal(live[i].image, offline[i].image)
    assert torch.equal(live.camera.K, offline.camera.K)


def test_mask_is_carried_warped_with_the_frames(tmp_path):
    """data.mask: read once, undistorted and resized with the frames (nearest neighbour), in every pair's
    meta["ignore_mask"] at the working size."""
    Hs, Ws = 120, 160
    mask = np.zeros((Hs, Ws), np.uint8)
    mask[90:, :] = 255          # a bonnet
    mask[10:30, 120:150] = 1    # a logo; any non-zero value counts
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    # Frames that show the mask itself: warped alike, the frame's bright pixels are the ignored ones.
    vw = cv2.VideoWriter(str(tmp_path / "m.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (Ws, Hs))
    for _ in range(3):
        vw.write(cv2.cvtColor(np.where(mask > 0, 255, 0).astype(np.uint8), cv2.COLOR_GRAY2BGR))
    vw.release()
    (tmp_path / "k.yaml").write_text("fx: 100\nfy: 98\ncx: 83\ncy: 57\ndistortion: [-0.3, 0.08, 0, 0, 0]\n")
    src = build_source({"name": "video", "path": str(tmp_path / "m.mp4"), "intrinsics": str(tmp_path / "k.yaml"),
                       "resize": 0.5, "mask": str(tmp_path / "mask.png")})
    for p in src:
        ignore = p.meta["ignore_mask"]
        assert ignore.dtype == torch.bool and tuple(ignore.shape) == p.size == (60, 80)
        bright = p.image.mean(0) > 0.5
        assert float((bright == ignore).float().mean()) > 0.97
    # Each pair has its own copy (a consumer may change it).
    a, b = src[0].meta["ignore_mask"], src[1].meta["ignore_mask"]
    assert torch.equal(a, b) and a.data_ptr() != b.data_ptr()
    # No distortion, no resize: exactly the mask.
    plain = VideoSource(tmp_path / "m.mp4", hfov_deg=90.0, mask=tmp_path / "mask.png")
    assert torch.equal(plain[0].meta["ignore_mask"], torch.from_numpy(mask > 0))
    # Resized only: nearest neighbour.
    half = VideoSource(tmp_path / "m.mp4", hfov_deg=90.0, mask=tmp_path / "mask.png", resize=[80, 60])
    want = cv2.resize(mask, (80, 60), interpolation=cv2.INTER_NEAREST) > 0
    assert torch.equal(half[0].meta["ignore_mask"], torch.from_numpy(want))
    assert "ignore_mask" not in VideoSource(tmp_path / "m.mp4", hfov_deg=90.0)[0].meta


def test_pincushion_pixels_without_a_source_are_ignored(tmp_path):
    v = write_video(tmp_path / "c.mp4", 2)
    (tmp_path / "k.yaml").write_text(f"fx: 40\nfy: 40\ncx: {(W - 1) / 2}\ncy: {(H - 1) / 2}\ndistortion: [0.4, 0, 0, 0, 0]\n")
    p = VideoSource(v, intrinsics=tmp_path / "k.yaml")[0]
    ignore = p.meta["ignore_mask"]
    # Pincushion with the camera matrix kept: the image corners have no source, the centre has.
    assert bool(ignore[0, 0]) and bool(ignore[-1, -1]) and not bool(ignore[H // 2, W // 2])
    # There the frame is black (at the edge of the ignored rim a blend with black).
    assert float(p.image[:, 0, 0].max()) == 0.0 and float(p.image[:, ~ignore].min()) > 0.05
    assert float(p.image[:, ignore].mean()) < 0.5 * float(p.image[:, ~ignore].mean())


@pytest.mark.parametrize("size,want", [((540, 960), (540, 960)), ((720, 1280), (530, 942)), ((48, 80), (48, 80))])
def test_resize_auto_sizes(size, want):
    assert working_size("auto", size[1], size[0]) == want


def test_resize_auto_is_about_half_a_megapixel_never_upscaled():
    from monostixels.data.video import AUTO_PIXELS

    for W_, H_ in ((1920, 1080), (1280, 720), (1280, 960), (2560, 1440), (1000, 1000)):
        h, w = working_size("auto", W_, H_)
        assert h % 2 == 0 and w % 2 == 0
        assert abs(h * w / AUTO_PIXELS - 1) < 0.01 and abs(w / h - W_ / H_) < 0.01
    for W_, H_ in ((640, 480), (960, 540), (10, 10)):
        assert working_size("auto", W_, H_) == (H_, W_)


def test_resize_auto_is_the_video_default_and_bad_values_fail(tmp_path):
    from monostixels.pipeline import load_config

    conf = load_config(["data=video"]).data
    assert conf.resize == "auto" and conf.mask == "auto"  # the bonnet found from the first frames
    v = write_video(tmp_path / "c.mp4", 3)
    src = build_source({"name": "video", "path": str(v), "hfov_deg": 90, "resize": "auto"})
    assert src[0].size == (H, W)  # small frames stay as they are
    for bad in ("big", [1, 2, 3], -1):
        with pytest.raises(InputError, match="data.resize"):
            build_source({"name": "video", "path": str(v), "hfov_deg": 90, "resize": bad})


@pytest.mark.parametrize("case", ["mask_size", "mask_missing", "mask_all", "distortion_length", "intrinsics_size"])
def test_lens_and_mask_bad_input_fails_clearly(tmp_path, case):
    v = write_video(tmp_path / "c.mp4", 3)
    kw: dict = {"hfov_deg": 90.0}
    if case == "mask_size":
        cv2.imwrite(str(tmp_path / "mask.png"), np.zeros((30, 40), np.uint8))
        kw["mask"] = tmp_path / "mask.png"
    if case == "mask_missing":
        kw["mask"] = tmp_path / "nomask.png"
    if case == "mask_all":
        cv2.imwrite(str(tmp_path / "mask.png"), np.full((H, W), 255, np.uint8))
        kw["mask"] = tmp_path / "mask.png"
    if case == "distortion_length":
        (tmp_path / "k.yaml").write_text("fx: 40\nfy: 40\ncx: 40\ncy: 24\ndistortion: [-0.2, 0.01, 0]\n")
        kw = {"intrinsics": tmp_path / "k.yaml"}
    if case == "intrinsics_size":  # a calibration of a 1280x720 mode for 80x48 frames
        (tmp_path / "k.yaml").write_text("fx: 900\nfy: 900\ncx: 640\ncy: 360\nwidth: 1280\nheight: 720\n")
        kw = {"intrinsics": tmp_path / "k.yaml"}
    want = {"mask_size": rf"data.mask: .*mask\.png is 40x30 pixels, the frames are {W}x{H}",
            "mask_missing": r"data.mask: file .*nomask\.png does not exist",
            "mask_all": r"mask\.png ignores every pixel",
            "distortion_length": r"intrinsics: .*k\.yaml key distortion holds 3 numbers",
            "intrinsics_size": rf"intrinsics: .*k\.yaml holds for 1280x720 images .*the video's frames are {W}x{H}"}[case]
    with pytest.raises(InputError, match=want) as err:
        VideoSource(v, **kw)
    assert "\n" not in str(err.value)
