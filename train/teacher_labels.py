"""Cache the Cityscapes teacher's soft labels over every real frame, for distillation.

The teacher (the shared ESPNetv2 ONNX files, fixed input sizes 384x1248 and 640x1024) runs once
per (frame, view); its class probabilities, mapped to our 10 classes by summing the Cityscapes
classes of each of ours (``mapping``, -1 drops the background channel and the rest is
renormalised), are stored uint8-quantised (``round(255 p)``) at ``1 / downsample`` of the
teacher's resolution in one compressed ``.npz`` per entry, plus one line per entry in
``<out>/manifest.jsonl``. ``train.semantic`` (``data.soft``) reads the manifest.

Views (``views``):

- ``full``: the whole frame, **letterboxed**: resized with its aspect ratio kept so that it fits
  the teacher's input, padded with the mean colour (zero after normalisation) on the right and at
  the bottom; only the image area of the output is kept.
- ``zoom``: ``columns`` windows side by side, each ``1 / zoom`` of the full view's footprint,
  centred on the row ``center_row`` (fraction of the height: the horizon band, where distant and
  thin objects are), each letterboxed the same way: the teacher sees far objects ``zoom`` times
  larger, which it labels better.

Video sources (``kind: video``) are decoded with OpenCV once; their frames are written as JPEG
(quality 95) under ``<out>/frames/<source>/`` so that training reads images like any other.

Resumable: an entry whose ``.npz`` exists and is in the manifest is skipped. ONNX Runtime runs
with ``threads`` intra-op threads (1: the machine is shared).

Run from the repository root::

    nice -n 19 python -m train.teacher_labels                   # all sources (conf/teacher_labels.yaml)
    nice -n 19 python -m train.teacher_labels limit=20          # the first 20 new entries only
"""
from __future__ import annotations

import glob
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

import cv2
import hydra
import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from monostixels._checks import InputError, one_line_errors
from monostixels.core.classes import NUM_CLASSES

__all__ = [
    "SoftEntry",
    "view_windows",
    "letterbox",
    "map_probabilities",
    "quantise",
    "dequantise",
    "save_entry",
    "load_entry",
    "read_manifest",
    "Teacher",
    "list_frames",
    "run",
    "main",
]

logger = logging.getLogger("train.teacher_labels")

#: Quantisation steps of a stored probability (uint8).
QUANT_LEVELS = 255


@dataclass(frozen=True)
class SoftEntry:
    """One cached teacher output: a window of one frame.

    Attributes:
        id: ``source/frame/view`` (unique; the manifest key).
        source: source name (``conf/teacher_labels.yaml``), e.g. ``kitti_0028``, ``dashcam``.
        frame: frame number within its source (KITTI: the raw frame number; video: the index).
        view: view name (``full``, ``zoom2_0``, ...).
        image: the image file (RGB read by OpenCV).
        box: ``(x0, y0, x1, y1)`` the window in the image's pixels (x1, y1 exclusive).
        fx: the camera's focal length in pixels (training resizes to a common focal length).
        probs: the ``.npz`` file with ``probs`` uint8 (10, h, w) over the window.
        labels: CamVid label image of the frame or None (hard labels where they exist).
    """

    id: str
    source: str
    frame: int
    view: str
    image: str
    box: tuple[int, int, int, int]
    fx: float
    probs: str
    labels: str | None = None

    def to_json(self) -> str:
        return json.dumps({**self.__dict__, "box": list(self.box)})

    @staticmethod
    def from_dict(d: dict[str, Any]) -> "SoftEntry":
        return SoftEntry(**{**d, "box": tuple(int(v) for v in d["box"]), "frame": int(d["frame"]),
                            "fx": float(d["fx"])})


