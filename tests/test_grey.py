"""Grey images (monostixels/core/grey.py): kornia's 8-bit conversions give OpenCV's values for every colour,
and the flow colour map (torchvision's flow_to_image) keeps its scale."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from monostixels._checks import InputError
from monostixels.core.grey import to_gray, to_gray_u8


def _every_colour() -> np.ndarray:
    """(4096, 4096, 3) uint8: each of the 2^24 colours once."""
    v = np.arange(256, dtype=np.uint8)
    r, g, b = np.meshgrid(v, v, v, indexing="ij")
    return np.stack([r.ravel(), g.ravel(), b.ravel()], -1).reshape(4096, 4096, 3)


def test_8bit_grey_is_opencvs_for_every_colour():
    img = _every_colour()
    chw = img.transpose(2, 0, 1)
    assert np.array_equal(to_gray_u8(chw), cv2.cvtColor(img, cv2.COLOR_RGB2GRAY))
    assert np.array_equal(to_gray_u8(chw, order="bgr"), cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))


def test_8bit_grey_refuses_what_it_cannot_convert():
    with pytest.raises(InputError, match="uint8"):
        to_gray_u8(np.zeros((3, 4, 4), dtype=np.float32))
    with pytest.raises(InputError, match="order"):
        to_gray_u8(np.zeros((3, 4, 4), dtype=np.uint8), order="rbg")
    with pytest.raises(InputError, match="image"):
        to_gray_u8(np.zeros((4, 4, 3), dtype=np.uint8))


def test_float_grey_is_the_weighted_channel_sum():
    x = torch.rand(3, 7, 9, generator=torch.Generator().manual_seed(0))
    w = np.asarray((0.299, 0.587, 0.114), dtype=np.float32)
    want = x[0].numpy() * w[0] + x[1].numpy() * w[1] + x[2].numpy() * w[2]
    assert np.array_equal(to_gray(x).numpy(), want)
    assert np.array_equal(to_gray(x.requires_grad_()).detach().numpy(), want)  # torch's path: the same float32s


def test_flow_colours_saturate_at_max_flow():
    from monostixels.output.viz import flow_colormap

    # Right at half, full and twice max_flow: half is paler, twice is clipped to full.
    fu = torch.tensor([[2.0, 4.0, 8.0]])
    rgb = flow_colormap(torch.stack([fu, torch.zeros_like(fu)]), max_flow=4.0).astype(int)
    half, full, twice = rgb[0]
    assert tuple(full) == tuple(twice) == (255, 0, 0)
    assert half[0] == 255 and 120 <= half[1] <= 130 and 120 <= half[2] <= 130
    # By default the largest magnitude saturates.
    assert tuple(flow_colormap(torch.stack([fu, torch.zeros_like(fu)]))[0, 2]) == (255, 0, 0)
