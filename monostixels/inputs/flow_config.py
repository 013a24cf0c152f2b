"""The settings of the flow backends: the schemas of the options of the config group ``flow``
(monostixels.config_schema), one dataclass per backend (``name``), read by :mod:`monostixels.inputs.flow`.

The defaults are those of the option named after the backend (``flow=deepflow``, ``flow=dis``,
``flow=raft``, ``flow=gt``); the other options (``deepflow_fast``, ``dis_refine``) override some of them.
The covariance settings (``confidence`` ... ``fb_weight``) are those of
:class:`monostixels.inputs.confidence.ConfidenceParams`: pixels of the full-size image.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional, Union

from monostixels._checks import choice, option_params

__all__ = ["FLOW_SCHEMAS", "DisPreset", "RaftSize", "RaftRuntime", "Precision", "FlowConfidence", "DeepFlowMatches", "FlowConfig", "GtFlowConfig", "ImageFlowConfig", "DisFlowConfig", "DeepFlowConfig",
           "RaftFlowConfig", "flow_name", "flow_params"]


# The choices among names of the flow settings: OmegaConf refuses any other value (monostixels._checks.Choice).
DisPreset = choice("DisPreset", "ultrafast fast medium", __name__)  # OpenCV's DIS presets (preset, matches_preset)
RaftSize = choice("RaftSize", "small large", __name__)  # torchvision's RAFT models
RaftRuntime = choice("RaftRuntime", "auto torch onnx", __name__)  # where RAFT runs
Precision = choice("Precision", "float32 int8", __name__)  # the precision of a network's weights
FlowConfidence = choice("FlowConfidence", "constant structure_tensor", __name__)  # the covariance's method
DeepFlowMatches = choice("DeepFlowMatches", "dis none", __name__)  # DeepFlow's large-displacement guidance


@dataclass
class GtFlowConfig:
    """``flow=gt``: the data source's ground-truth flow, with a constant covariance by default.

    Attributes:
        name: the backend (``gt``).
        sigma: standard deviation of the flow (pixels), the covariance ``sigma^2 I`` of ``constant``.
        confidence: covariance method, ``constant`` | ``structure_tensor``
            (:func:`monostixels.inputs.confidence.flow_covariance`).
        sigma_max: standard deviation (pixels) of the pixels without ground-truth flow (flow 0: no information).
        noise: intensity noise of the grey image (values in [0, 1]; ``structure_tensor``).
        window_sigma: Gaussian window of the structure tensor (pixels).
        sigma_min: flow standard deviation floor (pixels; ``structure_tensor``); None = the smaller of 0.25 px
            and ``sigma``.
    """

    name: str = "gt"
    sigma: float = 0.5
    confidence: FlowConfidence = FlowConfidence.constant
    sigma_max: float = 20.0
    noise: float = 0.01
    window_sigma: float = 2.0
    sigma_min: Optional[float] = None


@dataclass
class ImageFlowConfig:
    """The settings every image backend (``dis``, ``deepflow``, ``raft``) shares: the covariance, the
    resolution the backend runs at and the refinement at full size (monostixels.inputs.flow's docstring).

    Attributes:
        name: the backend.
        confidence: covariance method, ``constant`` | ``structure_tensor``
            (:func:`monostixels.inputs.confidence.flow_covariance`).
        sigma: flow standard deviation (pixels) of ``constant``.
        noise: intensity noise of the grey image (values in [0, 1]).
        window_sigma: Gaussian window of the structure tensor (pixels).
        sigma_min: flow standard deviation floor (pixels).
        sigma_max: flow standard deviation ceiling (pixels).
        fb_consistency: check the flow forward-backward (the backend runs both ways: twice the flow time) and
            add ``(fb_weight * round-trip error)^2 I`` to the covariance: where the round trip does not close
            (occlusions, foliage, the image border) the flow is trusted less.
        fb_weight: weight of the round-trip error (dimensionless).
        scale: resolution the backend runs at, in (0, 1]: the images are downscaled by it (area), the flow
            upsampled back.
        refine: refine the flow at full resolution after the backend (OpenCV's VariationalRefinement); the
            covariance is then computed on the full-size image, else on the downscaled one.
        refine_passes: passes of the refinement where it is on, each warping again by the last one's flow.
    """

    name: str = ""
    confidence: FlowConfidence = FlowConfidence.structure_tensor
    sigma: float = 0.5
    noise: float = 0.01
    window_sigma: float = 2.0
    sigma_min: float = 0.25
    sigma_max: float = 20.0
    fb_consistency: bool = False
    fb_weight: float = 1.0
    scale: float = 1.0
    refine: bool = False
    refine_passes: int = 1


@dataclass
class DisFlowConfig(ImageFlowConfig):
    """``flow=dis``: OpenCV's DIS flow (Kroeger et al. 2016), fast, less accurate than DeepFlow;
    ``flow=dis_refine`` refines it once at full size.

    Attributes:
        preset: DIS preset, ``ultrafast`` | ``fast`` | ``medium``.
    """

    name: str = "dis"
    preset: DisPreset = DisPreset.medium


@dataclass
class DeepFlowConfig(ImageFlowConfig):
    """``flow=deepflow``: OpenCV contrib's DeepFlow (Weinzaepfel et al. 2013), the paper's flow, at full size,
    refined and checked forward-backward; ``flow=deepflow_fast`` runs it at half size.

    Attributes:
        matches: large-displacement guidance (DeepFlow's matching term, which OpenCV's DeepFlow lacks):
            ``dis`` = warp by DIS's dense patch matches, DeepFlow solves for the residual; ``none`` = OpenCV's as is.
        matches_preset: the DIS preset of the matches (they stay at full size whatever ``scale``).
        bands: DeepFlow's variational stage on this many overlapping vertical strips, one thread each (it
            runs on one core otherwise).
    """

    name: str = "deepflow"
    matches: DeepFlowMatches = DeepFlowMatches.dis
    matches_preset: DisPreset = DisPreset.medium
    bands: int = 1
    sigma_min: float = 0.3
    fb_consistency: bool = True
    refine: bool = True
    refine_passes: int = 4


@dataclass
class RaftFlowConfig(ImageFlowConfig):
    """``flow=raft``: torchvision's RAFT with weights from a local file (never downloaded), in torch or
    through ONNX Runtime (models/MODEL_CARD.md).

    Attributes:
        size: ``small`` | ``large`` (must match the weights file).
        weights: state dict or train/flow.py checkpoint (relative paths: working directory, then repository root).
        runtime: ``auto`` | ``torch`` | ``onnx``. ``auto``: ONNX Runtime on the export beside the weights (their
            name with .onnx) where there is one, made with ``iters`` updates, and no GPU; else torch.
            ``onnx``: the file ``onnx``.
        onnx: the ONNX file of ``runtime=onnx``.
        precision: ``float32`` | ``int8``; ``int8``: ``runtime=auto`` takes the INT8 copy beside the weights
            (``<name>_int8.onnx``) where there is one.
        iters: recurrent refinement steps (an ONNX file has its own, fixed at export).
        threads: ONNX Runtime's intra-op threads (0 = the process's: :mod:`monostixels._threads`).
    """

    name: str = "raft"
    size: RaftSize = RaftSize.small
    weights: Optional[str] = "models/raft_small.pt"
    runtime: RaftRuntime = RaftRuntime.auto
    onnx: Optional[str] = "models/raft_small.onnx"
    precision: Precision = Precision.int8
    iters: int = 12
    threads: int = 0
    # RAFT's flow comes from a grid of 1/8 of its input: below full size its motion boundaries smear, and
    # the refinement restores the sub-pixel detail (docs/experiments.md "Flow").
    scale: float = 0.75
    refine: bool = True
    refine_passes: int = 4
    sigma_min: float = 0.3
    fb_consistency: bool = True


#: The schema of each flow backend by its ``name`` (the options ``deepflow_fast``, ``deepflow_fb`` and
#: ``dis_refine`` are those of their backend with other values).
FLOW_SCHEMAS: dict[str, type] = {"gt": GtFlowConfig, "deepflow": DeepFlowConfig, "dis": DisFlowConfig,
                                 "raft": RaftFlowConfig}

#: The settings of any flow backend.
FlowConfig = Union[GtFlowConfig, DisFlowConfig, DeepFlowConfig, RaftFlowConfig]


def flow_name(cfg: Any) -> str:
    """The backend (``name``) of a ``flow`` config node, dict or settings dataclass ("" where it has none)."""
    if isinstance(cfg, tuple(FLOW_SCHEMAS.values())):
        return cfg.name
    return str((cfg or {}).get("name", "") if hasattr(cfg, "get") or cfg is None else "")


def flow_params(cfg: Any) -> FlowConfig:
    """The settings of a ``flow`` config node (or dict) as its backend's dataclass (:data:`FLOW_SCHEMAS`);
    a dataclass given is returned as it is."""
    return option_params(FLOW_SCHEMAS, cfg, "flow")
