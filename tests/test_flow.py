"""Flow backends, the flow covariance and the flow metrics (monostixels.inputs.flow / confidence / raft)."""
from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from monostixels._checks import InputError
from monostixels._cpu import int8_path
from monostixels.data.base import FramePair, GroundTruth
from monostixels.core.geometry import Camera, intrinsics
from monostixels.inputs.confidence import ConfidenceParams, fb_consistency_error, flow_covariance
from monostixels.inputs.flow import estimate_flow, flow_metrics
from monostixels.inputs.quantize import can_saturate
from monostixels.inputs.raft import OnnxRaft, RaftFlow, TorchRaft, build_raft, export_onnx, load_raft_weights, padded_size

REPO = Path(__file__).resolve().parents[1]


def _camera(H: int, W: int) -> Camera:
    return Camera(K=intrinsics(0.9 * W, 0.85 * W, 0.47 * W, 0.52 * H))


def _texture(H: int, W: int, seed: int = 0) -> torch.Tensor:
    """Smooth random texture (3, H, W) in [0, 1] (sum of blurred noise octaves)."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((H, W), np.float32)
    for k, amp in ((3, 0.5), (7, 0.3), (15, 0.2)):
        img += amp * cv2.GaussianBlur(rng.random((H, W)).astype(np.float32), (0, 0), k / 3.0)
    img = (img - img.min()) / (img.max() - img.min())
    return torch.from_numpy(img)[None].repeat(3, 1, 1)


# --- covariance ---------------------------------------------------------------------------------


def test_structure_tensor_covariance_edge_and_textureless():
    H, W = 48, 64
    img = torch.zeros(3, H, W)
    img[:, :, 32:] = 1.0  # vertical edge at u = 31.5
    p = ConfidenceParams(method="structure_tensor", noise=0.01, window_sigma=2.0, sigma_min=0.1, sigma_max=20.0)
    cov = flow_covariance(img, p)
    on_edge = cov[24, 31]
    # Along the edge (v direction) the flow is unknown: the ceiling; across it (u) it is well known.
    assert on_edge[1, 1] == pytest.approx(p.sigma_max**2, rel=1e-3)
    assert float(on_edge[0, 0]) < 0.05 * p.sigma_max**2
    assert abs(float(on_edge[0, 1])) < 1e-4
    # Textureless: ceiling in every direction.
    flat = cov[24, 5]
    assert torch.allclose(flat, torch.eye(2) * p.sigma_max**2, rtol=1e-3)
    # Positive definite everywhere, eigenvalues within [sigma_min^2, sigma_max^2].
    ev = torch.linalg.eigvalsh(cov.double())
    assert float(ev.min()) >= p.sigma_min**2 * (1 - 1e-4)
    assert float(ev.max()) <= p.sigma_max**2 * (1 + 1e-4)


def test_structure_tensor_covariance_matches_forstner_formula():
    # A linear ramp I = g u has J = diag(g^2, 0) exactly (away from the border): C_uu = noise^2 / (N g^2).
    H, W = 40, 80
    g = 0.01  # intensity per pixel
    u = torch.arange(W, dtype=torch.float32)
    img = (g * u)[None, None].expand(3, H, W).clone()
    p = ConfidenceParams(method="structure_tensor", noise=0.02, window_sigma=1.5, sigma_min=0.01, sigma_max=50.0)
    cov = flow_covariance(img, p)
    n_eff = 4 * math.pi * p.window_sigma**2
    info = n_eff * g**2 / p.noise**2 + 1.0 / p.sigma_max**2
    assert float(cov[20, 40, 0, 0]) == pytest.approx(1.0 / info, rel=1e-3)
    assert float(cov[20, 40, 1, 1]) == pytest.approx(p.sigma_max**2, rel=1e-3)


def test_constant_covariance_and_fb_inflation():
    H, W = 20, 30
    img = _texture(H, W)
    p = ConfidenceParams(method="constant", sigma=0.7, sigma_min=0.1, sigma_max=10.0, fb_weight=2.0)
    cov = flow_covariance(img, p)
    assert torch.allclose(cov, 0.49 * torch.eye(2).expand(H, W, 2, 2))
    err = torch.zeros(H, W)
    err[3, 4] = 1.5
    err[5, 6] = float("inf")
    cov = flow_covariance(img, p, fb_error=err)
    assert float(cov[3, 4, 0, 0]) == pytest.approx(0.49 + (2.0 * 1.5) ** 2, rel=1e-5)
    assert float(cov[5, 6, 1, 1]) == pytest.approx(p.sigma_max**2, rel=1e-5)
    assert float(cov[0, 0, 0, 0]) == pytest.approx(0.49, rel=1e-5)


def test_fb_consistency_error():
    H, W = 24, 32
    fwd = torch.zeros(2, H, W)
    fwd[0], fwd[1] = -2.0, 1.0
    back = -fwd.clone()
    err = fb_consistency_error(fwd, back)
    assert float(err[5:15, 5:25].abs().max()) < 1e-5
    # Leaving the image: unchecked (inf) at the left border where u - 2 < 0.
    assert bool(torch.isinf(err[10, 0]))
    err_bad = fb_consistency_error(fwd, torch.zeros(2, H, W))
    assert float(err_bad[10, 10]) == pytest.approx(math.hypot(2.0, 1.0), rel=1e-5)


# --- backends -------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["deepflow", "dis"])
def test_opencv_backends_direction(name):
    # cur(x) = prev(x - d): the pixel x of the current image is at x - d in the previous one.
    H, W = 96, 128
    big = _texture(H + 20, W + 20, seed=1)
    d = (3, 2)  # (du, dv) pixels
    prev = big[:, 10:10 + H, 10:10 + W]
    cur = big[:, 10 - d[1]:10 - d[1] + H, 10 - d[0]:10 - d[0] + W]
    pair = FramePair(image=cur.contiguous(), image_prev=prev.contiguous(), camera=_camera(H, W), name="shift")
    cfg = OmegaConf.create({"name": name, "confidence": "structure_tensor"})
    res = estimate_flow(pair, cfg)
    assert res.flow.shape == (2, H, W) and res.cov.shape == (H, W, 2, 2)
    inner = res.flow[:, 15:-15, 15:-15]
    assert float(inner[0].median()) == pytest.approx(-d[0], abs=0.25)
    assert float(inner[1].median()) == pytest.approx(-d[1], abs=0.25)
    assert res.backend == name and res.seconds > 0
    assert float(torch.linalg.eigvalsh(res.cov.double()).min()) > 0


def test_deepflow_follows_large_displacements_with_matches():
    # A synthetic street scene at half size: the near road moves 10-30 px. OpenCV's DeepFlow alone
    # (no matching term) loses it; guided by dense matches it must beat both itself and DIS.
    from monostixels.data.synthetic import render_pair

    pair = render_pair(9, scale=0.5)
    epe = {}
    for name, matches in (("deepflow", "none"), ("deepflow", "dis"), ("dis", None)):
        raw = {"confidence": "structure_tensor", "refine": False, "fb_consistency": False}  # the backend alone
        cfg = OmegaConf.create({"name": name, **raw, **({"matches": matches} if matches else {})})
        res = estimate_flow(pair, cfg)
        epe[(name, matches)] = flow_metrics(res.flow, pair.gt.flow, pair.gt.flow_valid)["epe"]
    assert epe[("deepflow", "none")] > 5.0
    assert epe[("deepflow", "dis")] < 2.0
    assert epe[("deepflow", "dis")] < epe[("dis", None)]
    with pytest.raises(InputError, match="flow.matches"):
        estimate_flow(pair, OmegaConf.create({"name": "deepflow", "matches": "sift"}))


def test_refinement_passes_converge_towards_the_ground_truth():
    # One variational refinement linearises around its start; each further pass warps again by the
    # refined flow. From DIS's coarse flow on a street render, 3 passes must end nearer the ground
    # truth than 1, on the static pixels of small displacement most of all (what the static depth needs).
    from monostixels.data.synthetic import render_pair
    from monostixels.inputs.flow import compute_flow

    pair = render_pair(9, scale=0.5)
    gt, valid = pair.gt.flow, pair.gt.flow_valid
    small = valid & ~pair.gt.moving & (gt.norm(dim=0) < 4)
    err = {}
    for passes in (1, 3):
        cfg = OmegaConf.create({"name": "dis", "refine": True, "refine_passes": passes})
        e = (compute_flow(pair.image, pair.image_prev, cfg) - gt).norm(dim=0)
        err[passes] = (float(e[valid].mean()), float(e[small].median()))
    assert err[3][0] < err[1][0]
    assert err[3][1] < 0.8 * err[1][1]
    for bad in (0, -1, 1.5, True, "four"):
        with pytest.raises(InputError, match="flow.refine_passes"):
            compute_flow(pair.image, pair.image_prev, OmegaConf.create({"name": "dis", "refine": True, "refine_passes": bad}))


def test_the_kept_refinement_gives_what_a_new_one_gives():
    # The variational refinement is kept per thread (its buffers reused). Calls on other images and
    # flows, at another size and in another thread must return exactly what a new object returns.
    import cv2
    from concurrent.futures import ThreadPoolExecutor

    from monostixels.inputs.flow_backends import _DIS_PRESETS, _dis_calc, gray_u8, refine_flow

    pairs = [(gray_u8(_texture(96, 160, s)), gray_u8(torch.roll(_texture(96, 160, s), (1, 3 + s), (1, 2))))
             for s in (0, 1)]
    pairs.append((pairs[0][0][:64, :128].copy(), pairs[0][1][:64, :128].copy()))

    def kept(a, b, f):
        return refine_flow((a, b), torch.from_numpy(f.transpose(2, 0, 1).copy())).permute(1, 2, 0).numpy()

    with ThreadPoolExecutor(1) as other:
        for i in (0, 1, 2, 0, 1):
            a, b = pairs[i]
            f = _dis_calc(_DIS_PRESETS["medium"], a, b, None if i != 1 else np.full((*a.shape, 2), 2.0, np.float32))
            want = f.copy()
            cv2.VariationalRefinement_create().calc(a, b, want)
            assert not np.array_equal(want, f)
            for got in (kept(a, b, f), other.submit(kept, a, b, f).result()):
                assert np.array_equal(got, want)


def test_fb_consistency_marks_pixels_that_leave_the_image():
    H, W = 96, 128
    big = _texture(H + 20, W + 20, seed=4)
    prev = big[:, 10:10 + H, 10:10 + W].contiguous()
    cur = big[:, 8:8 + H, 7:7 + W].contiguous()  # d = (3, 2): flow = (-3, -2)
    pair = FramePair(image=cur, image_prev=prev, camera=_camera(H, W), name="shift")
    base = {"name": "dis", "confidence": "structure_tensor", "sigma_max": 20.0}
    plain = estimate_flow(pair, OmegaConf.create(base))
    fb = estimate_flow(pair, OmegaConf.create({**base, "fb_consistency": True}))
    # u + f_u < 0 for u < 3: the round trip cannot be checked -> the covariance ceiling.
    assert torch.allclose(fb.cov[40:60, 0], 400.0 * torch.eye(2).expand(20, 2, 2), rtol=1e-3)
    # Interior: consistent flow, covariance close to the structure-tensor one (< 0.5 px^2 added).
    inner = (slice(20, -20), slice(20, -20))
    added = (fb.cov[inner][..., 0, 0] - plain.cov[inner][..., 0, 0]).median()
    assert 0.0 <= float(added) < 0.5


def test_shipped_deepflow_covariance_is_small_where_the_flow_is_right():
    # The `deepflow` config group checks the flow forward-backward and has a sub-pixel noise floor: its
    # covariance must separate good from bad flow vectors (the solver then trusts sub-pixel flow
    # where the round trip closes) — on a rendered street, against the ground-truth flow.
    from monostixels.data.synthetic import render_pair
    from monostixels.pipeline import load_config

    cfg = load_config(["flow=deepflow"]).flow
    assert cfg.fb_consistency and cfg.sigma_min < 1.0
    # `deepflow_fb` (its earlier name) is the same flow input.
    assert OmegaConf.to_container(load_config(["flow=deepflow_fb"]).flow) == OmegaConf.to_container(cfg)
    pair = render_pair(9, scale=0.5)
    res = estimate_flow(pair, cfg)
    err = (res.flow - pair.gt.flow).norm(dim=0)
    sigma = torch.linalg.eigvalsh(res.cov.double())[..., 1].sqrt()
    valid = pair.gt.flow_valid
    good, bad = valid & (err < 0.5), valid & (err > 3.0)
    assert int(good.sum()) > 1000 and int(bad.sum()) > 100
    # Right vectors get (near) the floor, wrong ones several times more.
    assert float(sigma[good].median()) < 0.6
    assert float(sigma[bad].median()) > 3 * float(sigma[good].median())
    # Without the check, the same floor would call the wrong vectors just as certain.
    plain = estimate_flow(pair, OmegaConf.merge(cfg, {"fb_consistency": False}))
    sigma_plain = torch.linalg.eigvalsh(plain.cov.double())[..., 1].sqrt()
    assert float(sigma_plain[bad].median()) < float(sigma[bad].median()) / 2


def test_gt_backend_and_missing_gt():
    H, W = 16, 20
    img = _texture(H, W)
    flow = torch.randn(2, H, W)
    valid = torch.ones(H, W, dtype=torch.bool)
    valid[0, 0] = False
    flow[:, 0, 0] = float("nan")  # NaN where there is no ground truth is fine
    pair = FramePair(image=img, image_prev=img, camera=_camera(H, W), gt=GroundTruth(flow=flow, flow_valid=valid), name="p")
    res = estimate_flow(pair, OmegaConf.create({"name": "gt", "sigma": 0.5, "sigma_max": 20.0}))
    assert torch.equal(res.flow[:, 1:, 1:], flow[:, 1:, 1:])
    assert torch.allclose(res.cov[3, 4], 0.25 * torch.eye(2))
    assert float(res.flow[0, 0, 0]) == 0.0 and float(res.cov[0, 0, 0, 0]) == pytest.approx(400.0)
    bad = FramePair(image=img, image_prev=img, camera=_camera(H, W), name="p", meta={"source": "kitti_raw"})
    with pytest.raises(InputError, match="kitti_raw"):
        estimate_flow(bad, OmegaConf.create({"name": "gt", "sigma": 0.5}))
    # The oracle keeps the true motion where the source knows it, also at occluded pixels
    # (flow_valid False but finite): only NaN means "no value".
    occluded = torch.randn(2, H, W)
    hidden = torch.zeros(H, W, dtype=torch.bool)
    hidden[2:5, 3:6] = True
    pair = FramePair(image=img, image_prev=img, camera=_camera(H, W), name="p",
                     gt=GroundTruth(flow=occluded, flow_valid=~hidden))
    res = estimate_flow(pair, OmegaConf.create({"name": "gt", "sigma": 0.5, "sigma_max": 20.0}))
    assert torch.equal(res.flow, occluded) and torch.allclose(res.cov[3, 4], 0.25 * torch.eye(2))
    nan_pair = FramePair(image=img, image_prev=img, camera=_camera(H, W), name="p",
                         gt=GroundTruth(flow=torch.full((2, H, W), float("nan"))))
    with pytest.raises(InputError, match="no finite value"):
        estimate_flow(nan_pair, OmegaConf.create({"name": "gt", "sigma": 0.5}))


def test_bad_inputs():
    H, W = 16, 20
    img = _texture(H, W)
    pair = FramePair(image=img, image_prev=img, camera=_camera(H, W), name="p")
    with pytest.raises(InputError, match="flow.name"):
        estimate_flow(pair, OmegaConf.create({"name": "farneback"}))
    with pytest.raises(InputError, match="flow.preset"):
        estimate_flow(pair, OmegaConf.create({"name": "dis", "preset": "turbo"}))
    with pytest.raises(InputError, match="confidence"):
        estimate_flow(pair, OmegaConf.create({"name": "dis", "confidence": "magic"}))
    with pytest.raises(InputError, match="shape"):
        flow_metrics(torch.zeros(3, H, W), torch.zeros(2, H, W))
    nan = torch.zeros(2, H, W)
    nan[0, 1, 1] = float("nan")
    with pytest.raises(InputError, match="non-finite"):
        flow_metrics(nan, torch.zeros(2, H, W))


# --- RAFT -----------------------------------------------------------------------------------------


def test_raft_padded_size():
    assert padded_size(375, 1242) == (376, 1248)
    assert padded_size(100, 50) == (128, 128)
    assert padded_size(128, 160) == (128, 160)


def test_raft_missing_and_wrong_weights(tmp_path):
    missing = tmp_path / "nope.pt"
    with pytest.raises(InputError, match="nope.pt"):
        load_raft_weights(missing)
    H, W = 16, 20
    img = _texture(H, W)
    pair = FramePair(image=img, image_prev=img, camera=_camera(H, W), name="p")
    with pytest.raises(InputError, match="nope.pt"):
        estimate_flow(pair, OmegaConf.create({"name": "raft", "weights": str(missing)}))
    with pytest.raises(InputError, match="nope.onnx"):
        estimate_flow(pair, OmegaConf.create({"name": "raft", "runtime": "onnx", "onnx": str(tmp_path / "nope.onnx")}))
    wrong = tmp_path / "wrong.pt"
    torch.save({"conv.weight": torch.zeros(3)}, wrong)
    with pytest.raises(InputError, match="does not fit RAFT-small"):
        load_raft_weights(wrong, "small")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="cannot read"):
        load_raft_weights(garbage)


@pytest.fixture(scope="module")
def raft3(tmp_path_factory: pytest.TempPathFactory) -> tuple[RaftFlow, Path]:
    """Random RAFT-small with 3 updates and its ONNX export (any size, 128x160 traced), shared by the
    tests below: an export takes 15-20 s. The weights are rounded to float16, as the shipped state dict
    is, so that the float16 test compares like with like."""
    torch.manual_seed(0)
    net = RaftFlow(build_raft("small"), num_flow_updates=3).eval()
    net.raft.load_state_dict({k: v.half().float() if v.is_floating_point() else v
                              for k, v in net.raft.state_dict().items()})
    return net, export_onnx(net, tmp_path_factory.mktemp("raft3") / "raft.onnx", 128, 160)


def test_raft_onnx_with_float16_weights_is_half_the_file_and_the_same_flow(tmp_path, raft3):
    # The shipped state dict is float16: the torch path computes with float16-rounded weights (raft3's).
    net, full = raft3
    H, W = 128, 160
    half = export_onnx(net, tmp_path / "half.onnx", H, W, half_weights=True)
    # Every float32 weight is stored in 2 bytes instead of 4 (the graph itself is the same).
    n_weights = sum(v.numel() for v in net.state_dict().values() if v.is_floating_point())
    assert full.stat().st_size - half.stat().st_size > 0.95 * 2 * n_weights
    a, b = _texture(H, W, seed=6), _texture(H, W, seed=7)
    f_torch = TorchRaft(net)(a, b)
    assert float(f_torch.abs().max()) > 1e-2
    assert torch.allclose(OnnxRaft(half)(a, b), f_torch, atol=1e-3)
    assert torch.allclose(OnnxRaft(half)(a, b), OnnxRaft(full)(a, b), atol=1e-4)


def test_raft_torch_and_onnx_agree(tmp_path, raft3):
    net, path = raft3
    H, W = 128, 160
    a, b = _texture(H, W, seed=2), _texture(H, W, seed=3)
    f_torch = TorchRaft(net)(a, b)
    f_onnx = OnnxRaft(path)(a, b)
    assert f_torch.shape == (2, H, W)
    assert float(f_torch.abs().max()) > 1e-2  # random weights still give a non-trivial output
    assert torch.allclose(f_torch, f_onnx, atol=1e-3)
    # The graph takes any size (multiples of 8 after padding) and both directions as one batch.
    c, d = _texture(141, 203, seed=4), _texture(141, 203, seed=5)
    fwd, bwd = OnnxRaft(path).both_ways(c, d)
    assert fwd.shape == (2, 141, 203)
    assert torch.allclose(fwd, TorchRaft(net)(c, d), atol=1e-3) and torch.allclose(bwd, TorchRaft(net)(d, c), atol=1e-3)
    # A graph traced for one size refuses a larger image clearly.
    fixed = export_onnx(net, tmp_path / "fixed.onnx", H, W, dynamic=False)
    assert torch.allclose(OnnxRaft(fixed)(a, b), f_torch, atol=1e-3)
    with pytest.raises(InputError, match="exported for 128x160"):
        OnnxRaft(fixed)(_texture(136, 160), _texture(136, 160))
    # The state dict round-trips through load_raft_weights and the flow backend.
    wpath = tmp_path / "w.pt"
    torch.save({"model": net.raft.state_dict()}, wpath)
    pair = FramePair(image=a, image_prev=b, camera=_camera(H, W), name="p")
    raw = {"scale": 1.0, "refine": False, "fb_consistency": False}  # the network alone
    res = estimate_flow(pair, OmegaConf.create({"name": "raft", "weights": str(wpath), "iters": 3, **raw}))
    assert torch.allclose(res.flow, f_torch, atol=1e-4)
    res_onnx = estimate_flow(pair, OmegaConf.create({"name": "raft", "runtime": "onnx", "onnx": str(path), **raw}))
    assert torch.allclose(res_onnx.flow, f_torch, atol=1e-3)


def test_raft_runtime_auto_takes_the_export_beside_the_weights(tmp_path, raft3):
    """runtime=auto on a CPU: ONNX Runtime on the weights' own export (same name, .onnx) when it was
    made with the configured updates; torch for other updates, and for weights without an export."""
    import shutil

    from monostixels.inputs.flow_backends import _raft_net

    net, export = raft3
    torch.save(net.raft.state_dict(), tmp_path / "mine.pt")
    shutil.copy(export, tmp_path / "mine.onnx")
    assert OnnxRaft(tmp_path / "mine.onnx").num_flow_updates == 3
    torch.save(net.raft.state_dict(), tmp_path / "other.pt")
    cfg = {"name": "raft", "runtime": "auto", "weights": str(tmp_path / "mine.pt"), "iters": 3, "precision": "float32",
           "scale": 1.0, "refine": False, "fb_consistency": False}
    assert isinstance(_raft_net(OmegaConf.create(cfg)), OnnxRaft)
    assert isinstance(_raft_net(OmegaConf.create({**cfg, "iters": 4})), TorchRaft)
    assert isinstance(_raft_net(OmegaConf.create({**cfg, "weights": str(tmp_path / "other.pt")})), TorchRaft)
    a, b = _texture(128, 160, seed=8), _texture(128, 160, seed=9)
    pair = FramePair(image=a, image_prev=b, camera=_camera(128, 160), name="p")
    flows = [estimate_flow(pair, OmegaConf.create({**cfg, "runtime": rt})).flow for rt in ("auto", "torch")]
    assert torch.allclose(flows[0], flows[1], atol=1e-3)
    with pytest.raises(InputError, match="flow.runtime"):
        _raft_net(OmegaConf.create({**cfg, "runtime": "tensorrt"}))


def test_raft_int8_copy_quantizes_the_convolutions_and_keeps_the_flow(tmp_path):
    """quantize_onnx: the shipped weights' graph with its convolutions in INT8 (calibrated on one
    render) gives the float graph's flow on another render within a fraction of a pixel, and a
    graph that is not both ways is refused, naming the file."""
    import onnx

    from monostixels.data.synthetic import render_pair
    from monostixels.inputs.raft import quantize_onnx

    # The shipped float graph itself (the export of the shipped weights; exporting them again takes 25 s).
    f32 = REPO / "models" / "raft_small.onnx"
    calib, test = render_pair(5, scale=0.2), render_pair(6, scale=0.2)
    q8 = quantize_onnx(f32, tmp_path / "q8.onnx", [(calib.image, calib.image_prev)])
    ops = [n.op_type for n in onnx.load(str(q8)).graph.node]
    assert ops.count("DequantizeLinear") > ops.count("Conv") > 0  # every Conv reads quantized inputs
    runner = OnnxRaft(q8)
    assert OnnxRaft(f32).quantized is None and OnnxRaft(f32).num_flow_updates >= 2
    assert runner.quantized == "int8" and runner.num_flow_updates == OnnxRaft(f32).num_flow_updates
    want = OnnxRaft(f32)(test.image, test.image_prev)
    got = runner(test.image, test.image_prev)
    assert float(want.abs().mean()) > 1.0
    assert 0 < float((got - want).norm(dim=0).mean()) < 0.1 * float(want.norm(dim=0).mean())
    fixed = export_onnx(RaftFlow(build_raft("small"), 1), tmp_path / "fixed.onnx", 128, 160, dynamic=False)
    with pytest.raises(InputError, match="fixed.onnx"):
        quantize_onnx(fixed, tmp_path / "x.onnx", [(calib.image, calib.image_prev)])


def test_shipped_raft_files_agree_and_auto_runs_the_onnx_one():
    """models/raft_small.onnx is the export of models/raft_small.pt (the same flow on a render), with
    the shipped config's updates recorded, so that runtime=auto takes it on a CPU."""
    from monostixels.inputs.flow_backends import _raft_net
    from monostixels.pipeline import load_config

    cfg = load_config(["flow=raft"]).flow
    onnx_net = _raft_net(OmegaConf.merge(cfg, {"runtime": "onnx"}))
    assert onnx_net.num_flow_updates == int(cfg.iters)
    if not torch.cuda.is_available():
        assert isinstance(_raft_net(cfg), OnnxRaft)
    torch_net = _raft_net(OmegaConf.merge(cfg, {"runtime": "torch"}))
    assert torch_net.module.raft.mask_predictor is not None  # the shipped weights carry the convex upsampler
    from monostixels.data.synthetic import render_pair

    pair = render_pair(0, scale=0.25)
    f_onnx, f_torch = onnx_net(pair.image, pair.image_prev), torch_net(pair.image, pair.image_prev)
    assert float(f_torch.abs().max()) > 1.0
    assert float((f_onnx - f_torch).abs().max()) < 0.02
    # The INT8 copy (flow.precision=int8, the default): what auto runs on a CPU, the same updates, a flow
    # within a few percent of the float one's (0.27 px of 7 px here, before any refinement) and as close
    # to the ground truth.
    int8_file = REPO / "models" / "raft_small_int8.onnx"
    int8 = _raft_net(OmegaConf.merge(cfg, {"runtime": "onnx", "onnx": str(int8_file)}))
    assert int8.quantized == "int8" and int8.num_flow_updates == int(cfg.iters) and cfg.precision == "int8"
    # The copy's 8-bit weights can saturate the 16-bit pairwise sums of a CPU without VNNI (0.37 px from the
    # float flow here on an emulated Haswell, 0.27 px with VNNI; monostixels/inputs/quantize.py): auto runs the
    # float graph there.
    saturates = int8_path() == "no_vnni" and can_saturate(int8_file)
    if not torch.cuda.is_available():
        assert _raft_net(cfg).quantized == (None if saturates else "int8")
        assert _raft_net(OmegaConf.merge(cfg, {"precision": "float32"})).quantized is None
    if not saturates:
        f_int8 = int8(pair.image, pair.image_prev)
        assert float((f_int8 - f_torch).norm(dim=0).mean()) < 0.05 * float(f_torch.norm(dim=0).mean())
        epe = [float((f - pair.gt.flow).norm(dim=0).mean()) for f in (f_torch, f_int8)]
        assert epe[1] < 1.03 * epe[0]
    with pytest.raises(InputError, match="flow.precision: expected one of float32, int8, got 'fp8'"):
        load_config(["flow=raft", "flow.precision=fp8"])  # the schema refuses it (flow_config.Precision)


