"""INT8 copies of our ONNX networks: their convolutions quantized, the rest float.

Static quantization with ONNX Runtime's tools (QDQ; weights signed, per output channel; activations
unsigned, per tensor, their ranges the min / max seen on calibration inputs). Only ``Conv`` is
quantized: the convolutions are most of the time of RAFT and of the FCN-8s on a CPU, while what
follows them (RAFT's correlation lookup and flow arithmetic, the FCN's upsampling of scores) keeps
float32. On a CPU with 8-bit dot products (AVX-512 VNNI, AVX-VNNI) an INT8 convolution takes about
half the time of a float one (models/MODEL_CARD.md).

Used by :func:`monostixels.inputs.raft.quantize_onnx` (RAFT, ``flow.runtime=auto``) and
:func:`quantize_fcn8s_onnx` (the FCN-8s of ``semantic=fcn8s_int8``, the semantic net of
``preset=fast``).
"""
from __future__ import annotations

import logging
import os
import tempfile
import warnings
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from monostixels._checks import InputError

__all__ = ["quantize_convolutions", "quantize_fcn8s_onnx"]

logger = logging.getLogger(__name__)


def quantize_convolutions(proto: Any, dst: str | os.PathLike, feeds: Iterable[dict[str, np.ndarray]],
                          metadata: dict[str, str]) -> Path:
    """Write an INT8 copy of the float graph ``proto`` (an ``onnx.ModelProto``) to ``dst``.

    Args:
        proto: the float graph (changed in place: float16 weights become float32 initializers).
        dst: the INT8 file to write.
        feeds: calibration inputs, each ``{input name: array}`` as the graph is run.
        metadata: ``metadata_props`` of the copy (``quantized: int8`` is added).

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
                                op_types_to_quantize=["Conv"], per_channel=True, activation_type=QuantType.QUInt8,
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


def quantize_fcn8s_onnx(src: str | os.PathLike, dst: str | os.PathLike, images: Iterable[torch.Tensor],
                        scale: float = 1.0) -> Path:
    """An INT8 copy of an FCN-8s ONNX file (:func:`monostixels.inputs.fcn8s.export_onnx`: input ``image``
    (1, 3, h, w) RGB in [0, 1], ImageNet normalisation inside the graph).

    Args:
        src: the float file (e.g. ``models/fcn8s_real.onnx``).
        dst: the INT8 file to write.
        images: calibration images (3, H, W) RGB in [0, 1]; each is resized by ``scale`` and padded to a
            multiple of 32, as ``semantic=fcn8s`` feeds the net.
        scale: resize factor of the calibration images.

    Returns:
        ``dst``, with the float file's metadata, ``quantized: int8`` and ``int8_from`` (the float file's name).
    """
    import onnx

    from monostixels.inputs.semantic import _preprocess

    src = Path(src)
    if not src.is_file():
        raise InputError(f"quantize: no ONNX file at {src}")
    proto = onnx.load(str(src))
    if [i.name for i in proto.graph.input] != ["image"]:
        raise InputError(f"quantize: {src} is not an FCN-8s export (one input named 'image'), "
                         f"it has inputs {[i.name for i in proto.graph.input]}")
    meta = {p.key: p.value for p in proto.metadata_props}

    def feeds() -> Iterable[dict[str, np.ndarray]]:
        for image in images:
            # The graph normalises itself: mean 0, std 1 here, as OnnxSegmenter calls it for our nets.
            x, _ = _preprocess(image, input_size=None, scale=scale, mean=(0.0, 0.0, 0.0),
                               std=(1.0, 1.0, 1.0), pad_to=32)
            yield {"image": x.numpy()}

    return quantize_convolutions(proto, dst, feeds(), {**meta, "int8_from": src.name})
