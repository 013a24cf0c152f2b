"""The faster paths of the pipeline against their plain definitions: the vectorised mover check
(monostixels.post.movers) and the flow at a reduced resolution (``flow.scale``, monostixels.inputs.flow)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from monostixels._checks import InputError
from monostixels.core.classes import DYNAMIC_OBJECT, STATIC_OBJECT
from monostixels.data.base import FramePair
from monostixels.post.sfm import triangulate
from monostixels.core.geometry import Camera, Motion, apply_homography, homography, intrinsics, pixel_rays
from monostixels.inputs.flow import compute_flow, estimate_flow, flow_metrics
from monostixels.post.movers import MoverCheckParams, check_movers
from monostixels.core.stixels import segment_lower_median
from monostixels.core.stixels import StixelWorld

# Asymmetric camera (fx != fy, cx, cy off centre), H != W, a small yaw.
H, W, WS = 48, 70, 5
K = intrinsics(60.0, 55.0, 37.0, 21.0)
N_G = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
_YAW = 0.01
R = torch.tensor([[math.cos(_YAW), 0.0, math.sin(_YAW)], [0.0, 1.0, 0.0], [-math.sin(_YAW), 0.0, math.cos(_YAW)]],
                 dtype=torch.float64)
MOTION = Motion(R, torch.tensor([0.03, 0.01, 1.0], dtype=torch.float64))


def _check_movers_loop(stixels: StixelWorld, flow: torch.Tensor, motion: Motion, prm: MoverCheckParams) -> StixelWorld:
    """The mover check written stixel by stixel, each column bottom-up (its definition before it was vectorised)."""
    z = triangulate(flow, stixels.K, motion).depth.double()
    Kd, Rd, td = stixels.K.double(), motion.R.double(), motion.t.double()
    n_all, f = stixels.normals().double(), flow.double()
    ng = stixels.ground_normal.double()
    out_type, out_p = stixels.type.clone(), stixels.inverse_depth.clone()
    still: dict[int, bool] = {}
    d_static: dict[int, float] = {}
    d_ground: dict[int, float] = {}  # ground height under a dynamic stixel's stack (nan: none)

    def contact_row(k: int, d: float, h: float) -> float:
        x = Kd @ (d * n_all[k] + h * ng)
        return float(x[1] / x[2])

    order = sorted(range(len(stixels.type)), key=lambda k: (int(stixels.column[k]), -int(stixels.v_top[k])))
    for k in order:
        if int(stixels.type[k]) != DYNAMIC_OBJECT:
            continue
        c0 = int(stixels.column[k]) * stixels.column_width
        c1 = min(c0 + stixels.column_width, W)
        v0, v1 = int(stixels.v_top[k]), int(stixels.v_bottom[k]) + 1
        below = [b for b in range(len(stixels.type))
                 if int(stixels.column[b]) == int(stixels.column[k]) and int(stixels.v_top[b]) == v1]
        b = below[0] if below else None
        p_model = float(stixels.inverse_depth[k])
        d_model = 1.0 / p_model if p_model > 0 else math.inf
        b_still = b is not None and int(stixels.type[b]) == DYNAMIC_OBJECT and still[b]
        if b is not None and int(stixels.type[b]) == 0 and float(stixels.inverse_depth[b]) > 0 and math.isfinite(d_model):
            d_ground[k] = 1.0 / float(stixels.inverse_depth[b])  # on a ground stixel
        elif b is not None and int(stixels.type[b]) == DYNAMIC_OBJECT and not b_still and prm.follow_below:
            d_ground[k] = d_ground[b]  # on a moving stack: the stack's ground
        else:
            d_ground[k] = math.nan
        d_ref = d_static[b] if (b_still and prm.follow_below) else d_model
        still[k] = False
        vv, uu = torch.meshgrid(torch.arange(v0, v1, dtype=torch.float64), torch.arange(c0, c1, dtype=torch.float64),
                                indexing="ij")
        zz = z[v0:v1, c0:c1]
        ok = torch.isfinite(zz) & (zz >= prm.min_depth) & (zz <= prm.max_depth)
        d_static[k] = float((zz[ok] * (pixel_rays(Kd, uu[ok], vv[ok]) @ n_all[k])).median()) if ok.any() else math.nan
        d_s = d_static[k]
        if int(ok.sum()) < prm.min_pixels or not d_s > 0:
            continue
        up, vp = apply_homography(homography(Kd, Rd, td, n_all[k], torch.tensor(1.0 / d_s, dtype=torch.float64)), uu, vv)
        e_s = float(torch.hypot(up - uu - f[0, v0:v1, c0:c1], vp - vv - f[1, v0:v1, c0:c1]).median())
        if e_s > prm.max_static_residual_px or abs(d_ref / d_s - 1.0) > prm.min_depth_discrepancy:
            continue
        h = d_ground[k]
        if math.isfinite(h) and abs(contact_row(k, d_s, h) - contact_row(k, d_model, h)) > prm.max_contact_gap_px:
            continue
        still[k] = True
        out_type[k] = STATIC_OBJECT
        out_p[k] = torch.as_tensor(1.0 / d_s, dtype=out_p.dtype)
    return StixelWorld(**{**stixels.__dict__, "type": out_type, "inverse_depth": out_p})


def _random_scene(seed: int) -> tuple[StixelWorld, torch.Tensor]:
    """Random stixels (2-4 per column, mixed types) and a flow: static walls at random depths, some
    columns pushed sideways (crossing movers), noise."""
    g = torch.Generator().manual_seed(seed)
    ncol = -(-W // WS)
    cols, tops, bots, types, ps = [], [], [], [], []
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    flow = torch.zeros(2, H, W, dtype=torch.float64)
    for c in range(ncol):
        cuts = sorted(torch.randperm(H - 2, generator=g)[: int(torch.randint(1, 4, (1,), generator=g))].add(1).tolist())
        edges = [0, *cuts, H]
        for a, b in zip(edges[:-1], edges[1:]):
            depth = float(torch.empty(1).uniform_(3.0, 40.0, generator=g))
            n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
            Hm = homography(K.double(), R, MOTION.t, n, torch.tensor(1.0 / depth, dtype=torch.float64))
            up, vp = apply_homography(Hm, u[a:b, c * WS:(c + 1) * WS], v[a:b, c * WS:(c + 1) * WS])
            flow[0, a:b, c * WS:(c + 1) * WS] = up - u[a:b, c * WS:(c + 1) * WS]
            flow[1, a:b, c * WS:(c + 1) * WS] = vp - v[a:b, c * WS:(c + 1) * WS]
            if float(torch.rand(1, generator=g)) < 0.25:
                flow[0, a:b, c * WS:(c + 1) * WS] += 5.0  # crossing mover
            cols.append(c)
            tops.append(a)
            bots.append(b - 1)
            types.append(DYNAMIC_OBJECT if float(torch.rand(1, generator=g)) < 0.7 else STATIC_OBJECT)
            # Model depth: right, 10-50 % off, or sky-like 0 (no depth).
            r = float(torch.rand(1, generator=g))
            ps.append(0.0 if r < 0.1 else 1.0 / (depth * (1.0 + 0.5 * r)))
            if b == H and c % 2 == 0:
                types[-1], ps[-1] = 0, 1.0 / float(torch.empty(1).uniform_(1.0, 2.0, generator=g))  # ground, height
    flow = flow + 0.3 * torch.randn(flow.shape, generator=g, dtype=torch.float64)
    n = len(cols)
    st = StixelWorld(
        column_width=WS, image_size=(H, W), K=K, ground_normal=N_G,
        column=torch.tensor(cols), v_top=torch.tensor(tops), v_bottom=torch.tensor(bots),
        type=torch.tensor(types), cls=torch.full((n,), 6), inverse_depth=torch.tensor(ps, dtype=torch.float32),
        motion=torch.full((n, 3), 0.1, dtype=torch.float64), cost=torch.zeros(n),
        tau=torch.full((n, 2), 0.2, dtype=torch.float64), energy=torch.zeros(ncol))
    return st, flow.float()


@pytest.mark.parametrize("variant", ["default", "tight_contact", "no_follow"])
@pytest.mark.parametrize("seed", range(6))
def test_vectorised_mover_check_equals_the_loop(seed, variant):
    st, flow = _random_scene(seed)
    # The test camera is small (f = 60 px): a tight contact tolerance makes the ground-contact test decide.
    prm = {"default": MoverCheckParams(keep_classes=(), max_dynamic_residual_ratio=math.inf, isolated_stand_still=False, contact_sliver_rows=0.0, min_pixels=5),
           "tight_contact": MoverCheckParams(keep_classes=(), max_dynamic_residual_ratio=math.inf, isolated_stand_still=False, contact_sliver_rows=0.0, min_pixels=5, max_contact_gap_px=0.3),
           "no_follow": MoverCheckParams(keep_classes=(), max_dynamic_residual_ratio=math.inf, isolated_stand_still=False, contact_sliver_rows=0.0, min_pixels=5, max_contact_gap_px=0.3, follow_below=False)}[variant]
    want = _check_movers_loop(st, flow, MOTION, prm)
    got = check_movers(st, flow, MOTION, params=prm)
    assert torch.equal(got.type, want.type)
    assert torch.equal(got.inverse_depth, want.inverse_depth)
    changed = (st.type == DYNAMIC_OBJECT) & (got.type == STATIC_OBJECT)
    assert got.flags["static_checked"] == int(changed.sum())
    assert 0 < int(changed.sum()) < int((st.type == DYNAMIC_OBJECT).sum())  # the scene exercises both outcomes
    assert float(got.motion[changed].abs().max()) == 0.0 and float(got.tau[changed].abs().max()) == 0.0
    assert torch.equal(got.motion[~changed], st.motion[~changed])
    # A given point depth (the SfM baseline's) gives the same answer as triangulating here.
    depth = triangulate(flow, st.K, MOTION).depth
    assert torch.equal(check_movers(st, flow, MOTION, point_depth=depth, params=prm).type, got.type)


def test_mover_check_variants_decide_differently():
    """The random scenes exercise the ground-contact test and the bottom-up reference depth."""
    differ = {"contact": 0, "follow": 0}
    for seed in range(6):
        st, flow = _random_scene(seed)
        a = check_movers(st, flow, MOTION, params=MoverCheckParams(keep_classes=(), max_dynamic_residual_ratio=math.inf, isolated_stand_still=False, contact_sliver_rows=0.0, min_pixels=5, max_contact_gap_px=math.inf))
        b = check_movers(st, flow, MOTION, params=MoverCheckParams(keep_classes=(), max_dynamic_residual_ratio=math.inf, isolated_stand_still=False, contact_sliver_rows=0.0, min_pixels=5, max_contact_gap_px=0.3))
        c = check_movers(st, flow, MOTION, params=MoverCheckParams(keep_classes=(), max_dynamic_residual_ratio=math.inf, isolated_stand_still=False, contact_sliver_rows=0.0, min_pixels=5, max_contact_gap_px=0.3, follow_below=False))
        differ["contact"] += int((a.type != b.type).sum())
        differ["follow"] += int((b.type != c.type).sum())
    assert differ["contact"] > 0 and differ["follow"] > 0


def test_segment_lower_median_matches_torch_median():
    g = torch.Generator().manual_seed(3)
    counts = torch.tensor([1, 2, 5, 0, 6, 3])
    values = torch.randn(int(counts.sum()), generator=g, dtype=torch.float64)
    values[3] = values[4]  # a tie
    values[-2] = math.nan  # the last segment holds a NaN
    seg = torch.repeat_interleave(torch.arange(len(counts)), counts)
    got = segment_lower_median(values, seg, counts)
    start = 0
    for s, n in enumerate(counts.tolist()):
        if n == 0:
            assert math.isnan(float(got[s]))
        else:
            want = values[start:start + n].median()
            assert (math.isnan(float(got[s])) and math.isnan(float(want))) or float(got[s]) == float(want)
        start += n


# --- flow.scale / flow.refine -------------------------------------------------------------------


def _texture(h: int, w: int, seed: int = 0) -> torch.Tensor:
    """Smooth random texture (3, h, w) in [0, 1]."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for k, amp in ((2, 0.5), (5, 0.3), (11, 0.2)):
        img += amp * cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), k / 3.0)
    img = (img - img.min()) / (img.max() - img.min())
    return torch.from_numpy(img)[None].repeat(3, 1, 1)


