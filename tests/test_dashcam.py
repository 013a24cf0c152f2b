"""The shared dashcam clip (a US interstate at ~25 m/s, unknown camera): what each pair's flags say about
its camera motion, and the outputs that follow from them. Skips without ``../shared/data/dashcam``."""
from __future__ import annotations

from pathlib import Path

import pytest

CLIP = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "dashcam" / "highway_solid_white_right.mp4"

pytestmark = pytest.mark.skipif(not CLIP.is_file(), reason=f"the shared dashcam clip is not at {CLIP}")


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
            assert row["scale_from"] in ("photometric", "road_marks", "ground_flow", "sequence")
    # The lane dashes fix the scale at highway speed (the flow of the near road does not): every pair metric,
    # at a steady speed near the dashes' yardstick (12.19 m per 12 frames at 25 fps, ~25 m/s; camera.height
    # is a guess, so the band is a highway's).
    assert rep["no_metric_share"] == 0.0
    assert 15.0 <= rep["speed_mean_mps"] <= 40.0 and rep["speed_cv"] <= 0.15
    assert sum(row["scale_from"] == "road_marks" for row in rep["per_pair"]) >= 4
    assert rep["ttc_warnings"] == 0
