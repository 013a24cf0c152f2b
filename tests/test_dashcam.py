"""The shared dashcam clip (a US interstate at ~25 m/s, unknown camera): what each pair's flags say about
its camera motion, and the outputs that follow from them (skips without ``../shared/data/dashcam``); and how
the benchmark counts false movers."""
from __future__ import annotations

from pathlib import Path

import pytest

CLIP = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "dashcam" / "highway_solid_white_right.mp4"

needs_clip = pytest.mark.skipif(not CLIP.is_file(), reason=f"the shared dashcam clip is not at {CLIP}")


@needs_clip
def test_the_dashcam_clips_flags_poses_and_warnings_agree_with_what_the_camera_motion_knew():
    from benchmarks.dashcam import measure

    rep = measure([f"data.path={CLIP}", "data.hfov_deg=58", "data.step=2", "data.frames=6", "camera.height=1.4",
                   "flow=dis"])
    assert rep["pairs"] == 6
    # degenerate_motion is true exactly for the pairs without a metric motion (a highway has no standing camera).
    assert rep["degenerate_consistent"]
    for row in rep["per_pair"]:
        known = row["camera_motion"] == "metric"
        assert (row["speed_mps"] is not None) == known
        if not known:
            assert row["ttc_warnings"] == 0  # nothing is called moving, nothing closes
        else:
            assert row["scale_from"] in ("photometric", "road_marks", "ground_flow", "scene", "sequence")
    # The lane dashes fix the scale at highway speed (the flow of the near road does not): every pair metric,
    # at a steady speed near the dashes' yardstick (12.19 m per 12 frames at 25 fps, ~25 m/s; camera.height
    # is a guess, so the band is a highway's).
    assert rep["no_metric_share"] == 0.0
    assert 15.0 <= rep["speed_mean_mps"] <= 40.0 and rep["speed_cv"] <= 0.15
    assert sum(row["scale_from"] == "road_marks" for row in rep["per_pair"]) >= 4
    assert rep["ttc_warnings"] == 0


def test_false_movers_count_moving_pixels_away_from_the_referees_movers_by_tenth_of_the_rows():
    import cv2
    import numpy as np

    from benchmarks.dashcam import false_movers

    moving = np.zeros((20, 10), bool)
    moving[0:2, 0:3] = True     # 6 px in the top tenth, far from any mover
    moving[18:20, 5:10] = True  # 10 px in the bottom tenth, far from any mover
    moving[8:12, 0:2] = True    # 8 px on the referee's car: not false
    referee = np.zeros((20, 10), np.int64)
    referee[8:12, 0:2] = 6      # vehicle
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))  # dilates the car by 1 px: still off the rest
    share, rows = false_movers(moving, referee, kernel)
    assert share == pytest.approx(16 / 200)
    assert rows[0] == pytest.approx(6 / 200) and rows[9] == pytest.approx(10 / 200)
    assert sum(rows[1:9]) == 0 and sum(rows) == pytest.approx(share)
