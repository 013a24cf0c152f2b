"""The process's thread budget (config key ``threads``, monostixels._threads): torch, OpenCV, ONNX Runtime."""
from __future__ import annotations

import os

import cv2
import pytest
import torch

from monostixels import _threads
from monostixels._checks import InputError
from monostixels._threads import available_cores, onnx_session_options, resolve_threads, set_threads, thread_counts


@pytest.fixture
def restore_threads():
    """Put torch's, OpenCV's and the module's thread counts back after a test changes them."""
    before = (torch.get_num_threads(), cv2.getNumThreads(), _threads._applied)
    yield
    torch.set_num_threads(before[0])
    cv2.setNumThreads(before[1])
    _threads._applied = before[2]


def test_auto_is_the_cores_this_process_may_use(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    quota = _threads.cgroup_cpu_limit()
    assert available_cores() == min(len(os.sched_getaffinity(0)), quota or 10**6)
    for auto in ("auto", "AUTO", None, 0):
        assert resolve_threads(auto) == available_cores()
    assert resolve_threads(3) == 3 and resolve_threads("2") == 2


def test_auto_honours_a_lower_omp_num_threads(monkeypatch):
    # A Ray worker given one CPU (or a user's own limit) sets OMP_NUM_THREADS: auto keeps to it.
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert resolve_threads("auto") == 1
    monkeypatch.setenv("OMP_NUM_THREADS", str(10**4))
    assert resolve_threads("auto") == available_cores()
    assert resolve_threads(2) == 2  # an explicit count wins


def test_a_container_quota_limits_auto(tmp_path, monkeypatch):
    # cgroup v2: "quota period" in microseconds; 1.5 CPUs of quota -> 2 threads; "max" = no quota.
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert _threads.cgroup_cpu_limit(tmp_path) == 2
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert _threads.cgroup_cpu_limit(tmp_path) is None
    # cgroup v1: quota -1 = none.
    v1 = tmp_path / "v1"
    (v1 / "cpu").mkdir(parents=True)
    (v1 / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
    assert _threads.cgroup_cpu_limit(v1) is None
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("100000\n")
    assert _threads.cgroup_cpu_limit(v1) == 1
    monkeypatch.setattr(_threads, "cgroup_cpu_limit", lambda: 1)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert available_cores() == 1 and resolve_threads("auto") == 1


@pytest.mark.parametrize("bad", [-1, 1.5, "many", True])
def test_bad_threads_names_the_option(bad):
    with pytest.raises(InputError, match="threads"):
        resolve_threads(bad)


def test_set_threads_reaches_torch_opencv_and_new_onnx_sessions(restore_threads):
    assert set_threads(1) == 1
    assert thread_counts() == {"torch": 1, "opencv": 1, "onnxruntime": 1}
    assert torch.get_num_threads() == 1 and cv2.getNumThreads() == 1
    assert onnx_session_options().intra_op_num_threads == 1
    # A later library Pipeline does not undo what the command line set.
    assert _threads.ensure_threads("auto") == 1 and torch.get_num_threads() == 1


def test_onnx_sessions_do_not_spin_and_run_sequentially(monkeypatch):
    import onnxruntime as ort

    monkeypatch.delenv("MONOSTIXELS_SPIN", raising=False)
    opts = onnx_session_options(1)
    assert opts.intra_op_num_threads == 1 and opts.inter_op_num_threads == 1
    assert opts.execution_mode == ort.ExecutionMode.ORT_SEQUENTIAL
    assert opts.get_session_config_entry("session.intra_op.allow_spinning") == "0"
    assert onnx_session_options().intra_op_num_threads == _threads.threads()
    # The comparison switch: ONNX Runtime's own default (spinning) is left alone.
    monkeypatch.setenv("MONOSTIXELS_SPIN", "1")
    with pytest.raises(RuntimeError, match="allow_spinning"):  # no entry set: ONNX Runtime's default
        onnx_session_options().get_session_config_entry("session.intra_op.allow_spinning")


def test_the_package_sessions_take_the_options():
    from monostixels.inputs.semantic import _fcn8s_segmenter
    from monostixels.pipeline import load_config

    cfg = load_config(["semantic=fcn8s"]).semantic
    seg = _fcn8s_segmenter(cfg, 1)
    if not hasattr(seg, "session"):
        pytest.skip("the FCN-8s ONNX file is absent: the torch segmenter has no ONNX session")
    opts = seg.session.get_session_options()
    assert opts.intra_op_num_threads == 1 and opts.inter_op_num_threads == 1
    assert opts.get_session_config_entry("session.intra_op.allow_spinning") == "0"


def test_config_has_one_threads_key():
    from monostixels.pipeline import load_config

    assert load_config([]).threads == "auto"
    assert load_config(["threads=1"]).threads == 1


def test_an_overlapped_stream_gives_torch_one_thread_less_while_it_runs(restore_threads):
    """stream.overlap: the sequence layer's thread and the next pair's flow keep the cores busy, so torch
    (and with it the photometric search's workers) gets one thread less than the budget while the
    sequence runs, at least one, and the budget back after; without overlap it keeps the budget."""
    from monostixels.data.synthetic import SyntheticSequenceSource
    from monostixels.pipeline import Pipeline, load_config
    from monostixels.build import pipeline_settings, sequence_settings
    from monostixels.sequence import SequenceRunner
    from monostixels.build import pipeline_settings, sequence_settings

    source = SyntheticSequenceSource(1, 2, seed=4, scale=0.25)
    for budget, overlap, inside in ((2, "true", 1), (3, "true", 2), (1, "true", 1), (2, "false", 2)):
        _threads._applied = None
        set_threads(budget)
        cfg = load_config(["flow=dis", "semantic=gt", "motion=gt", f"stream.overlap={overlap}"])
        runner = SequenceRunner(sequence_settings(cfg), Pipeline(pipeline_settings(cfg), sfm=False))
        seen = [torch.get_num_threads() for _ in runner.run(source)]
        assert seen == [inside] * len(source) and torch.get_num_threads() == budget, (budget, overlap, seen)
        assert (runner.stream.ahead > 0) == (overlap == "true")


def test_import_makes_idle_pool_threads_sleep():
    # Set on `import monostixels` (before torch and OpenCV load) unless the user chose otherwise.
    if os.environ.get("MONOSTIXELS_SPIN"):
        pytest.skip("MONOSTIXELS_SPIN is set: spinning left on")
    for key in ("OMP_WAIT_POLICY", "OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER", "OPENCV_THREAD_POOL_ACTIVE_WAIT_MAIN"):
        assert key in os.environ


def test_an_overlapping_pipeline_gives_opencv_one_thread(restore_threads):
    """Pipeline(pipeline_settings(overlap=True)) runs its flow in a thread beside other work, which keeps a core busy:
    OpenCV's pool gets one thread less than the budget there (at least one), the budget otherwise;
    torch keeps the budget (the solver's columns split over it)."""
    from monostixels.pipeline import Pipeline, load_config
    from monostixels.build import pipeline_settings

    set_threads(2)
    cfg = load_config(["data=synthetic", "flow=gt", "semantic=gt", "motion=gt"])
    Pipeline(pipeline_settings(cfg), overlap=True)
    assert cv2.getNumThreads() == 1 and torch.get_num_threads() == 2
    Pipeline(pipeline_settings(cfg), overlap=False)
    assert cv2.getNumThreads() == 2 and torch.get_num_threads() == 2
    _threads._applied = None
    set_threads(4)
    Pipeline(pipeline_settings(cfg), overlap=True)
    assert cv2.getNumThreads() == 3
    set_threads(1)
    Pipeline(pipeline_settings(cfg), overlap=True)
    assert cv2.getNumThreads() == 1