@pytest.mark.skipif(torch.cuda.is_available(), reason="runtime=auto takes torch on a GPU")
def test_without_vnni_an_int8_raft_with_8_bit_weights_gives_way_to_the_float_graph(monkeypatch, caplog):
    import logging

    from monostixels import _cpu
    from monostixels.inputs import flow_backends as flow_mod
    from monostixels.pipeline import load_config

    cfg = load_config(["flow=raft"]).flow
    monkeypatch.setattr(_cpu, "int8_path", lambda: "no_vnni")
    monkeypatch.setattr(flow_mod, "_saturates_here", lru_cache(flow_mod._saturates_here.__wrapped__))
    with caplog.at_level(logging.WARNING, logger="monostixels.inputs.flow_backends"):
        net = flow_mod._raft_net(cfg)
        assert net.quantized is None and net.path.name == "raft_small.onnx"
        flow_mod._raft_net(cfg)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "raft_small_int8.onnx has 8-bit weights" in warned[0]


def test_gather_correlation_lookup_equals_torchvisions_grid_sample():
    """GatherCorrBlock (the lookup our RAFT uses) against torchvision's CorrBlock: the same features,
    centroids inside, between cells, and beyond the volume's edges (zeros there) alike."""
    from monostixels._torchvision import torchvision
    from monostixels.inputs.raft import GatherCorrBlock

    torch.manual_seed(4)
    f1, f2 = torch.randn(2, 8, 18, 30), torch.randn(2, 8, 18, 30)
    ref = torchvision.models.optical_flow.raft.CorrBlock(num_levels=4, radius=3)
    ours = GatherCorrBlock(num_levels=4, radius=3)
    ref.build_pyramid(f1, f2)
    ours.build_pyramid(f1, f2)
    c = torch.rand(2, 2, 18, 30) * torch.tensor([50.0, 36.0]).view(1, 2, 1, 1) - torch.tensor([10.0, 9.0]).view(1, 2, 1, 1)
    c[0, :, 0, 0] = torch.tensor([4.0, 7.0])  # on a cell exactly
    want, got = ref.index_pyramid(c), ours.index_pyramid(c)
    assert got.shape == want.shape == (2, 4 * 49, 18, 30)
    assert float(want.abs().max()) > 1.0
    assert torch.allclose(got, want, atol=1e-5)