def view_windows(height: int, width: int, input_hw: Sequence[int], view: dict[str, Any]) -> list[tuple[str, tuple[int, int, int, int]]]:
    """Windows ``(name, (x0, y0, x1, y1))`` of one view of a ``height`` x ``width`` frame.

    ``full`` is the whole frame. ``zoom`` windows have the size of the full view's footprint in the
    teacher input divided by ``zoom`` (i.e. the teacher resizes them ``zoom`` times more than the
    full frame), ``columns`` of them spread evenly across the width, centred on ``center_row``.
    """
    name = str(view["name"])
    if "zoom" not in view:
        return [(name, (0, 0, width, height))]
    zoom, cols = float(view["zoom"]), int(view.get("columns", 1))
    if zoom < 1 or cols < 1:
        raise InputError(f"views.{name}: zoom must be >= 1 and columns >= 1, got {zoom}, {cols}")
    s_full = min(input_hw[0] / height, input_hw[1] / width)
    # Window = the teacher input at zoom x the full view's scale, clipped to the frame.
    wh = min(height, round(input_hw[0] / (s_full * zoom)))
    ww = min(width, round(input_hw[1] / (s_full * zoom)))
    cy = float(view.get("center_row", 0.5)) * height
    y0 = int(np.clip(round(cy - wh / 2), 0, height - wh))
    xs = np.linspace(0, width - ww, cols) if cols > 1 else [(width - ww) / 2]
    return [(f"{name}_{k}", (int(round(x)), y0, int(round(x)) + ww, y0 + wh)) for k, x in enumerate(xs)]


def letterbox(image: np.ndarray, input_hw: Sequence[int]) -> tuple[np.ndarray, tuple[int, int]]:
    """Resize ``image`` (h, w, 3) uint8 RGB keeping its aspect so that it fits ``input_hw``.

    Returns:
        ((H_in, W_in, 3) float32 RGB [0, 1] with zeros right / below, (h', w') the resized size).
    """
    h, w = image.shape[:2]
    s = min(input_hw[0] / h, input_hw[1] / w)
    nh, nw = min(int(input_hw[0]), max(1, round(h * s))), min(int(input_hw[1]), max(1, round(w * s)))
    resized = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    out = np.zeros((int(input_hw[0]), int(input_hw[1]), 3), np.float32)
    out[:nh, :nw] = resized.astype(np.float32) / 255.0
    return out, (nh, nw)


def map_probabilities(logits: torch.Tensor, mapping: Sequence[int]) -> torch.Tensor:
    """(C, H, W) teacher logits -> (10, H, W) probabilities of our classes.

    Softmax over the teacher classes whose ``mapping`` is not -1 (a dropped channel, e.g. the
    background, takes no mass), then each of our classes gets the sum of its teacher classes.
    """
    if logits.shape[0] != len(mapping):
        raise InputError(f"teacher mapping: {len(mapping)} entries for {logits.shape[0]} output channels")
    keep = [k for k, m in enumerate(mapping) if m >= 0]
    p = torch.softmax(logits[keep].float(), dim=0)
    idx = torch.tensor([mapping[k] for k in keep])
    out = torch.zeros((NUM_CLASSES, *logits.shape[1:]), dtype=torch.float32)
    out.index_add_(0, idx, p)
    return out


def quantise(probs: torch.Tensor) -> np.ndarray:
    """(C, H, W) probabilities -> uint8 ``round(255 p)`` (error at most 1/510 per value)."""
    return (probs.clamp(0, 1) * QUANT_LEVELS + 0.5).to(torch.uint8).numpy()


def dequantise(q: np.ndarray) -> torch.Tensor:
    """uint8 (C, H, W) -> float32 probabilities renormalised to sum 1 per pixel."""
    p = torch.from_numpy(q.astype(np.float32) / QUANT_LEVELS)
    return p / p.sum(0, keepdim=True).clamp_min(1e-6)


