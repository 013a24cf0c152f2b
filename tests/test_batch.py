"""`monostixels batch`: clips on 2 local Ray workers into a Parquet dataset, checked against `run`'s JSON."""
from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import tempfile
from pathlib import Path

import numpy as np
import pytest

from monostixels._checks import InputError
from monostixels.batch import Clip, clip_data_config, discover_clips
from tests._clips import FAST, FPS, cli, hide_module, write_frames_clip, write_video_clip

#: Columns compared with stixels.json, in its names.
_JSON_KEYS = ("column", "v_top", "v_bottom", "type", "class", "inverse_depth", "depth")
DOC = Path(__file__).resolve().parents[1] / "docs" / "batch_and_viewer.md"


def doc_python_blocks(needle: str) -> list[str]:
    """The ```python blocks of docs/batch_and_viewer.md that contain ``needle``."""
    return [b for b in re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S) if needle in b]


@pytest.fixture
def ray_tmp():
    """A Ray temp folder of this test alone (short: Ray's socket paths must stay under 108 bytes).

    On teardown, any process still running from it (a Ray node whose driver was killed by a time-out)
    is ended by its id, and the folder removed.
    """
    d = tempfile.mkdtemp(prefix="msray", dir="/tmp")
    yield d
    for pid in (p for p in os.listdir("/proc") if p.isdigit()):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
        except OSError:
            continue
        if d in cmd and int(pid) != os.getpid():
            try:
                os.kill(int(pid), signal.SIGKILL)
            except OSError:
                pass
    shutil.rmtree(d, ignore_errors=True)


def _json_rows(run_out: Path) -> list[tuple]:
    """(frame, frame name, column, v_top, v_bottom, type, class, inverse depth, depth, motion) of `run`'s JSON."""
    rows = []
    dirs = sorted(d for d in (run_out / "run").iterdir() if d.is_dir())
    for i, d in enumerate(dirs):
        for s in json.loads((d / "stixels.json").read_text())["stixels"]:
            rows.append((i, d.name, *(s[k] for k in _JSON_KEYS), *s["motion"]))
    return rows


def _parquet_rows(table, clip: str) -> list[tuple]:
    import pyarrow.compute as pc

    t = table.filter(pc.equal(table["clip"], clip)).to_pydict()
    keys = ("frame", "frame_name", *_JSON_KEYS, "motion_x", "motion_y", "motion_z")
    return list(zip(*(t[k] for k in keys)))


def _same(a: list[tuple], b: list[tuple]) -> bool:
    """Rows equal: ints and names exactly, floats to 1e-9 relative (None = null / JSON null)."""
    if len(a) != len(b):
        return False
    for ra, rb in zip(a, b):
        for x, y in zip(ra, rb):
            if isinstance(x, float) or isinstance(y, float):
                if x is None or y is None or not math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-12):
                    return False
            elif x != y:
                return False
    return True