@pytest.mark.parametrize("mask_hidden", [0, 16])
def test_raft_flow_equals_torchvisions_last_prediction(mask_hidden):
    """RaftFlow runs RAFT's updates itself and upsamples once, after the last: the same flow as the
    last of torchvision's per-update predictions, bilinear and convex upsampling alike."""
    torch.manual_seed(3)
    raft = build_raft("small", mask_hidden=mask_hidden).eval()
    a, b = _texture(128, 192, seed=2)[None], _texture(128, 192, seed=3)[None]
    with torch.inference_mode():
        want = raft(2 * a - 1, 2 * b - 1, num_flow_updates=3)[-1]
        got = RaftFlow(raft, 3)(a, b)
    assert float(want.abs().max()) > 0.01
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-6)


def test_convex_upsampling_equals_torchvisions():
    """convex_upsample (the softmax written out, for ONNX Runtime) is torchvision's upsample_flow with a mask."""
    from monostixels._torchvision import torchvision
    from monostixels.inputs.raft import convex_upsample

    torch.manual_seed(5)
    flow, mask = 6 * torch.randn(2, 2, 5, 7), 4 * torch.randn(2, 9 * 64, 5, 7)
    want = torchvision.models.optical_flow._utils.upsample_flow(flow, up_mask=mask)
    got = convex_upsample(flow, mask)
    assert got.shape == want.shape == (2, 2, 40, 56)
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-5)
    # Each vector is a convex combination of 8x its 3x3 neighbours (zero beyond the border).
    assert float(got.abs().max()) <= 8 * float(flow.abs().max()) + 1e-4