def _shift_pair(d: tuple[int, int], h: int = 90, w: int = 132) -> FramePair:
    """cur(x) = prev(x - d): the flow current -> previous is -d everywhere (d = (du, dv) pixels)."""
    big = _texture(h + 24, w + 24, seed=2)
    prev = big[:, 12:12 + h, 12:12 + w].contiguous()
    cur = big[:, 12 - d[1]:12 - d[1] + h, 12 - d[0]:12 - d[0] + w].contiguous()
    return FramePair(image=cur, image_prev=prev, camera=Camera(K=intrinsics(100.0, 95.0, 70.0, 40.0)), name="shift")


@pytest.mark.parametrize("name", ["deepflow", "dis"])
@pytest.mark.parametrize("refine", [False, True])
def test_scaled_flow_is_in_full_size_pixels(name, refine):
    # An asymmetric shift (du != dv) on H != W at scale 0.6 (h / H != w / W): a vector left in grid
    # pixels would read 0.6 d, a swapped axis would read (dv, du).
    d = (5, 2)
    pair = _shift_pair(d)
    res = estimate_flow(pair, OmegaConf.create({"name": name, "scale": 0.6, "refine": refine, "refine_passes": 1,
                                                "fb_consistency": False, "confidence": "structure_tensor"}))
    assert res.flow.shape == (2, 90, 132) and res.cov.shape == (90, 132, 2, 2)
    inner = res.flow[:, 15:-15, 15:-15]
    assert float(inner[0].median()) == pytest.approx(-d[0], abs=0.3)
    assert float(inner[1].median()) == pytest.approx(-d[1], abs=0.3)
    ev = torch.linalg.eigvalsh(res.cov.double())
    assert float(ev.min()) > 0