def save_entry(path: Path, probs: torch.Tensor) -> None:
    """Write quantised ``probs`` (10, h, w) to ``path`` (.npz, compressed), atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.npz")
    np.savez_compressed(tmp, probs=quantise(probs))
    tmp.replace(path)


def load_entry(path: str | Path) -> torch.Tensor:
    """The (10, h, w) float32 probabilities stored at ``path``."""
    with np.load(path) as z:
        return dequantise(z["probs"])


def read_manifest(path: str | Path) -> list[SoftEntry]:
    """Entries of a manifest (``manifest.jsonl``); the last line of an id wins, a torn line is skipped."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"teacher manifest {p} not found (python -m train.teacher_labels writes it)")
    out: dict[str, SoftEntry] = {}
    for line in p.read_text().splitlines():
        try:
            e = SoftEntry.from_dict(json.loads(line))
        except (json.JSONDecodeError, TypeError, KeyError):
            continue  # a line cut by an interrupted write
        out[e.id] = e
    return list(out.values())


class Teacher:
    """The ONNX teacher at its fixed input size, letterboxed, on one ONNX Runtime thread budget.

    Args:
        path: the ``.onnx`` file, input (1, 3, H_in, W_in), output (1, C, H_in, W_in) logits.
        mean, std: ImageNet normalisation of RGB [0, 1].
        mapping: teacher class -> our class (or -1).
        threads: ONNX Runtime intra-op threads.
        input_size: (H_in, W_in) for a model without a static input size (ignored otherwise).
    """

    def __init__(self, path: str | Path, *, mean: Sequence[float], std: Sequence[float], mapping: Sequence[int],
                 threads: int = 1, input_size: Sequence[int] | None = None) -> None:
        import onnxruntime as ort  # local: only the teacher needs it

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
        self.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        inp = self.session.get_inputs()[0]
        static = all(isinstance(d, int) and d > 0 for d in inp.shape[2:])
        if not static and input_size is None:
            raise InputError(f"teacher {path}: no static input size; give the source an input_size [H, W]")
        hw = inp.shape[2:] if static else input_size
        self.name, self.input_hw = inp.name, (int(hw[0]), int(hw[1]))
        self.mean = np.asarray(mean, np.float32).reshape(1, 1, 3)
        self.std = np.asarray(std, np.float32).reshape(1, 1, 3)
        self.mapping = [int(m) for m in mapping]

    def __call__(self, window: np.ndarray, downsample: float) -> torch.Tensor:
        """(10, h, w) probabilities of ``window`` (H, W, 3) uint8 RGB; (h, w) = the window's size in
        the teacher input divided by ``downsample``."""
        x, (nh, nw) = letterbox(window, self.input_hw)
        valid = np.zeros(x.shape[:2], bool)
        valid[:nh, :nw] = True
        x = np.where(valid[..., None], (x - self.mean) / self.std, 0.0).astype(np.float32)
        out = self.session.run(None, {self.name: x.transpose(2, 0, 1)[None]})[0][0]
        probs = map_probabilities(torch.from_numpy(out[:, :nh, :nw]), self.mapping)
        size = (max(1, round(nh / downsample)), max(1, round(nw / downsample)))
        return F.interpolate(probs[None], size=size, mode="area")[0]