def test_raft_small_with_the_convex_upsampler_exports_and_loads(tmp_path):
    """RAFT-small with a mask predictor: the weights file says so (load_raft_weights builds it), the
    ONNX graph gives the torch flow, and its upsampling is not the bilinear one."""
    torch.manual_seed(1)
    net = RaftFlow(build_raft("small", mask_hidden=24), num_flow_updates=2).eval()
    wpath = tmp_path / "convex.pt"
    torch.save(net.raft.state_dict(), wpath)
    loaded = load_raft_weights(wpath, "small")
    assert loaded.mask_predictor is not None and loaded.mask_predictor.conv.in_channels == 24
    H, W = 128, 160
    a, b = _texture(H, W, seed=6), _texture(H, W, seed=7)
    f_torch = TorchRaft(RaftFlow(loaded, 2))(a, b)
    assert torch.allclose(f_torch, TorchRaft(net)(a, b))
    path = export_onnx(net, tmp_path / "convex.onnx", H, W)
    assert torch.allclose(OnnxRaft(path)(a, b), f_torch, atol=1e-3)
    # The same body without the head upsamples bilinearly: a different flow.
    bilinear = build_raft("small")
    bilinear.load_state_dict({k: v for k, v in net.raft.state_dict().items() if not k.startswith("mask_predictor.")})
    assert float((TorchRaft(RaftFlow(bilinear.eval(), 2))(a, b) - f_torch).abs().max()) > 1e-3
    # A large model's file is not RAFT-small, head or not.
    torch.save(build_raft("large").state_dict(), tmp_path / "large.pt")
    with pytest.raises(InputError, match="large.pt"):
        load_raft_weights(tmp_path / "large.pt", "small")


