"""The writer interface (monostixels/output/writers.py): `run` and `batch` hand every frame to their writers
through one loop; each writer sees every frame once, in order, and is closed once, also on an error."""
from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import pytest

from monostixels._checks import InputError
from monostixels.output.writers import Frame, RunSummary, StixelRows, Writer, write_sequence
from tests._clips import FAST, write_frames_clip


class _Log(Writer):
    """Records what the loop hands it; ``fail_at``: the frame index whose write raises, ``fail_close``:
    its close raises."""

    def __init__(self, fail_at: int | None = None, fail_close: bool = False) -> None:
        self.frames: list[int] = []
        self.closed: list[BaseException | None] = []
        self.fail_at, self.fail_close = fail_at, fail_close

    def write(self, frame: Frame) -> None:
        if frame.index == self.fail_at:
            raise RuntimeError(f"write of frame {frame.index} failed")
        self.frames.append(frame.index)

    def close(self, error: BaseException | None = None) -> None:
        self.closed.append(error)
        if self.fail_close:
            raise OSError("close failed")


def _steps(n: int, fail_after: int | None = None):
    for i in range(n):
        if i == fail_after:
            raise InputError(f"frame {i}: unreadable")
        yield SimpleNamespace(pair=f"pair{i}", result=f"result{i}")


def test_every_writer_gets_every_frame_once_and_is_closed_once():
    a, b = _Log(), _Log()
    assert write_sequence(_steps(4), [a, b]) == 4
    assert a.frames == b.frames == [0, 1, 2, 3]
    assert a.closed == b.closed == [None]


def test_writers_are_closed_once_with_the_error_that_stopped_the_sequence():
    # The source fails part-way: the frames before it were written, every writer closed once with the error.
    a, b = _Log(), _Log()
    with pytest.raises(InputError, match="frame 2: unreadable"):
        write_sequence(_steps(4, fail_after=2), [a, b])
    assert a.frames == b.frames == [0, 1]
    assert len(a.closed) == len(b.closed) == 1 and isinstance(a.closed[0], InputError) and b.closed[0] is a.closed[0]
    # A writer fails: the writers after it did not get that frame; all are closed once with its error.
    a, bad, c = _Log(), _Log(fail_at=1), _Log()
    with pytest.raises(RuntimeError, match="write of frame 1 failed"):
        write_sequence(_steps(3), [a, bad, c])
    assert a.frames == [0, 1] and bad.frames == [0] and c.frames == [0]
    assert all(len(w.closed) == 1 and isinstance(w.closed[0], RuntimeError) for w in (a, bad, c))


def test_a_failing_close_does_not_keep_the_others_open():
    a, bad, c = _Log(), _Log(fail_close=True), _Log()
    with pytest.raises(OSError, match="close failed"):
        write_sequence(_steps(2), [a, bad, c])
    assert a.closed == bad.closed == c.closed == [None]
    # On an error already raised, the sequence's error is the one that comes out.
    a, bad = _Log(), _Log(fail_close=True)
    with pytest.raises(InputError):
        write_sequence(_steps(3, fail_after=1), [a, bad])
    assert len(a.closed) == len(bad.closed) == 1


def test_the_summary_is_not_written_after_an_error(tmp_path):
    src = SimpleNamespace(skipped_frames=[], restarts=[])
    summary = RunSummary(tmp_path, src, "frames", 1.65)
    summary.close(RuntimeError("stopped"))
    assert not (tmp_path / "summary.json").exists() and summary.lines == []
    # No pair made while frames were skipped: one clear error, and no summary.
    src = SimpleNamespace(skipped_frames=["0001.png"], restarts=[])
    with pytest.raises(InputError, match="no frame pair could be made: 1 unreadable"):
        RunSummary(tmp_path, src, "frames", 1.65).close()
    assert not (tmp_path / "summary.json").exists()