def test_scaled_flow_upsampling_convention():
    # A zoom about the continuous point c: x_prev = c + k (x - c), with pixel centres at u + 0.5.
    # Sampled at the grid's pixel centres, upsampled and rescaled, it must be the full-size zoom flow.
    from monostixels.inputs.flow_resample import upsample_flow

    k, cu, cv = 1.04, 50.3, 20.7
    H, W, h, w = 60, 150, 24, 50  # grid scales 0.4 (rows) and 1/3 (columns)
    vl, ul = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    sx, sy = w / W, h / H
    low = torch.stack([(k - 1) * ((ul + 0.5) - cu * sx), (k - 1) * ((vl + 0.5) - cv * sy)]).float()
    up = upsample_flow(low, (H, W))
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    want = torch.stack([(k - 1) * ((u + 0.5) - cu), (k - 1) * ((v + 0.5) - cv)]).float()
    assert torch.allclose(up[:, 3:-3, 3:-3], want[:, 3:-3, 3:-3], atol=1e-4)


def test_scaled_covariance_units():
    # Without refinement the covariance is computed on the grid and mapped to full-size pixels^2:
    # `constant` must still be sigma^2 (full-size pixels), floor and ceiling hold.
    pair = _shift_pair((3, 1))
    res = estimate_flow(pair, OmegaConf.create({"name": "dis", "scale": 0.5, "confidence": "constant", "sigma": 0.8,
                                                "sigma_min": 0.8}))
    assert torch.allclose(res.cov, 0.64 * torch.eye(2).expand(90, 132, 2, 2), rtol=0.02, atol=1e-6)
    st = estimate_flow(pair, OmegaConf.create({"name": "dis", "scale": 0.5, "confidence": "structure_tensor",
                                               "sigma_min": 1.0, "sigma_max": 20.0}))
    ev = torch.linalg.eigvalsh(st.cov.double())
    assert float(ev.min()) >= 1.0 * 0.98 and float(ev.max()) <= 400.0 * 1.02
    # Below the floor, textured pixels are pinned less on the grid than at full size (the grid lost
    # the finest texture), and in full-size pixels^2 (not grid pixels^2, 4x smaller).
    low = {"name": "dis", "confidence": "structure_tensor", "sigma_min": 0.01, "sigma_max": 20.0}
    grid = estimate_flow(pair, OmegaConf.create({**low, "scale": 0.5})).cov[10:-10, 10:-10, 0, 0].median()
    full = estimate_flow(pair, OmegaConf.create(low)).cov[10:-10, 10:-10, 0, 0].median()
    assert 3.0 * float(full) < float(grid) < 40.0 * float(full)


