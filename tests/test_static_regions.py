"""Static image regions (a bonnet in view): found from the frames, and left out of every stage."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.lens_standin import bonnet_mask
from monostixels._checks import InputError
from monostixels.data.synthetic import render_pair
from monostixels.data.static_regions import (STILL_WINDOW, apply_ignore_mask, find_static_region, spread_samples,
                                              still_pixels)

#: Rows of the painted bonnet at the bottom of a quarter-size render (94 rows), its top edge curved.
_BONNET_MIN, _BONNET_MAX = 10, 16


def _bonnet(H: int, W: int) -> np.ndarray:
    """(H, W) bool: a bonnet whose top edge rises towards the middle of the picture."""
    return bonnet_mask(H, W, _BONNET_MIN, _BONNET_MAX)


def _paint(img: torch.Tensor, mask: np.ndarray) -> torch.Tensor:
    """The image with a dark, reflective (textured, but fixed) bonnet over ``mask``."""
    H, W = mask.shape
    g = np.random.default_rng(5)
    paint = 0.15 + 0.35 * (g.random((H, W)) > 0.7)  # the same pattern in every frame: it does not move
    out = img.clone()
    m = torch.from_numpy(mask)
    out[:, m] = torch.from_numpy(paint[mask]).float()
    return out


def _clip(seed: int = 3):
    pair = render_pair(seed, scale=0.25)
    return pair, [pair.image_prev, pair.image, pair.image_prev, pair.image]


def _bgr(img: torch.Tensor) -> np.ndarray:
    return (img.permute(1, 2, 0).numpy()[..., ::-1] * 255).round().astype(np.uint8)


def _write_clip(path: Path, frames: list[np.ndarray], K: torch.Tensor) -> None:
    """An MJPG video of ``frames`` (BGR) at 5 fps, and its intrinsics ``K`` in ``intr.yaml`` beside it."""
    import cv2

    H, W = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 5.0, (W, H))
    for f in frames:
        writer.write(f)
    writer.release()
    (path.parent / "intr.yaml").write_text(f"fx: {float(K[0, 0])}\nfy: {float(K[1, 1])}\ncx: {float(K[0, 2])}\n"
                                           f"cy: {float(K[1, 2])}\n")


def test_a_bonnet_is_found_and_nothing_else():
    pair, frames = _clip()
    H, W = pair.size
    truth = _bonnet(H, W)
    found = find_static_region([_bgr(_paint(f, truth)) for f in frames])
    assert found.any()
    # The bonnet, to within a few rows at its curved edge (strips of 16 px; on average 3 rows too high at most).
    assert (found & truth).sum() >= 0.9 * truth.sum()
    assert (found & ~truth).sum() <= 3 * W
    assert not found[: H - _BONNET_MAX - 6].any()
    # The same clip without a bonnet: the road moves to the bottom edge, nothing is static.
    assert not find_static_region([_bgr(f) for f in frames]).any()
    # A standing camera (every frame the same): everything is static, which is no bonnet.
    still = _bgr(_paint(pair.image, truth))
    assert not find_static_region([still, still, still]).any()
    with pytest.raises(InputError, match="at least 3 frames"):
        find_static_region([still, still])


def test_a_bonnet_is_found_through_changing_exposure_and_shake():
    """The camera's exposure follows the scene and the camera shakes on its mount by a fraction of a pixel: a
    bonnet's grey values change from frame to frame, its pattern does not (the Kochi phone's dashboard)."""
    import cv2

    pair, frames = _clip()
    H, W = pair.size
    truth = _bonnet(H, W)
    # A real bonnet's pattern is smooth at the pixel scale (reflections, seams), unlike _paint's pixel noise.
    g = cv2.GaussianBlur(np.random.default_rng(5).random((H, W)).astype(np.float32), (0, 0), 2.5)
    pattern = 0.05 + 0.85 * (g - g.min()) / (g.max() - g.min())
    out = []
    for k, f in enumerate(frames):
        img = _bgr(f).astype(np.float32)
        img[truth] = 255.0 * pattern[truth][:, None]
        shift = np.float32([[1, 0, 0.2 * (-1) ** k], [0, 1, 0.1 * (-1) ** k]])  # shake, sub-pixel
        img = cv2.warpAffine(img, shift, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out.append(np.clip(img * (0.8 if k % 2 else 1.2), 0, 255).astype(np.uint8))  # exposure
    found = find_static_region(out)
    assert (found & truth).sum() >= 0.9 * truth.sum() and (found & ~truth).sum() <= 3 * W
    # The pixel test itself: a gain and an offset keep a pattern; a shift by its own size does not.
    g = np.random.default_rng(1).random((40, 40)).astype(np.float32)
    assert still_pixels(g, 0.7 * g + 0.1)[8:-8, 8:-8].all()
    assert still_pixels(g, np.roll(g, 7, axis=1))[8:-8, 8:-8].mean() < 0.05


def test_samples_are_runs_spread_over_the_whole_clip():
    runs = spread_samples(100, 4)
    assert runs[0][:2] == [0, 4] and runs[-1][-1] == 99 and len(runs) == 4
    assert all(len(r) == 4 and r[1] - r[0] == 4 for r in runs)
    assert all(a[-1] < b[0] for a, b in zip(runs[:-1], runs[1:]))  # no overlap
    assert spread_samples(3) == [[0, 1, 2]] and spread_samples(0) == []
    with pytest.raises(InputError, match="bad sampling"):
        spread_samples(10, 0)


def test_a_bonnet_is_found_where_the_camera_stands_at_first(tmp_path):
    """The camera stands for the first 12 frames (2.4 s) and drives later: data.mask=auto reads runs of frames
    spread over the clip, and finds the bonnet in the runs where the scene moves."""
    from monostixels.build import build_source
    from monostixels.pipeline import load_config

    pair, frames = _clip()
    H, W = pair.size
    truth = _bonnet(H, W)
    path = tmp_path / "standing_first.avi"
    _write_clip(path, [_bgr(_paint(f, truth)) for f in [frames[0]] * 12 + frames + frames], pair.camera.K)
    cfg = load_config(["data=video", f"data.path={path}", f"data.intrinsics={tmp_path / 'intr.yaml'}",
                       "data.resize=null", "data.mask=auto"])
    ignore = build_source(cfg.data)[0].meta["ignore_mask"].numpy()
    assert (ignore & truth).sum() >= 0.9 * truth.sum() and (ignore & ~truth).sum() <= 3 * W
    # The first frames alone, as data.mask=auto read them before: a standing camera, no region.
    still = [_bgr(_paint(frames[0], truth))] * 6
    assert not find_static_region(still).any()


def test_a_standing_camera_with_traffic_and_no_bonnet_has_no_static_region():
    """The camera stands through the clip while a car crosses the picture: the road below keeps as still as
    a bonnet would, but the scene above it hardly moves, so nothing is found."""
    pair, _ = _clip()
    H, W = pair.size
    base = _bgr(pair.image)
    car = np.random.default_rng(7).integers(0, 255, (H // 6, W // 5, 3), dtype=np.uint8)
    frames = []
    for k in range(12):
        f = base.copy()
        u = (k * W // 12) % (W - car.shape[1])
        f[H // 2 - car.shape[0]: H // 2, u:u + car.shape[1]] = car  # a car driving across, in the middle band
        frames.append(f)
    assert not find_static_region(frames, [4, 4, 4]).any()
    assert not find_static_region([base] * 12, [4, 4, 4]).any()
    with pytest.raises(InputError, match="do not split"):
        find_static_region(frames, [4, 4])


def test_an_ignore_mask_splits_into_cut_rows_and_pixels():
    H, W = 20, 30
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[16:] = True  # 4 whole rows at the bottom
    mask[12:16, :5] = True  # and a corner above them
    split = apply_ignore_mask(mask, (H, W))
    assert split.crop_rows == 16
    assert split.pixels is not None and tuple(split.pixels.shape) == (16, W) and int(split.pixels.sum()) == 20
    assert apply_ignore_mask(torch.zeros(H, W, dtype=torch.bool), (H, W)).crop_rows == H
    with pytest.raises(InputError, match=r"size \(20, 31\) differs"):
        apply_ignore_mask(torch.zeros(H, W + 1, dtype=torch.bool), (H, W))
    with pytest.raises(InputError, match="too little of the picture"):
        apply_ignore_mask(torch.ones(H, W, dtype=torch.bool), (H, W))


def test_the_pipeline_leaves_the_bonnet_out_and_keeps_the_frame_size():
    import dataclasses

    from monostixels.pipeline import Pipeline, load_config
    from monostixels.build import pipeline_settings

    pair, _ = _clip()
    H, W = pair.size
    bonnet = _bonnet(H, W)
    painted = dataclasses.replace(pair, image=_paint(pair.image, bonnet), image_prev=_paint(pair.image_prev, bonnet),
                                  meta=dict(pair.meta, ignore_mask=torch.from_numpy(bonnet)))
    cfg = load_config(["data.scale=0.25", "flow=dis", "semantic=gt", "motion=gt"])
    res = Pipeline(pipeline_settings(cfg), sfm=False).run(painted)
    st = res.stixels
    assert st.image_size == (H, W) and res.pair is painted
    assert int(st.v_bottom.max()) < H - _BONNET_MIN  # the rows that are bonnet all across: no stixel
    assert st.flags["ignored_pixels"] == int(bonnet.sum())
    assert tuple(res.flow.flow.shape) == (2, H, W) and tuple(res.flow.cov.shape) == (H, W, 2, 2)
    depth = st.depth_map()
    assert tuple(depth.shape) == (H, W)
    assert not bool((depth[H - _BONNET_MIN:] > 0).any())
    # Above the cut the frame is solved: the ground and objects are there.
    assert int((st.type == 0).sum()) > 0 and int((st.type == 1).sum()) > 0


def test_a_video_source_finds_the_bonnet_itself(tmp_path):
    """data=video with data.mask=auto (the default): the pairs carry the bonnet as their ignore mask."""
    from monostixels.build import build_source
    from monostixels.pipeline import load_config

    pair, frames = _clip()
    H, W = pair.size
    truth = _bonnet(H, W)
    path = tmp_path / "bonnet.avi"
    _write_clip(path, [_bgr(_paint(f, truth)) for f in frames + frames[:2]], pair.camera.K)
    common = ["data=video", f"data.path={path}", f"data.intrinsics={tmp_path / 'intr.yaml'}", "data.resize=null"]
    src = build_source(load_config(common).data)
    ignore = src[0].meta["ignore_mask"]
    assert (ignore.numpy() & truth).sum() >= 0.9 * truth.sum() and (ignore.numpy() & ~truth).sum() <= 3 * W
    assert "ignore_mask" not in build_source(load_config(common + ["data.mask=null"]).data)[0].meta


_SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.mark.skipif(not _SHARED.is_dir(), reason=f"the shared real samples are not at {_SHARED}")
@pytest.mark.parametrize("pattern", ["kitti_raw/2011_09_30/2011_09_30_drive_0028_sync/image_02/data/*.jpg",
                                     "ddad_dgp/scene_01/rgb/CAMERA_01/*.jpg"])  # driving; standing still
def test_real_frames_without_a_bonnet_have_no_static_region(pattern):
    import cv2

    frames = [cv2.imread(str(p)) for p in sorted(_SHARED.glob(pattern))[:6]]
    assert len(frames) >= 3
    assert not find_static_region(frames).any()


@pytest.mark.skipif(not (_SHARED / "dashcam").is_dir(), reason=f"the shared dashcam clip is not at {_SHARED}")
def test_a_smooth_bonnet_reflecting_the_sky_is_found_on_a_real_highway_clip():
    # A real bonnet is smooth and dark and mirrors the scene above: texture only at its edge, and a
    # reflection that changes from frame to frame. Pasted on the shared highway clip, frames 0.2 s apart.
    import cv2

    cap = cv2.VideoCapture(str(_SHARED / "dashcam" / "highway_solid_white_right.mp4"))
    frames = []
    for k in range(26):
        ok, f = cap.read()
        assert ok
        if k % 5 == 0:
            frames.append(f)
    H, W = frames[0].shape[:2]
    u = np.arange(W)
    edge = (0.9 * H + 0.06 * H * ((u - W / 2) / (W / 2)) ** 2).astype(int)
    truth = np.arange(H)[:, None] >= edge[None, :]
    painted = []
    for f in frames:
        sky = cv2.GaussianBlur(cv2.resize(np.ascontiguousarray(f[: H // 3][::-1]), (W, H)), (0, 0), 5)
        bonnet = np.clip(35.0 + 0.25 * sky.astype(np.float32), 0, 255)
        out = np.where(truth[..., None], bonnet, f.astype(np.float32))
        out[np.clip(edge, 0, H - 1), u] = 110.0  # the lip of the bonnet catches the light
        painted.append(out.astype(np.uint8))
    found = find_static_region(painted)
    assert (found & truth).sum() >= 0.9 * truth.sum()
    # Above its edge, at most the rows without texture a strip may bridge (GAP_SHARE of the height); where
    # the reflection of trees moves, a strip says nothing, and the rest still makes a bonnet.
    rows = np.arange(H)[:, None]
    assert not (found & (rows < edge[None, :] - 0.06 * H)).any()
    assert not find_static_region(frames).any()  # the clip as filmed has none


def test_run_on_a_bonnet_clip_keeps_the_frame_size_and_reads_ahead(tmp_path):
    """A video with a bonnet through the sequence layer with the stream reading ahead (preset=fast): every
    pair is solved at the cropped size, its inputs computed ahead are used, the outputs have the frame's size."""
    from monostixels.build import build_source
    from monostixels.pipeline import load_config
    from monostixels.sequence import SequenceRunner
    from monostixels.build import sequence_settings

    pair, frames = _clip()
    H, W = pair.size
    truth = _bonnet(H, W)
    path = tmp_path / "bonnet.avi"
    _write_clip(path, [_bgr(_paint(f, truth)) for f in frames + frames], pair.camera.K)
    cfg = load_config(["data=video", f"data.path={path}", f"data.intrinsics={tmp_path / 'intr.yaml'}",
                       "data.resize=null", "preset=fast", "semantic=none", "keyframes.min_distance_m=0"])
    runner = SequenceRunner(sequence_settings(cfg))
    source = build_source(cfg.data)
    found = source[0].meta["ignore_mask"].numpy()
    # The bonnet, and at most the rows its pattern's window reaches above its edge (STILL_WINDOW // 2).
    assert (found & truth).sum() >= 0.9 * truth.sum() and (found & ~truth).sum() <= (STILL_WINDOW // 2) * W
    steps = list(runner.run(source))
    assert len(steps) == 7
    for s in steps:
        st = s.result.stixels
        assert s.pair.size == (H, W) and st.image_size == (H, W) and st.flags["ignored_pixels"] == int(found.sum())
        assert int(st.v_bottom.max()) < H - _BONNET_MIN
    assert runner.stream.ahead >= 4  # the pairs read ahead were the ones solved