def test_run_and_batch_write_the_same_stixels(tmp_path, capsys):
    """`run` (its per-frame stixels.json) and `batch`'s clip (its rows, without Ray) on one small clip."""
    from omegaconf import OmegaConf

    from monostixels import cli
    from monostixels.batch import Clip, process_clip
    from monostixels.pipeline import load_config

    clip = write_frames_clip(tmp_path / "clip", seed=5)
    run_cfg = load_config([*cli.command_overrides("run", ["data=frames", f"data.root={clip}", *FAST]),
                           f"outputs={tmp_path / 'out'}", "command=run"])
    cli._run(run_cfg)
    assert "run: 3 frame pair(s)" in capsys.readouterr().out
    run_dir = tmp_path / "out" / "run"
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["frame_pairs"] == 3 and summary["camera"]["pairs"] == 3

    batch_cfg = load_config([*cli.command_overrides("batch", [*FAST]), "command=batch"])
    entry, table = process_clip(OmegaConf.to_container(batch_cfg, resolve=True), Clip("clip", str(clip), "frames"))
    assert entry["status"] == "ok" and entry["frames"] == 3, entry
    rows = table.to_pydict()
    frames = sorted(d for d in run_dir.iterdir() if d.is_dir())
    assert [d.name for d in frames] == sorted(set(rows["frame_name"]))
    k = 0
    for i, d in enumerate(frames):
        for s in json.loads((d / "stixels.json").read_text())["stixels"]:
            assert (rows["frame"][k], rows["frame_name"][k]) == (i, d.name)
            for key in ("column", "v_top", "v_bottom", "type", "class", "track_id"):
                got = rows[key][k]
                assert (-1 if key == "track_id" and got is None else got) == s[key], (d.name, key)
            for key in ("inverse_depth", "depth"):
                assert (rows[key][k] is None and s[key] is None) or math.isclose(rows[key][k], s[key], rel_tol=1e-9)
            assert [rows[f"motion_{c}"][k] for c in "xyz"] == pytest.approx(s["motion"], rel=1e-9, abs=1e-12)
            k += 1
    assert k == len(rows["frame"]) == entry["rows"] > 100


def test_stixel_rows_hold_nothing_after_an_error():
    rows = StixelRows(fps=None)
    rows.close(RuntimeError("stopped"))
    assert rows.table is None and rows.frames == 0


def test_run_writes_its_files_through_the_writers(tmp_path):
    """The writers of `run` on one synthetic pair: each frame's files, named as docs/conventions.md 4.3 says."""
    from monostixels.data.synthetic import SyntheticSource
    from monostixels.build import build_writers
    from monostixels.output.writers import FrameFiles
    from monostixels.pipeline import Pipeline, load_config
    from monostixels.build import pipeline_settings, sequence_settings
    from monostixels.sequence import SequenceRunner
    from monostixels.build import pipeline_settings, sequence_settings

    cfg = load_config(["data.scale=0.25", "flow=gt", "semantic=gt", "motion=gt", f"outputs={tmp_path}"])
    src = SyntheticSource(2, seed=0, scale=0.25)
    writers = build_writers(cfg, src, Path(cfg.outputs) / "run")
    assert writers.videos is not None  # two pairs: a sequence
    runner = SequenceRunner(sequence_settings(cfg), Pipeline(pipeline_settings(cfg), allow_motion_failure=True, sfm=False, report_height=True))
    assert write_sequence(runner.run(src), writers.all) == 2
    run = tmp_path / "run"
    for i in range(2):
        d = run / src[i].name
        assert sorted(p.name for p in d.iterdir()) == sorted(FrameFiles.NAMES)
        assert len(json.loads((d / "stixels.json").read_text())["stixels"]) > 0
    assert (run / "video.mp4").stat().st_size > 0 and (run / "bev.mp4").stat().st_size > 0
    assert json.loads((run / "summary.json").read_text())["frame_pairs"] == 2
    lines = writers.report(2)
    assert lines[-1].startswith("run: 2 frame pair(s)") and "videos" in lines[-1]