def test_half_resolution_deepflow_on_a_rendered_street():
    # Known ground-truth flow: DeepFlow with its variational stage at half size stays close to the
    # full-size result; the full-size refinement brings it back to within 0.15 px of it.
    from monostixels.data.synthetic import render_pair

    pair = render_pair(9, scale=0.4)
    epe = {}
    raw = {"name": "deepflow", "confidence": "structure_tensor", "refine": False, "refine_passes": 1, "fb_consistency": False}
    for key, extra in (("full", {}), ("half", {"scale": 0.5}), ("half_refined", {"scale": 0.5, "refine": True})):
        res = estimate_flow(pair, OmegaConf.create({**raw, **extra}))
        epe[key] = flow_metrics(res.flow, pair.gt.flow, pair.gt.flow_valid)["epe"]
    assert epe["full"] < 2.0
    assert epe["half"] < epe["full"] + 0.5
    assert epe["half_refined"] < epe["full"] + 0.15


@pytest.mark.parametrize("bad", [0, -0.5, 1.5, float("nan"), "half"])
def test_bad_flow_scale_names_the_option(bad):
    pair = _shift_pair((2, 1))
    with pytest.raises(InputError, match=r"flow\.scale"):
        estimate_flow(pair, OmegaConf.create({"name": "dis", "scale": bad}))
    with pytest.raises(InputError, match=r"flow\.scale"):
        compute_flow(pair.image, pair.image_prev, OmegaConf.create({"name": "deepflow", "scale": bad}))


def test_flow_scale_too_small_and_bad_refine():
    pair = _shift_pair((2, 1))
    with pytest.raises(InputError, match=r"flow\.scale.*16 px"):
        estimate_flow(pair, OmegaConf.create({"name": "dis", "scale": 0.1}))
    with pytest.raises(InputError, match=r"flow\.refine"):
        estimate_flow(pair, OmegaConf.create({"name": "dis", "refine": "maybe"}))


# --- closed-form covariance -----------------------------------------------------------------------


def test_clip_eigenvalues_closed_form_matches_eigh():
    from monostixels.inputs.confidence import _clip_eigenvalues

    g = torch.Generator().manual_seed(5)
    A = torch.randn(200, 2, 2, generator=g, dtype=torch.float64)
    C = A @ A.transpose(-1, -2) * torch.rand(200, 1, 1, generator=g, dtype=torch.float64) * 30
    C[0] = 7.0 * torch.eye(2, dtype=torch.float64)  # isotropic, inside the bounds
    C[1] = torch.tensor([[1e-4, 0.0], [0.0, 1e-4]], dtype=torch.float64)  # isotropic, below the floor
    C[2] = torch.tensor([[500.0, 3.0], [3.0, 0.01]], dtype=torch.float64)  # both bounds hit
    lo, hi = 0.5, 100.0
    got = _clip_eigenvalues(C[:, 0, 0].numpy(), C[:, 0, 1].numpy(), C[:, 1, 1].numpy(), lo, hi).double()
    L, V = torch.linalg.eigh(C)
    want = V @ torch.diag_embed(L.clamp(lo, hi)) @ V.transpose(-1, -2)
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-5)
    assert torch.equal(got[:, 0, 1], got[:, 1, 0])


