"""The CPU the package runs on: its model and the instruction-set flags that choose its code paths.

Two results depend on them. ONNX Runtime's INT8 convolutions use 8-bit dot products where the CPU
has VNNI (AVX-512 VNNI, AVX-VNNI), else pairs of u8 x s8 products added into saturating 16-bit sums
(``monostixels/inputs/quantize.py``); the solver's C++ kernel is compiled for the CPU
(``monostixels/core/_dp_cpp.py``). Runs (``summary.json``, docs/conventions.md, section 4.3) and the
benchmarks' JSON (section 4.7) record both, so that a number can be placed.

The flags are read from ``/proc/cpuinfo`` (Linux); elsewhere they are unknown (None).
"""
from __future__ import annotations

import functools
import platform
from pathlib import Path
from typing import Any

__all__ = ["FLAGS", "cpu_info", "int8_path", "runtime_report"]

#: The flags recorded (Linux ``/proc/cpuinfo`` names): AVX2, AVX-512, and the two VNNI extensions.
FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx_vnni")
_CPUINFO = Path("/proc/cpuinfo")


@functools.lru_cache(maxsize=1)
def cpu_info() -> dict[str, Any]:
    """``{"model": str | None, "machine": str, "flags": {flag: bool | None}}`` of this CPU (:data:`FLAGS`;
    None where they cannot be read)."""
    model, flags = None, None
    try:
        lines = _CPUINFO.read_text().splitlines()
    except OSError:
        lines = []
    for line in lines:
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "model name" and model is None:
            model = value.strip()
        elif key == "flags" and flags is None:
            flags = set(value.split())
    return {"model": model or platform.processor() or None, "machine": platform.machine(),
            "flags": {f: (None if flags is None else f in flags) for f in FLAGS}}


def int8_path(info: dict[str, Any] | None = None) -> str:
    """ONNX Runtime's INT8 convolution path on this CPU: ``vnni`` (8-bit dot products), ``no_vnni`` (x86-64
    without them: saturating 16-bit pairwise sums), ``not_x86`` or ``unknown`` (flags unreadable)."""
    info = cpu_info() if info is None else info
    if info["machine"].lower() not in ("x86_64", "amd64"):
        return "not_x86"
    flags = info["flags"]
    if flags["avx512_vnni"] is None:
        return "unknown"
    return "vnni" if flags["avx512_vnni"] or flags["avx_vnni"] else "no_vnni"


def runtime_report() -> dict[str, Any]:
    """What a run ran on (``summary.json`` ``platform``): ``cpu`` (:func:`cpu_info`), ``onnxruntime`` (its
    version, None where it is not installed), ``int8_path`` (:func:`int8_path`) and ``solver_build`` (the
    C++ kernel's compiler flags where it is loaded, else None)."""
    try:
        import onnxruntime

        ort_version = onnxruntime.__version__
    except ImportError:
        ort_version = None
    from monostixels.core import _dp_cpp

    return {"cpu": cpu_info(), "onnxruntime": ort_version, "int8_path": int8_path(),
            "solver_build": _dp_cpp.build_flags() if _dp_cpp.loaded() else None}
