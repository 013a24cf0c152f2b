"""`monostixels run ... output.rerun=true`: the .rrd read back with rerun's own API, frame by frame."""
from __future__ import annotations

import json
import math
import os
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from tests._clips import FAST, FPS, cli, hide_module, write_video_clip

rr = pytest.importorskip("rerun", reason='the viewer extra (pip install -e ".[viewer]")')


def _read_rrd(path: Path) -> tuple[dict[str, dict[str, dict[int, object]]], dict[str, dict[str, object]]]:
    """``{entity: {component: {frame: value}}}`` of the temporal data, and the static data."""
    from rerun.chunk import RrdReader

    temporal: dict = defaultdict(lambda: defaultdict(dict))
    static: dict = defaultdict(dict)
    for chunk in RrdReader(path).stream():
        rb = chunk.to_record_batch()
        comps = [n for n in rb.schema.names if ":" in n]
        if chunk.is_static:
            for n in comps:
                static[chunk.entity_path][n] = rb.column(n).to_pylist()[-1]
            continue
        frames = rb.column("frame").to_pylist()
        times = rb.column("time").to_pylist() if "time" in rb.schema.names else [None] * len(frames)
        for n in comps:
            for f, t, v in zip(frames, times, rb.column(n).to_pylist()):
                temporal[chunk.entity_path][n][f] = v
                temporal[chunk.entity_path]["time"][f] = t
    return temporal, static


def test_run_writes_a_rerun_recording(tmp_path):
    intr = write_video_clip(tmp_path / "clip.mp4")
    p = cli(["run", "data=video", f"data.path={tmp_path / 'clip.mp4'}", f"data.intrinsics={intr}", *FAST,
             "output.rerun=true"], tmp_path)
    out = tmp_path / "outputs" / "run"
    rrd = out / "recording.rrd"
    assert rrd.is_file() and f"rerun {rrd.relative_to(tmp_path)}" in p.stdout
    frame_dirs = sorted(d for d in out.iterdir() if d.is_dir())
    assert len(frame_dirs) == 3
    data, static = _read_rrd(rrd)
    movers = 0
    # World = first camera, declared as x right, y down, z forward.
    assert static["/world"]["ViewCoordinates:xyz"][0] == list(rr.ViewCoordinates.RDF.as_arrow_array().to_pylist()[0])
    for i, d in enumerate(frame_dirs):
        st = json.loads((d / "stixels.json").read_text())
        H, W = st["image_size"]
        K = np.array(st["K"])
        # The camera: pinhole of the JSON's K and image size, posed in the world.
        assert np.allclose(np.array(data["/world/camera/image"]["Pinhole:image_from_camera"][i][0]).reshape(3, 3).T,
                           K, atol=1e-4)
        assert data["/world/camera/image"]["Pinhole:resolution"][i][0] == [W, H]
        R = np.array(data["/world/camera"]["Transform3D:mat3x3"][i][0]).reshape(3, 3).T  # column-major
        t = np.array(data["/world/camera"]["Transform3D:translation"][i][0])
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-5)
        # Image (JPEG), depth (H x W) and point cloud.
        assert len(data["/world/camera/image/rgb"]["EncodedImage:blob"][i][0]) > 100
        assert data["/world/camera/image/depth"]["DepthImage:format"][i][0]["width"] == W
        assert len(data["/world/camera/points"]["Points3D:positions"][i]) > 0
        # The video's time: frame k of a 10 fps clip (pair i's current frame is video frame i + 1).
        assert data["/world/stixels"]["time"][i].total_seconds() == pytest.approx((i + 1) / FPS)
        # One box per object stixel of the frame's JSON, in JSON order: each box's front face (the
        # centre less half its depth extent along the box's axis) is at the stixel's depth.
        objects = [s for s in st["stixels"] if s["type"] in ("static_object", "dynamic_object")]
        centres = np.array(data["/world/stixels"]["Boxes3D:centers"][i]).reshape(-1, 3)
        assert len(centres) == len(objects) > 0
        quats = np.array(data["/world/stixels"]["Boxes3D:quaternions"][i]).reshape(-1, 4)
        half = np.array(data["/world/stixels"]["Boxes3D:half_sizes"][i]).reshape(-1, 3)
        from scipy.spatial.transform import Rotation

        axes_cam = R.T @ Rotation.from_quat(quats).as_matrix()  # box axes in the camera frame
        front = (centres - t) @ R - axes_cam[:, :, 2] * half[:, 2:3]
        depth = np.array([s["depth"] for s in objects])
        assert np.allclose(front[:, 2], depth, rtol=0.02)
        # Movers: an arrow per dynamic stixel that moves.
        dyn = [s for s in objects if s["type"] == "dynamic_object" and any(s["motion"])]
        assert len(data["/world/movers"]["Arrows3D:vectors"].get(i) or []) == len(dyn)
        movers += len(dyn)
    assert movers > 0
    # The docs' example of reading the recording back gives the same boxes per frame.
    from tests.test_batch import doc_python_blocks

    (block,) = doc_python_blocks("RrdReader")
    ns: dict = {}
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        exec(compile(block, "docs/batch_and_viewer.md", "exec"), ns)  # noqa: S102 — our own documentation's code
    finally:
        os.chdir(cwd)
    assert ns["boxes_per_frame"] == {i: len(data["/world/stixels"]["Boxes3D:centers"][i]) for i in range(3)}
    # The camera went forward, back, forward: frames 0 and 2 are at the same place, frame 1 near the start.
    t = [np.array(data["/world/camera"]["Transform3D:translation"][i][0]) for i in range(3)]
    assert np.linalg.norm(t[0]) > 0.3 and np.linalg.norm(t[1]) < 0.3 * np.linalg.norm(t[0])