def test_flow_covariance_computed_in_place_equals_the_written_formulas():
    # flow_covariance reuses its arrays step by step; the formulas written out with a fresh array for
    # each step must give the same bits (an aliasing slip would not).
    from monostixels.inputs.confidence import ConfidenceParams, _structure_tensor_parts, flow_covariance, to_gray

    g = torch.Generator().manual_seed(3)
    img = torch.rand(3, 48, 64, generator=g)
    img[:, 20:30] = 0.5  # a textureless band: the prior and the ceiling
    fb = torch.rand(48, 64, generator=g) * 4
    fb[::5, ::3] = float("inf")
    fb[7, 9] = float("nan")
    for p in (ConfidenceParams(), ConfidenceParams(sigma_min=1.0, fb_weight=0.5), ConfidenceParams(method="constant")):
        for err in (None, fb):
            got = flow_covariance(img, p, fb_error=err).double()
            if p.method == "constant":
                a = np.full((48, 64), p.sigma**2)
                b = np.zeros((48, 64))
                c = a.copy()
            else:
                jxx, jxy, jyy = (x.astype(np.float64) for x in _structure_tensor_parts(to_gray(img).numpy(), p.window_sigma))
                k = 4.0 * math.pi * p.window_sigma**2 / p.noise**2
                prior = 1.0 / p.sigma_max**2
                ia, ib, ic = jxx * k + prior, jxy * k, jyy * k + prior
                det = ia * ic - ib * ib
                a, b, c = ic / det, -ib / det, ia / det
            if err is not None:
                e = np.minimum(p.fb_weight * np.nan_to_num(err.numpy(), nan=np.inf), p.sigma_max).astype(np.float64)
                a, c = a + e * e, c + e * e
            lo, hi = p.sigma_min**2, p.sigma_max**2
            m, h = 0.5 * (a + c), 0.5 * (a - c)
            r = np.sqrt(h * h + b * b)
            l1, l2 = np.clip(m + r, lo, hi), np.clip(m - r, lo, hi)
            m2, r2 = 0.5 * (l1 + l2), 0.5 * (l1 - l2)
            ratio = np.divide(r2, r, out=np.zeros_like(r), where=r > 0)
            want = np.stack([np.stack([m2 + ratio * h, ratio * b], -1), np.stack([ratio * b, m2 - ratio * h], -1)], -2)
            if p.method == "constant" and err is None:
                want = np.broadcast_to(np.diag([p.sigma**2] * 2), (48, 64, 2, 2))
            assert torch.equal(got, torch.from_numpy(want.astype(np.float32)).double()), (p, err is None)


def test_structure_tensor_of_a_diagonal_ramp():
    # I = gu u + gv v (gu != gv, opposite signs): J = [[gu^2, gu gv], [gu gv, gv^2]] away from the border.
    from monostixels.inputs.confidence import structure_tensor

    gu, gv = 0.004, -0.007
    v, u = torch.meshgrid(torch.arange(40, dtype=torch.float32), torch.arange(70, dtype=torch.float32), indexing="ij")
    J = structure_tensor(0.5 + gu * u + gv * v, 2.0)[10:-10, 10:-10]
    want = torch.tensor([[gu * gu, gu * gv], [gu * gv, gv * gv]])
    assert torch.allclose(J, want.expand_as(J), rtol=1e-3, atol=1e-9)


# --- pipeline: semantics beside the flow ----------------------------------------------------------


def test_overlapped_inputs_give_the_same_result():
    from monostixels.data.synthetic import render_pair
    from monostixels.pipeline import Pipeline, load_config
    from monostixels.build import pipeline_settings

    pair = render_pair(1, scale=0.25)
    cfg = load_config(["flow=dis", "semantic=gt", "motion=gt"])
    a = Pipeline(pipeline_settings(cfg), overlap=True).run(pair)
    b = Pipeline(pipeline_settings(cfg), overlap=False).run(pair)
    assert torch.equal(a.flow.flow, b.flow.flow) and torch.equal(a.semantic, b.semantic)
    assert torch.equal(a.stixels.type, b.stixels.type) and torch.equal(a.stixels.inverse_depth, b.stixels.inverse_depth)
    assert set(a.seconds) >= {"flow", "semantic", "motion", "solver", "wall"}
    assert a.seconds["wall"] >= a.seconds["flow"] and a.total_seconds <= a.seconds["wall"]


def test_overlapped_semantics_error_reaches_the_caller():
    from monostixels.data.synthetic import render_pair
    from monostixels.pipeline import Pipeline, load_config
    from monostixels.build import pipeline_settings

    pair = render_pair(1, scale=0.25)
    pair.gt.labels = None  # semantic=gt without ground-truth labels: the semantics thread raises
    with pytest.raises(InputError, match="no ground-truth labels"):
        Pipeline(pipeline_settings(load_config(["flow=dis", "semantic=gt", "motion=gt"])), overlap=True).run(pair)


def test_semantics_beside_the_flow_use_one_onnx_thread_and_give_the_same_scores():
    from monostixels.data.synthetic import render_pair
    from monostixels.inputs.semantic import _fcn8s_segmenter, estimate_semantics
    from monostixels.pipeline import load_config

    pair = render_pair(1, scale=0.25)
    cfg = load_config(["semantic=fcn8s"]).semantic
    one = estimate_semantics(pair, cfg, threads=1)
    assert _fcn8s_segmenter(cfg, 1).session.get_session_options().intra_op_num_threads == 1
    assert _fcn8s_segmenter(cfg, 1) is not _fcn8s_segmenter(cfg)
    assert torch.equal(one, estimate_semantics(pair, cfg))


