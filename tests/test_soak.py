"""A short soak (benchmarks/soak.py): 300 frames of a street played forward and back through the
sequence layer of ``monostixels run``; tracks are born and die, and nothing that lives from frame to
frame grows with the frame count."""
from __future__ import annotations

import numpy as np
import pytest

from omegaconf import OmegaConf

from benchmarks.soak import pingpong_index, run_soak, soak_config, write_pingpong_clip
from monostixels.sequence.stream import _HISTORY_FRAMES

#: Frame pairs of the short soak; scene frames one way (a period of 2 * LENGTH = 40 frames, so each
#: third of the soak holds 2.5 periods); image size over KITTI's (75x248: still tracks to make).
FRAMES, LENGTH, SCALE = 300, 20, 0.2
#: The fast preset's choices but for the semantic net (none here: the cheapest real inputs).
LIGHT = ["semantic=none"]


def test_pingpong_plays_forward_and_back_without_a_jump():
    frames = [pingpong_index(n, 3) for n in range(10)]
    assert frames == [0, 1, 2, 3, 2, 1, 0, 1, 2, 3]
    assert all(abs(a - b) == 1 for a, b in zip(frames, frames[1:]))  # every step one scene frame: no jump


@pytest.fixture(scope="module")
def soak(tmp_path_factory):
    folder = tmp_path_factory.mktemp("soak")
    video, intr = write_pingpong_clip(folder, FRAMES, scale=SCALE, length=LENGTH)
    cfg = soak_config(video, intr, sets=LIGHT)
    return cfg, run_soak(cfg, progress=False)


def test_soak_tracks_are_born_die_and_stay_bounded(soak):
    cfg, rec = soak
    n = len(rec.tracks)
    assert n == FRAMES and rec.failed == 0
    live = np.asarray(rec.tracks)
    # Born and removed all along: more ids were given than are alive, and the count falls at times.
    assert rec.tracks_born > live[-1] > 0
    assert (np.diff(live) < 0).sum() > n // 10
    # A track unseen for more than max_age_frames is dropped, so no more can be alive than the
    # stixels of that many frames (+ the current one) of this scene.
    max_age = OmegaConf.to_object(cfg.temporal).max_age_frames
    assert live[2 * n // 3:].max() <= (max_age + 1) * max(rec.stixels)
    # No growth trend: the last third holds no more tracks on average than the middle third (each
    # covers whole periods of the forward-and-back drive but half a one), with a margin for that half.
    assert live[2 * n // 3:].mean() <= 1.25 * live[n // 3: 2 * n // 3].mean()


def test_soak_buffers_stay_bounded(soak):
    cfg, rec = soak
    window = OmegaConf.to_object(cfg.keyframes).window
    sizes = {k: max(b[k] for b in rec.buffers) for k in rec.buffers[0]}
    # The sequence layer's frames (poses) and the source's decoded frames: the keyframe window and the
    # current frame; the stream's kept frames: its history or the chain window.
    assert sizes["sequence_frames"] <= window + 1
    assert sizes["source_frames"] <= window + 1
    assert sizes["stream_frames"] <= max(_HISTORY_FRAMES, window + 1)
    assert sizes["stream_chain_steps"] <= sizes["stream_frames"]
    # And no larger late than early: the second half's largest sizes are reached in the first half.
    half = len(rec.buffers) // 2
    for k in sizes:
        if k != "tracks":
            assert max(b[k] for b in rec.buffers[half:]) <= max(b[k] for b in rec.buffers[:half]), k