# --- metrics --------------------------------------------------------------------------------------


def test_flow_metrics_hand_computed():
    gt = torch.zeros(2, 1, 4)
    gt[0] = torch.tensor([[10.0, 100.0, 1.0, 50.0]])
    est = gt.clone()
    est[0, 0, 0] += 4.0   # err 4 > 3 and > 0.5: outlier
    est[0, 0, 1] += 4.0   # err 4 > 3 but < 5 % of 100: inlier
    est[1, 0, 2] += 2.0   # err 2 < 3: inlier
    valid = torch.tensor([[True, True, True, False]])
    est[0, 0, 3] += 30.0  # invalid pixel: ignored
    m = flow_metrics(est, gt, valid)
    assert m["epe"] == pytest.approx((4 + 4 + 2) / 3)
    assert m["fl_all"] == pytest.approx(1 / 3)


def test_raft_forward_backward_refined_hands_on_its_grey_image(tmp_path):
    """With the forward-backward check and the refinement, RAFT returns the current image's grey (the
    next pair's previous one), and a grey handed in changes nothing."""
    from monostixels.inputs.flow_backends import gray_u8

    torch.manual_seed(2)
    net = RaftFlow(build_raft("small"), num_flow_updates=2).eval()
    wpath = tmp_path / "w.pt"
    torch.save({"model": net.raft.state_dict()}, wpath)
    H, W = 128, 160
    a, b = _texture(H, W, seed=8), _texture(H, W, seed=9)
    pair = FramePair(image=a, image_prev=b, camera=_camera(H, W), name="p")
    cfg = OmegaConf.create({"name": "raft", "weights": str(wpath), "iters": 2, "refine": True, "fb_consistency": True,
                            "scale": 1.0, "refine_passes": 1, "precision": "float32"})
    cold = estimate_flow(pair, cfg)
    assert cold.grey is not None and np.array_equal(cold.grey, gray_u8(a.float()))
    warm = estimate_flow(pair, cfg, grey_prev=gray_u8(b.float()))
    assert torch.equal(warm.flow, cold.flow) and torch.equal(warm.cov, cold.cov)