def list_frames(src: dict[str, Any], out: Path) -> Iterator[tuple[int, Path, str | None]]:
    """``(frame number, image path, CamVid label path or None)`` of one source of the config.

    ``kind``: ``images`` (``glob``; the frame number is the file stem's trailing digits or the
    index), ``camvid`` (``root`` and ``split``: the SegNet list, with labels), ``video`` (``path``:
    decoded with OpenCV, frames written to ``out/frames/<name>/NNNNNN.jpg`` once).
    """
    kind = str(src.get("kind", "images"))
    if kind == "images":
        paths = sorted(glob.glob(str(src["glob"])))
        if not paths:
            raise InputError(f"teacher source {src['name']}: no file matches {src['glob']!r}")
        for k, p in enumerate(paths):
            digits = "".join(ch for ch in Path(p).stem if ch.isdigit())
            yield (int(digits) if digits else k), Path(p), None
    elif kind == "camvid":
        from monostixels.data.camvid import read_camvid_split

        for k, item in enumerate(read_camvid_split(src["root"], str(src["split"]))):
            yield k, item.image, str(item.labels)
    elif kind == "video":
        folder = out / "frames" / str(src["name"])
        folder.mkdir(parents=True, exist_ok=True)
        cap = cv2.VideoCapture(str(src["path"]))
        if not cap.isOpened():
            raise InputError(f"teacher source {src['name']}: cannot open video {src['path']}")
        k = 0
        while True:
            ok, bgr = cap.read()
            if not ok:
                break
            p = folder / f"{k:06d}.jpg"
            if not p.is_file():
                cv2.imwrite(str(p), bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
            yield k, p, None
            k += 1
        cap.release()
        if k == 0:
            raise InputError(f"teacher source {src['name']}: video {src['path']} has no frame")
    else:
        raise InputError(f"teacher source {src['name']}: kind must be images, camvid or video, got {kind!r}")


def run(cfg: DictConfig) -> dict[str, Any]:
    """Label every (source, frame, view) of the config not yet in the manifest; returns counts."""
    out = Path(str(cfg.out))
    out.mkdir(parents=True, exist_ok=True)
    manifest = out / "manifest.jsonl"
    done = {e.id for e in read_manifest(manifest)} if manifest.is_file() else set()
    views = {str(v.name): OmegaConf.to_container(v, resolve=True) for v in cfg.views}
    teachers: dict[str, Teacher] = {}
    t = OmegaConf.to_container(cfg.teacher, resolve=True)
    # Jobs in pass order (all full views first: a run stopped early still covers every frame once).
    jobs: list[tuple[dict, dict, int, Path, str | None]] = []
    for view_name in cfg.passes:
        for src in cfg.sources:
            src = OmegaConf.to_container(src, resolve=True)
            if view_name in src.get("views", ["full"]):
                jobs += [(src, views[view_name], k, p, lab) for k, p, lab in list_frames(src, out)]
    limit = cfg.get("limit")
    new = 0
    t0 = time.monotonic()
    with manifest.open("a") as mf:
        for src, view, k, path, lab in tqdm(jobs, desc="teacher", mininterval=30):
            if limit is not None and new >= int(limit):
                break
            model = str(src["model"])
            if model not in teachers:
                teachers[model] = Teacher(model, mean=t["mean"], std=t["std"], mapping=t["mapping"],
                                          threads=int(cfg.threads), input_size=src.get("input_size"))
            teacher = teachers[model]
            bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if bgr is None:
                raise InputError(f"teacher source {src['name']}: cannot read {path}")
            # The windows depend on the frame size (a resumed run re-reads done frames: cheap).
            v = {**view, "center_row": src["center_row"]} if "center_row" in src and "zoom" in view else view
            windows = view_windows(bgr.shape[0], bgr.shape[1], teacher.input_hw, v)
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            for vname, (x0, y0, x1, y1) in windows:
                eid = f"{src['name']}/{k}/{vname}"
                npz = out / str(src["name"]) / f"{k:06d}_{vname}.npz"
                if eid in done and npz.is_file():
                    continue
                probs = teacher(rgb[y0:y1, x0:x1], float(cfg.downsample))
                save_entry(npz, probs)
                entry = SoftEntry(eid, str(src["name"]), k, vname, str(path), (x0, y0, x1, y1), float(src["fx"]),
                                  str(npz), lab)
                mf.write(entry.to_json() + "\n")
                mf.flush()
                done.add(eid)
                new += 1
    logger.info("%d new entries in %.0f s; %d in %s", new, time.monotonic() - t0, len(done), manifest)
    return {"new": new, "total": len(done), "manifest": str(manifest)}


@hydra.main(config_path="../conf", config_name="teacher_labels", version_base=None)
@one_line_errors("train.teacher_labels")
def main(cfg: DictConfig) -> None:
    """Hydra entry point (``python -m train.teacher_labels key=value ...``)."""
    print(json.dumps(run(cfg), indent=1))


if __name__ == "__main__":
    main()