def test_batch_on_ray_equals_run_and_resumes(tmp_path, ray_tmp):
    import pyarrow.dataset as ds

    clips = tmp_path / "clips"
    clips.mkdir()
    intr_a = write_video_clip(clips / "a.mp4", seed=3)  # a video with its intrinsics beside it
    write_frames_clip(clips / "b", seed=5)  # a folder of frames with intrinsics.yaml
    (clips / "corrupt.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + os.urandom(4000))
    out = tmp_path / "fleet"
    args = ["batch", f"batch.inputs={clips}", f"batch.output={out}", "batch.num_cpus=2", *FAST]
    env = {"RAY_TMPDIR": ray_tmp}
    p = cli(args, tmp_path, env=env, check=False)
    # The corrupt clip is reported (exit status 1, stderr, summary) while the others are written.
    assert p.returncode == 1, p.stderr
    assert "failed: corrupt" in p.stderr and "cannot decode" in p.stderr
    assert "Traceback" not in p.stderr
    summary = json.loads((out / "summary.json").read_text())["clips"]
    assert set(summary) == {"a", "b", "corrupt"}
    assert summary["corrupt"]["status"] == "failed" and "cannot decode" in summary["corrupt"]["error"]
    assert summary["corrupt"]["frames"] == 0
    for name in ("a", "b"):
        assert summary[name]["status"] == "ok" and summary[name]["error"] is None
        assert summary[name]["frames"] == 3 and summary[name]["seconds"] > 0
    parts = sorted(p.name for p in (out / "stixels.parquet").iterdir())
    assert parts == ["clip=a", "clip=b"]

    # The same clips through `monostixels run`: its JSON is what the dataset must hold, row for row.
    cli(["run", "data=video", f"data.path={clips / 'a.mp4'}", f"data.intrinsics={intr_a}", *FAST,
         f"outputs={tmp_path / 'run_a'}"], tmp_path)
    cli(["run", "data=frames", f"data.root={clips / 'b'}", *FAST, f"outputs={tmp_path / 'run_b'}"], tmp_path)
    table = ds.dataset(out / "stixels.parquet", partitioning="hive").to_table()
    for name in ("a", "b"):
        want, got = _json_rows(tmp_path / f"run_{name}"), _parquet_rows(table, name)
        assert len(got) == summary[name]["rows"] and len(want) > 100
        assert _same(got, want), f"clip {name}: Parquet rows differ from run's stixels.json"
    t = table.to_pydict()
    clip = np.array(t["clip"])
    # Frame times: video frame k at 10 fps; none for a folder of images.
    frame_a = np.array(t["frame"])[clip == "a"]
    assert np.allclose(np.array(t["timestamp"], dtype=float)[clip == "a"], (frame_a + 1) / FPS)
    assert np.allclose(np.array(t["dt"], dtype=float)[clip == "a"], 1 / FPS)
    assert all(v is None for v, c in zip(t["timestamp"], t["clip"]) if c == "b")
    # The sequence layer's fields, as in run's JSON (track -1 / TTC null there: null / inf here).
    for name in ("a", "b"):
        rows = [s for d in sorted(x for x in (tmp_path / f"run_{name}" / "run").iterdir() if x.is_dir())
                for s in json.loads((d / "stixels.json").read_text())["stixels"]]
        sel = clip == name
        track = [-1 if v is None else v for v in np.array(t["track_id"], dtype=object)[sel]]
        assert track == [s["track_id"] for s in rows]
        ttc = np.array(t["ttc_s"], dtype=float)[sel]
        want = np.array([math.inf if s["ttc_s"] is None else s["ttc_s"] for s in rows])
        assert np.array_equal(np.isinf(ttc), np.isinf(want)) and np.allclose(ttc[~np.isinf(ttc)], want[~np.isinf(want)])
        assert np.allclose(np.array(t["velocity_x"], dtype=float)[sel], [s["velocity"][0] for s in rows])
    # World positions: the cameras stay at one height over a flat road, so the road is at y = +1.65 m
    # (the camera height; y down) in the world frame too.
    ground = (np.array(t["type"]) == "ground") & np.array([y is not None for y in t["y"]])
    assert abs(np.median(np.array(t["y"], dtype=object)[ground].astype(float)) - 1.65) < 0.15

    _check_doc_queries(tmp_path, t)

    # A second run: nothing new to do; nothing rewritten; the failure still reported.
    mtimes = {f: f.stat().st_mtime_ns for f in (out / "stixels.parquet").rglob("*.parquet")}
    p2 = cli(args, tmp_path, env=env, check=False)
    assert p2.returncode == 1 and "0 run now, 3 done before" in p2.stdout and "failed: corrupt" in p2.stderr
    assert {f: f.stat().st_mtime_ns for f in (out / "stixels.parquet").rglob("*.parquet")} == mtimes
    assert json.loads((out / "summary.json").read_text())["clips"] == summary
    # Other settings into the same folder: refused, not mixed into the dataset.
    p3 = cli([*args, "prior.beta_mc=3.0"], tmp_path, env=env, check=False)
    assert p3.returncode == 1 and "other settings" in p3.stderr


def _check_doc_queries(cwd: Path, t: dict[str, list]) -> None:
    """The docs' DuckDB and pyarrow examples, run on the dataset in ``cwd/fleet``, against numpy."""
    blocks = doc_python_blocks("fleet/stixels.parquet")
    assert len(blocks) == 2
    ns: dict = {}
    old = os.getcwd()
    os.chdir(cwd)
    try:
        for b in blocks:
            exec(compile(b, str(DOC), "exec"), ns)  # noqa: S102 — our own documentation's code
    finally:
        os.chdir(old)
    typ, depth = np.array(t["type"]), np.array(t["depth"], dtype=object)
    key = list(zip(t["clip"], t["frame"]))
    want: dict[tuple, float] = {}
    for k, ty, d in zip(key, typ, depth):
        if ty in ("static_object", "dynamic_object") and d is not None:
            want[k] = min(want.get(k, math.inf), d)
    assert [(c, f) for c, f, _, _ in ns["nearest"]] == sorted(want)
    assert all(m == want[(c, f)] for c, f, m, _ in ns["nearest"])
    pa_rows = ns["nearest_pa"].to_pydict()
    assert dict(zip(zip(pa_rows["clip"], pa_rows["frame"]), pa_rows["depth_min"])) == want
    # Movers faster than 5 m/s: the tracks' velocity where there is one, else |motion| / dt where the
    # interval is known.
    speed = [math.hypot(vx, vy, vz) if vx is not None else (math.hypot(x, y, z) / dt if dt else None)
             for vx, vy, vz, x, y, z, dt in zip(t["velocity_x"], t["velocity_y"], t["velocity_z"], t["motion_x"],
                                                t["motion_y"], t["motion_z"], t["dt"])]
    fast = sorted((c, f, col) for c, f, col, ty, v in zip(t["clip"], t["frame"], t["column"], typ, speed)
                  if ty == "dynamic_object" and v is not None and v > 5)
    assert sorted((c, f, col) for c, f, col, *_ in ns["fast"]) == fast


def test_docs_list_every_column():
    from monostixels.batch import SCHEMA_FIELDS

    table = DOC.read_text().split("**Columns**", 1)[1].split("###", 1)[0]
    for name, _, _ in SCHEMA_FIELDS:
        assert f"`{name}`" in table, name


def test_discover_clips_and_their_data_config(tmp_path):
    (tmp_path / "fleet" / "car1").mkdir(parents=True)
    (tmp_path / "fleet" / "car2").mkdir()
    for car in ("car1", "car2"):
        (tmp_path / "fleet" / car / "front.mp4").write_bytes(b"")
    (tmp_path / "fleet" / "car1" / "front.intrinsics.yaml").write_text("fx: 1\nfy: 1\ncx: 0\ncy: 0\n")
    (tmp_path / "fleet" / "notes.txt").write_text("")
    frames = tmp_path / "fleet" / "drive7"
    frames.mkdir()
    (frames / "0000.png").write_bytes(b"")
    (frames / "intrinsics.yaml").write_text("fx: 1\nfy: 1\ncx: 0\ncy: 0\n")
    # A glob: colliding stems are told apart by their folders.
    clips = discover_clips(str(tmp_path / "fleet" / "*" / "front.mp4"), [".mp4"])
    assert [(c.name, c.kind) for c in clips] == [("car1_front", "video"), ("car2_front", "video")]
    # A folder of clips: its videos (none directly here) and its folders of images; not the output.
    clips = discover_clips(str(tmp_path / "fleet"), [".mp4"], exclude=tmp_path / "fleet" / "car1")
    assert [(c.name, c.kind) for c in clips] == [("drive7", "frames")]
    # A folder of images is itself one clip.
    assert [c.name for c in discover_clips(str(frames))] == ["drive7"]
    with pytest.raises(InputError, match="batch.inputs"):
        discover_clips(str(tmp_path / "nothing_*.mp4"))
    with pytest.raises(InputError, match="batch.inputs: not set"):
        discover_clips(None)
    # data.* options apply to every clip; intrinsics beside a video win over data.hfov_deg.
    user = {"name": "video", "path": "ignored.mp4", "hfov_deg": 90.0, "step": 2, "resize": 0.5, "intrinsics": None}
    car1 = clip_data_config(user, Clip("car1_front", str(tmp_path / "fleet" / "car1" / "front.mp4"), "video"))
    assert car1["path"].endswith("car1/front.mp4") and car1["step"] == 2 and car1["resize"] == 0.5
    assert car1["intrinsics"].endswith("front.intrinsics.yaml")
    car2 = clip_data_config(user, Clip("car2_front", str(tmp_path / "fleet" / "car2" / "front.mp4"), "video"))
    assert car2["intrinsics"] is None and car2["hfov_deg"] == 90.0
    drive = clip_data_config(user, Clip("drive7", str(frames), "frames"))
    assert drive["name"] == "frames" and drive["root"] == str(frames) and drive["step"] == 2
    # A folder takes them too (data=frames has hfov_deg and resize); its own intrinsics file wins over hfov_deg.
    assert drive["hfov_deg"] == 90.0 and drive["resize"] == 0.5 and drive["intrinsics"] is None
    with pytest.raises(InputError, match="data=synthetic"):
        clip_data_config({"name": "synthetic"}, clips[0])


def test_batch_without_its_extra_names_it(monkeypatch):
    from monostixels.batch import run_batch
    from monostixels.pipeline import load_config

    hide_module(monkeypatch, "ray")
    with pytest.raises(InputError, match=r'pip install -e "\.\[batch\]"'):
        run_batch(load_config(["batch.inputs=nowhere"]))


def test_batch_needs_inputs(tmp_path):
    p = cli(["batch", *FAST], tmp_path, check=False)
    assert p.returncode == 1 and "batch.inputs: not set" in p.stderr and "Traceback" not in p.stderr