# --- tiny images: a clear error, never a crash ------------------------------------------------------


@pytest.mark.parametrize("size", [(12, 40), (2, 2), (1, 1000)])
def test_tiny_images_fail_clearly_in_the_low_level_functions(size):
    """OpenCV's DIS and filters segfaulted on such images; the functions now raise InputError first."""
    from monostixels.inputs.confidence import structure_tensor
    from monostixels.inputs.flow_backends import _dis_calc

    H, W = size
    grey = np.random.default_rng(0).random((H, W)).astype(np.float32)
    with pytest.raises(InputError, match="structure tensor"):
        structure_tensor(torch.from_numpy(grey), 2.0)
    with pytest.raises(InputError, match=rf"{W}x{H}"):
        _dis_calc(1, (grey * 255).astype(np.uint8), (grey * 255).astype(np.uint8), None)
    with pytest.raises(InputError, match="structure tensor"):
        flow_covariance(torch.from_numpy(grey)[None].repeat(3, 1, 1), ConfidenceParams())


def test_dis_on_a_wide_low_image_fails_clearly():
    """16 x 1000 px: OpenCV's DIS asserts in its resize (a cv2.error); it becomes a named InputError."""
    from monostixels.inputs.flow_backends import _dis_calc

    a = (np.random.default_rng(1).random((16, 1000)) * 255).astype(np.uint8)
    with pytest.raises(InputError, match="1000x16"):
        _dis_calc(1, a, a, None)