def test_numpy_grey_images_equal_the_torch_formulas():
    import cv2

    from monostixels.inputs.confidence import to_gray
    from monostixels.inputs.flow_backends import gray_u8

    img = torch.rand(3, 41, 67, generator=torch.Generator().manual_seed(6)) * 1.2 - 0.1  # values outside [0, 1] too
    rgb = (img.clamp(0, 1).permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)
    assert np.array_equal(gray_u8(img), cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    ref = (img.float() * torch.tensor([0.299, 0.587, 0.114]).view(3, 1, 1)).sum(0)
    assert torch.equal(to_gray(img), ref) and torch.equal(to_gray(img.double()), ref)


def test_fast_finite_check_raises_the_same_error():
    from monostixels._checks import check_finite_fast

    x = torch.zeros(2, 5, 7)
    check_finite_fast(x, "flow")
    check_finite_fast(torch.zeros(3, 4, dtype=torch.uint8), "image")
    x[1, 2, 3] = float("nan")
    with pytest.raises(InputError, match=r"flow: 1 non-finite values .* first at index \(1, 2, 3\)"):
        check_finite_fast(x, "flow")
    with pytest.raises(InputError, match="non-finite"):
        estimate_flow(FramePair(image=torch.full((3, 20, 30), float("inf")), image_prev=torch.zeros(3, 20, 30),
                                camera=Camera(K=K)), OmegaConf.create({"name": "dis"}))


def test_refined_flow_shares_the_grey_images_with_the_backend():
    # One grey conversion for DeepFlow and the refinement: the same flow as each doing its own.
    import cv2

    from monostixels.inputs.flow_backends import _deepflow, gray_u8
    from monostixels.inputs.flow_config import flow_params

    pair = _shift_pair((3, 1), h=64, w=120)
    cfg = flow_params({"name": "deepflow", "scale": 0.5, "refine": True, "refine_passes": 1})
    got = compute_flow(pair.image, pair.image_prev, cfg)
    f = np.ascontiguousarray(_deepflow(pair.image, pair.image_prev, cfg).permute(1, 2, 0).numpy())
    cv2.VariationalRefinement_create().calc(gray_u8(pair.image), gray_u8(pair.image_prev), f)
    assert torch.equal(got, torch.from_numpy(np.ascontiguousarray(f.transpose(2, 0, 1))))


def test_pipeline_asks_for_one_onnx_thread_only_beside_an_image_flow(monkeypatch):
    from monostixels import pipeline as pipeline_mod
    from monostixels.data.synthetic import render_pair
    from monostixels.pipeline import Pipeline, load_config
    from monostixels.build import pipeline_settings

    asked = []
    real = pipeline_mod.estimate_semantics

    def recording(pair, cfg, *, threads=0):
        asked.append(threads)
        return real(pair, cfg, threads=threads)

    monkeypatch.setattr(pipeline_mod, "estimate_semantics", recording)
    pair = render_pair(1, scale=0.25)
    for flow, overlap in (("dis", True), ("dis", False), ("gt", True)):
        Pipeline(pipeline_settings(load_config([f"flow={flow}", "semantic=gt", "motion=gt"])), overlap=overlap, sfm=False).run(pair)
    assert asked == [1, 0, 0]


# --- flow.bands -----------------------------------------------------------------------------------


def test_bands_stitch_strips_in_place():
    # A "flow" that reads the image content: stitched strips must give back the image exactly,
    # so every strip sits at its own columns and the blend weights add up to 1.
    from monostixels.inputs.flow_backends import _in_bands

    h, w = 20, 301
    a = (np.arange(w, dtype=np.float32)[None, :] * 0.7 + np.arange(h, dtype=np.float32)[:, None]).astype(np.float32)

    def calc(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        return np.stack([p, 2.0 * q], -1)

    for bands in (1, 2, 3):
        out = _in_bands(calc, a, a, bands)
        assert out.shape == (h, w, 2)
        np.testing.assert_allclose(out[..., 0], a, rtol=1e-6)
        np.testing.assert_allclose(out[..., 1], 2.0 * a, rtol=1e-6)


def test_deepflow_in_two_bands_matches_one():
    d = (4, 1)
    pair = _shift_pair(d, h=80, w=200)
    base = {"name": "deepflow", "scale": 1.0, "confidence": "structure_tensor", "refine": False, "fb_consistency": False}
    one = estimate_flow(pair, OmegaConf.create({**base, "bands": 1})).flow
    two = estimate_flow(pair, OmegaConf.create({**base, "bands": 2})).flow
    inner = (slice(None), slice(12, -12), slice(12, -12))
    assert float(two[inner][0].median()) == pytest.approx(-d[0], abs=0.25)
    assert float(two[inner][1].median()) == pytest.approx(-d[1], abs=0.25)
    assert float((two - one)[inner].abs().mean()) < 0.1


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "two"])
def test_bad_flow_bands_names_the_option(bad):
    pair = _shift_pair((2, 1))
    with pytest.raises(InputError, match=r"flow\.bands"):
        estimate_flow(pair, OmegaConf.create({"name": "deepflow", "bands": bad}))


def test_too_many_bands_for_the_image():
    pair = _shift_pair((2, 1))  # 132 px wide: 3 strips of 44 px < 2 * 24 + 16
    with pytest.raises(InputError, match=r"flow\.bands.*too narrow"):
        estimate_flow(pair, OmegaConf.create({"name": "deepflow", "bands": 3}))


# --- ego-motion (monostixels.inputs.motion, monostixels.inputs.ground) -------------------------------------------------------