def test_rerun_missing_names_the_extra(monkeypatch):
    """Without rerun-sdk, output.rerun=true fails at once with the install command of the extra."""
    from monostixels._checks import InputError
    from monostixels.output.viewer import require_rerun

    hide_module(monkeypatch, "rerun")
    with pytest.raises(InputError, match=r'pip install -e "\.\[viewer\]"'):
        require_rerun()


def test_sequence_fields_reach_the_recording_and_the_rows(tmp_path):
    """Where the sequence layer adds track ids, velocities, TTCs and a pose, the boxes carry the labels,
    the arrows the velocities, and the dataset rows all three, at the pose's world positions."""
    from types import SimpleNamespace

    import torch

    from monostixels.batch import frame_rows
    from monostixels.core.classes import DYNAMIC_OBJECT, STATIC_OBJECT
    from monostixels.core.geometry import Camera
    from monostixels.data.base import FrameInfo
    from monostixels.output.scene3d import reference_points
    from monostixels.output.viewer import RerunRecorder
    from tests.test_scene3d import _world

    st = _world()
    n = len(st)
    st.track_id = torch.arange(n) + 10
    st.velocity = torch.zeros(n, 3, dtype=torch.float64)
    dyn = st.type == DYNAMIC_OBJECT
    st.velocity[dyn] = torch.tensor([1.0, 0.0, -7.0], dtype=torch.float64)
    st.ttc_s = torch.full((n,), float("inf"), dtype=torch.float64)
    st.ttc_s[dyn] = 2.5
    pose = np.eye(4)
    pose[:3, 3] = [2.0, 0.0, 30.0]
    H, W = st.image_size
    pair = SimpleNamespace(image=torch.rand(3, H, W), camera=Camera(K=st.K), name="seq_000007",
                           meta={"source": "video", "frame": 7, "dt": 0.1}, size=(H, W))
    pair.info = FrameInfo.of(pair.meta)
    res = SimpleNamespace(stixels=st, pose=pose, motion=SimpleNamespace(motion=None))

    rows = frame_rows(0, pair, res, pose, fps=10.0)
    assert rows["track_id"] == list(range(10, 10 + n))
    assert rows["ttc_s"][int(np.nonzero(dyn.numpy())[0][0])] == 2.5 and math.isinf(rows["ttc_s"][0])
    assert rows["velocity_z"][int(np.nonzero(dyn.numpy())[0][0])] == -7.0
    assert rows["timestamp"][0] == pytest.approx(0.7)
    X = reference_points(st)
    ok = ~np.isnan(X[:, 0])
    assert np.allclose(np.array(rows["z"], dtype=float)[ok], X[ok, 2] + 30.0)

    rec = RerunRecorder(tmp_path / "seq.rrd", fps=10.0)
    rec.log_frame(0, pair, res)
    rec.close()
    data, _ = _read_rrd(tmp_path / "seq.rrd")
    assert np.allclose(data["/world/camera"]["Transform3D:translation"][0][0], [2.0, 0.0, 30.0])
    objects = np.nonzero(np.isin(st.type.numpy(), (STATIC_OBJECT, DYNAMIC_OBJECT)))[0]
    labels = data["/world/stixels"]["Boxes3D:labels"][0]
    assert labels == [f"#{10 + i}" + (" TTC 2.5 s" if st.type[i] == DYNAMIC_OBJECT else "") for i in objects]
    vectors = np.array(data["/world/movers"]["Arrows3D:vectors"][0])
    assert vectors.shape == (int(dyn.sum()), 3) and np.allclose(vectors, [1.0, 0.0, -7.0])
