"""monostixels._cpu: the CPU's model and flags, ONNX Runtime's INT8 path on it, and the solver build's -march."""
from __future__ import annotations

from pathlib import Path

import pytest

from monostixels import _cpu
from monostixels.core import _dp_cpp

ZEN5 = ("processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC 9B45\n"
        "flags\t\t: fpu sse2 avx avx2 avx512f avx512bw avx_vnni avx512_vnni\n\n"
        "processor\t: 1\nmodel name\t: AMD EPYC 9B45\nflags\t\t: fpu sse2 avx avx2 avx512f avx_vnni avx512_vnni\n")
ZEN3 = "model name\t: AMD EPYC 7B13\nflags\t\t: fpu sse2 avx avx2 fma\n"
ALDER_LAKE = "model name\t: 12th Gen Intel(R) Core(TM) i7-1260P\nflags\t\t: avx avx2 avx_vnni\n"


def _info(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, text: str | None, machine: str = "x86_64") -> dict:
    path = tmp_path / ("absent" if text is None else "cpuinfo")
    if text is not None:
        path.write_text(text)
    monkeypatch.setattr(_cpu, "_CPUINFO", path)
    monkeypatch.setattr(_cpu.platform, "machine", lambda: machine)
    _cpu.cpu_info.cache_clear()
    try:
        return _cpu.cpu_info()
    finally:
        _cpu.cpu_info.cache_clear()


def test_the_model_flags_and_int8_path_of_each_kind_of_cpu(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    zen5 = _info(monkeypatch, tmp_path, ZEN5)
    assert zen5 == {"model": "AMD EPYC 9B45", "machine": "x86_64",
                    "flags": {"avx2": True, "avx512f": True, "avx512_vnni": True, "avx_vnni": True}}
    assert _cpu.int8_path(zen5) == "vnni"
    zen3 = _info(monkeypatch, tmp_path, ZEN3)
    assert zen3["flags"] == {"avx2": True, "avx512f": False, "avx512_vnni": False, "avx_vnni": False}
    assert _cpu.int8_path(zen3) == "no_vnni"
    assert _cpu.int8_path(_info(monkeypatch, tmp_path, ALDER_LAKE)) == "vnni"  # AVX-VNNI without AVX-512
    unknown = _info(monkeypatch, tmp_path, None)  # no /proc/cpuinfo (not Linux)
    assert set(unknown["flags"].values()) == {None} and _cpu.int8_path(unknown) == "unknown"
    assert _cpu.int8_path(_info(monkeypatch, tmp_path, ZEN3, machine="aarch64")) == "not_x86"


def test_the_report_of_a_run_names_this_cpu_onnxruntime_and_the_solver_build() -> None:
    rep = _cpu.runtime_report()
    assert set(rep) == {"cpu", "onnxruntime", "int8_path", "solver_build"}
    assert set(rep["cpu"]["flags"]) == set(_cpu.FLAGS) and rep["int8_path"] == _cpu.int8_path()
    assert rep["solver_build"] in (None, _dp_cpp.build_flags())


def test_the_kernels_march_comes_from_the_environment_and_names_its_build(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(_dp_cpp.MARCH_ENV, raising=False)
    assert _dp_cpp.march() == "native" and "-march=native" in _dp_cpp.build_flags()
    native = _dp_cpp.build_flags()
    monkeypatch.setenv(_dp_cpp.MARCH_ENV, "x86-64-v3")
    assert _dp_cpp.march() == "x86-64-v3"
    # Only the -march differs; exactness flags stay.
    assert [f for f in _dp_cpp.build_flags() if f not in native] == ["-march=x86-64-v3"]
    assert "-ffp-contract=off" in _dp_cpp.build_flags()
    monkeypatch.setenv(_dp_cpp.MARCH_ENV, "native; rm -rf /")
    with pytest.raises(ValueError, match="MONOSTIXELS_MARCH"):
        _dp_cpp.march()