def test_one_partition_median_equals_numpy():
    # Long arrays are bracketed from a subsample first; the kinds put the middles among ties, between
    # two clusters with no value between them ("split": the bracket misses), on zeros and -0.0, across
    # 60 orders of magnitude, and below zero.
    from monostixels.inputs.ground import _median

    rng = np.random.default_rng(3)
    kinds = ("float32", "ties", "float64", "split", "zeros", "wide", "signed")
    for n in (1, 2, 3, 4, 7, 100, 101, 4095, 4096, 4097, 40000, 40001):
        for kind in kinds:
            x = rng.random(n)
            if kind == "ties":
                x = np.round(x * 5) / 5
            elif kind == "split":  # half near 0.1, half near 0.9: no value between the middles
                x = np.where(np.arange(n) % 2 == 0, 0.1 + 1e-3 * x, 0.9 + 1e-3 * x)
            elif kind == "zeros":
                x = np.where(x < 0.6, 0.0, x)
                x[: n // 4] = -0.0
            elif kind == "wide":
                x = 10.0 ** rng.uniform(-30, 30, n)
            elif kind == "signed":
                x = x - 0.5
            x = x.astype(np.float64 if kind == "float64" else np.float32)
            assert _median(x) == float(np.median(x)), (n, kind)
    assert math.isnan(_median(np.array([1.0, np.nan, 2.0], dtype=np.float32)))


def test_ground_ransac_at_once_equals_the_loop_it_replaced():
    # fit_ground fits and scores its 300 hypotheses at once; the loop below is the algorithm as it was
    # (one lstsq and one score a hypothesis). Same draws, same winner, same fit and inliers, and the
    # generator left where the loop left it, on planes with outliers, a tilt limit and a few pixels.
    from monostixels.inputs.ground import fit_ground, tilt_deg

    def loop(A, b, thr, rng, n_g, max_tilt, hypotheses=300):
        N = len(A) // 2
        best, best_count = None, -1
        for _ in range(hypotheses):
            idx = rng.choice(N, size=2, replace=False)
            rows = np.r_[idx, idx + N]
            m, *_ = np.linalg.lstsq(A[rows], b[rows], rcond=None)
            if tilt_deg(m, n_g) > max_tilt:
                continue
            count = int((np.hypot(A[:N] @ m - b[:N], A[N:] @ m - b[N:]) < thr).sum())
            if count > best_count:
                best, best_count = m, count
        if best is None:
            best, *_ = np.linalg.lstsq(A, b, rcond=None)
        m = best
        for _ in range(3):
            inl = np.hypot(A[:N] @ m - b[:N], A[N:] @ m - b[N:]) < thr
            if inl.sum() < 3:
                break
            rows = np.r_[np.nonzero(inl)[0], np.nonzero(inl)[0] + N]
            m, *_ = np.linalg.lstsq(A[rows], b[rows], rcond=None)
        return m, np.hypot(A[:N] @ m - b[:N], A[N:] @ m - b[N:]) < thr

    g = np.random.default_rng(11)
    n_g = np.array([0.0, 1.0, 0.0])
    for N, outliers, max_tilt in ((60, 0.3, 10.0), (3000, 0.5, 10.0), (400, 0.9, 2.0), (50, 0.0, 180.0)):
        m_true = np.array([0.02, 0.6, -0.01])
        A = g.normal(size=(2 * N, 3))
        b = A @ m_true + g.normal(scale=0.2, size=2 * N)
        bad = g.random(N) < outliers
        b[np.r_[bad, bad]] += g.normal(scale=20.0, size=2 * int(bad.sum()))
        r1, r2 = np.random.default_rng(5), np.random.default_rng(5)
        m1, inl1 = fit_ground(A, b, 0.5, r1, n_g=n_g, max_tilt=max_tilt)
        m2, inl2 = loop(A, b, 0.5, r2, n_g, max_tilt)
        assert np.array_equal(m1, m2) and np.array_equal(inl1, inl2), (N, outliers, max_tilt)
        assert r1.integers(1 << 30) == r2.integers(1 << 30)


def test_max_eigenvalue_test_matches_eigvalsh():
    from monostixels.inputs.epipolar import max_eigenvalue_at_most

    rng = np.random.default_rng(4)
    A = rng.normal(size=(5000, 2, 2)) * rng.choice([0.3, 1.0, 3.0], size=(5000, 1, 1))
    cov = (A @ A.transpose(0, 2, 1) + 0.5 * np.eye(2)).astype(np.float32)
    # On the bound: eigenvalue exactly 4 (isotropic, axis-aligned), and just above / below it.
    edge = np.array([[[4, 0], [0, 4]], [[4, 0], [0, 1]], [[1, 0], [0, 4]], [[4.0001, 0], [0, 1]], [[3.9999, 0], [0, 1]],
                     [[2.5, 1.5], [1.5, 2.5]], [[2.5, 1.5001], [1.5001, 2.5]]], dtype=np.float32)
    cov = np.concatenate([cov, edge])
    lam = torch.linalg.eigvalsh(torch.from_numpy(cov).double()).numpy()[:, -1]
    got = max_eigenvalue_at_most(cov, 4.0)
    assert np.array_equal(got, lam <= 4.0)
    assert got[-7:].tolist() == [True, True, True, False, True, True, False]
    assert 0.2 < got.mean() < 0.8  # both outcomes exercised


def test_grey_equals_the_torch_weighted_sum():
    import cv2

    from monostixels.inputs.ground import _grey

    img = torch.rand(3, 37, 53, generator=torch.Generator().manual_seed(5)) * 1.2 - 0.1  # values outside [0, 1] too
    ref = img.float().clamp(0, 1).mul(torch.tensor([0.299, 0.587, 0.114])[:, None, None]).sum(0).numpy()
    assert np.array_equal(_grey(img), cv2.GaussianBlur(ref, (0, 0), 1.0))


def test_threaded_photometric_search_equals_the_sequential_one(monkeypatch):
    # The search warms its cost cache in a second thread; the result must be the sequential one.
    from monostixels.data.synthetic import render_pair
    from monostixels.inputs import ground as ground_mod
    from monostixels.inputs.flow import FlowResult
    from monostixels.eval.metrics import motion_errors
    from monostixels.inputs.motion import estimate_motion
    from monostixels.inputs.semantic import estimate_semantics

    pair = render_pair(3, scale=0.5)
    sem = estimate_semantics(pair, OmegaConf.create({"name": "gt"}))
    road = pair.gt.labels == 0
    flow = pair.gt.flow.clone()
    flow[:, road] = 20.0 * torch.randn(2, int(road.sum()), generator=torch.Generator().manual_seed(0))
    cov = (0.25 * torch.eye(2)).expand(*pair.size, 2, 2).contiguous()
    fr = FlowResult(flow=flow, cov=cov, seconds=0.0, backend="corrupted")
    cfg = OmegaConf.create({"name": "mono"})
    est = {}
    for workers in (1, 2, 3):
        monkeypatch.setattr(ground_mod, "_photometric_workers", lambda w=workers: w)
        est[workers] = estimate_motion(pair, fr, cfg, semantic=sem)
    assert "photometric" in est[1].reason
    assert motion_errors(est[1].motion, pair.motion)["scale_rel_err"] < 0.02
    for workers in (2, 3):
        assert est[workers].reason == est[1].reason
        assert torch.equal(est[workers].motion.t, est[1].motion.t) and torch.equal(est[workers].motion.R, est[1].motion.R)
        assert torch.equal(est[workers].ground_normal, est[1].ground_normal)


@pytest.mark.parametrize("seed", range(3))
def test_depth_map_equals_the_ray_plane_formula(seed):
    """StixelWorld.depth_map (the dot product written out per component) is bit for bit the (H, W, 3)
    ray-plane formula, with skew, a tilted ground normal, sky and uncovered pixels."""
    from monostixels.core.classes import SKY
    from monostixels.core.geometry import object_normals

    st, _ = _random_scene(seed)
    n_g = torch.tensor([0.02, 0.995, -0.05], dtype=torch.float64)
    Ks = K.clone()
    Ks[0, 1] = 0.7  # skew
    types = st.type.clone()
    types[::7] = SKY
    keep = torch.arange(len(types)) % 11 != 3  # some pixels without a stixel
    st = StixelWorld(**{**st.__dict__, "K": Ks, "ground_normal": n_g / n_g.norm(), "type": types})
    st = StixelWorld(**{**st.__dict__, **{k: getattr(st, k)[keep] for k in ("column", "v_top", "v_bottom", "type", "cls",
                                                                          "inverse_depth", "motion", "cost", "tau")}})
    idx = st.index_map()
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    ray = pixel_rays(Ks.double(), u, v)
    ng = st.ground_normal.double()
    safe = idx.clamp(min=0)
    typ, p = st.type[safe], st.inverse_depth.double()[safe]
    n = torch.where((typ == 0)[..., None], ng.expand(H, W, 3), object_normals(Ks.double(), ng, u[0])[None].expand(H, W, 3))
    ref = 1.0 / (p * (ray * n).sum(-1))
    ref = torch.where(typ == SKY, torch.full_like(ref, math.inf), ref)
    ref = torch.where(idx < 0, torch.full_like(ref, math.nan), ref).float()
    got = st.depth_map()
    assert bool((idx < 0).any()) and bool((typ == SKY).any())
    assert torch.equal(torch.nan_to_num(got, nan=-1.0), torch.nan_to_num(ref, nan=-1.0))


def test_the_speed_benchmark_times_a_video_clip_at_its_working_size(tmp_path):
    # benchmarks/pipeline_speed.py --video: the clip's frames through the sequence layer as `run` builds it.
    import time

    from benchmarks.pipeline_speed import time_preset, video_source
    from tests._clips import FAST, write_video_clip

    clip = tmp_path / "clip.mp4"
    intr = write_video_clip(clip)
    frames, cfg, overrides, size, running = time_preset(
        "fast", video_source(str(clip), 3, [f"data.intrinsics={intr}", "data.resize=null"]), FAST, 1, False,
        time.perf_counter)
    assert set(running) == {"torch", "opencv"} and min(running.values()) >= 1
    assert str(cfg.data.name) == "video" and "preset=fast" in overrides
    assert len(frames) == 2  # 3 pairs, 1 of them the warm-up
    assert size == [94, 310]
    assert all(f["total"] > 0 and f["total"] >= f["depth_map"] for f in frames)
