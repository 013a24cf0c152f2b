"""INT8 copies of our ONNX networks: their convolutions quantized, the rest float.

Static quantization with ONNX Runtime's tools (QDQ; weights signed, per output channel; activations
unsigned, per tensor, their ranges the min / max seen on calibration inputs). Only ``Conv`` is
quantized: the convolutions are most of the time of RAFT and of the FCN-8s on a CPU, while what
follows them (RAFT's correlation lookup and flow arithmetic, the FCN's upsampling of scores) keeps
float32. On a CPU with 8-bit dot products (AVX-512 VNNI, AVX-VNNI) an INT8 convolution takes about
half the time of a float one (models/MODEL_CARD.md).

Convention (the same result on every x86 CPU): on a CPU without VNNI, ONNX Runtime multiplies u8
activations by s8 weights with ``VPMADDUBSW``, which adds each pair of products into a saturating
16-bit sum. With weights of 7 bits (``reduce_range``: |w| <= :data:`SAFE_WEIGHT_MAX` = 64) no pair
can saturate: 2 x 255 x 64 = 32640 <= 32767, and the integer sums are those of the VNNI path.
:func:`can_saturate` tells a file whose weights are wider.

Used by :func:`monostixels.inputs.raft.quantize_onnx` (RAFT, ``flow.runtime=auto``) and
:func:`monostixels.inputs.semantic.quantize_fcn8s_onnx` (the FCN-8s of ``semantic=fcn8s_int8``, the
semantic net of ``preset=fast``), each beside the net's own input preparation.
"""
from __future__ import annotations

import logging
import os
import tempfile
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from monostixels._checks import InputError

__all__ = ["SAFE_WEIGHT_MAX", "can_saturate", "int8_weight_max", "quantize_convolutions"]

logger = logging.getLogger(__name__)

#: The largest |int8 weight| whose u8 x s8 products cannot saturate a pairwise 16-bit sum:
#: 2 x 255 x 64 = 32640 <= 32767 (ONNX Runtime's reduce_range gives weights in [-64, 64]).
SAFE_WEIGHT_MAX = 64


def quantize_convolutions(proto: Any, dst: str | os.PathLike, feeds: Iterable[dict[str, np.ndarray]],
                          metadata: dict[str, str], *, reduce_range: bool = True,
                          keep_float: Callable[[tuple[int, ...]], bool] | None = None) -> Path:
    """Write an INT8 copy of the float graph ``proto`` (an ``onnx.ModelProto``) to ``dst``.

    Args:
        proto: the float graph (changed in place: float16 weights become float32 initializers).
        dst: the INT8 file to write.
        feeds: calibration inputs, each ``{input name: array}`` as the graph is run.
        metadata: ``metadata_props`` of the copy (``quantized: int8`` is added).
        reduce_range: weights in 7 bits (|w| <= 64), so that no CPU's 16-bit pairwise sums saturate
            (module docstring); False: the full 8 bits.
        keep_float: called with each convolution's weight shape (out, in, kh, kw); True keeps that
            convolution float32.

    Returns:
        ``dst``.
    """
    import onnx
    from onnx import numpy_helper
    from onnxruntime.quantization import (CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType,
                                          quantize_static)

    # Float16 weights (read through a Cast, as our exports store them) back to float32 initializers:
    # the quantizer quantizes initializers per channel, not the output of a Cast.
    inits = {i.name: i for i in proto.graph.initializer}
    kept = []
    for node in proto.graph.node:
        if (node.op_type == "Cast" and node.input[0] in inits
                and inits[node.input[0]].data_type == onnx.TensorProto.FLOAT16):
            w = numpy_helper.to_array(inits[node.input[0]]).astype(np.float32)
            proto.graph.initializer.append(numpy_helper.from_array(w, node.output[0]))
        else:
            kept.append(node)
    del proto.graph.node[:]
    proto.graph.node.extend(kept)
    used = {name for node in proto.graph.node for name in node.input}
    for init in [i for i in proto.graph.initializer if i.name not in used]:
        proto.graph.initializer.remove(init)
    for k, node in enumerate(proto.graph.node):  # the quantizer names its nodes after these
        node.name = node.name or f"n{k}"
    shapes = {i.name: tuple(i.dims) for i in proto.graph.initializer}
    excluded = [node.name for node in proto.graph.node
                if node.op_type == "Conv" and keep_float is not None and node.input[1] in shapes
                and keep_float(shapes[node.input[1]])]
    seen = 0

    class _Feeds(CalibrationDataReader):
        def __init__(self) -> None:
            self.it = iter(feeds)

        def get_next(self) -> dict[str, np.ndarray] | None:
            nonlocal seen
            nxt = next(self.it, None)
            seen += nxt is not None
            return nxt

    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        f32 = Path(tmp) / "float32.onnx"
        onnx.save(proto, str(f32))
        # The quantizer logs a line per convolution and advice on the root logger: errors only meanwhile.
        root = logging.getLogger()
        level = root.level
        root.setLevel(max(level, logging.ERROR))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                quantize_static(str(f32), str(dst), _Feeds(), quant_format=QuantFormat.QDQ,
                                op_types_to_quantize=["Conv"], per_channel=True, reduce_range=reduce_range,
                                nodes_to_exclude=excluded, activation_type=QuantType.QUInt8,
                                weight_type=QuantType.QInt8, calibrate_method=CalibrationMethod.MinMax)
        except ValueError as err:
            if seen == 0:
                raise InputError(f"quantize: no calibration input for {dst}") from None
            raise InputError(f"quantize: {dst}: {err}") from err
        finally:
            root.setLevel(level)
    out = onnx.load(str(dst))
    del out.metadata_props[:]
    for key, value in {**metadata, "quantized": "int8"}.items():
        entry = out.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(out, str(dst))
    logger.info("quantized to INT8: %s (%.1f MB)", dst, dst.stat().st_size / 1e6)
    return dst


def int8_weight_max(path: str | os.PathLike) -> int:
    """The largest |w| over the int8 weights of the quantized convolutions (``DequantizeLinear`` of an int8
    initializer into a ``Conv``'s weight) of the ONNX file ``path``; 0 where there are none."""
    import onnx
    from onnx import numpy_helper

    proto = onnx.load(str(path))
    inits = {i.name: i for i in proto.graph.initializer}
    producers = {o: n for n in proto.graph.node for o in n.output}
    largest = 0
    for conv in (n for n in proto.graph.node if n.op_type == "Conv"):
        deq = producers.get(conv.input[1])
        if deq is None or deq.op_type != "DequantizeLinear" or deq.input[0] not in inits:
            continue
        w = numpy_helper.to_array(inits[deq.input[0]])
        if w.dtype == np.int8 and w.size:
            largest = max(largest, int(np.abs(w.astype(np.int16)).max()))
    return largest


def can_saturate(path: str | os.PathLike) -> bool:
    """Whether a pair of u8 x s8 products of the file's convolutions can overflow a 16-bit sum (weights wider
    than :data:`SAFE_WEIGHT_MAX`): its results then depend on the CPU (module docstring)."""
    return int8_weight_max(path) > SAFE_WEIGHT_MAX
