"""CamVid (Brostow et al. 2008) in the SegNet split: real street images with semantic labels.

Layout (the SegNet tutorial repository's, as in ``../shared/data/camvid``)::

    root/train.txt, val.txt, test.txt        "image label" per line, paths relative to root
    root/train/*.png|jpg, root/trainannot/*.png, ...   480x360 images, 8-bit labels 0..11

Label values: 0 sky, 1 building, 2 pole, 3 road, 4 pavement, 5 tree, 6 sign/symbol, 7 fence,
8 car, 9 pedestrian, 10 bicyclist, 11 void (not scored). They are mapped to our 10 classes
(``monostixels.core.classes.CLASS_NAMES``) by :data:`CAMVID_TO_OURS`:

======================  =============  ====================================================
CamVid                  ours           why
======================  =============  ====================================================
sky                     sky
building                building
pole                    pole
road                    road
pavement                sidewalk
tree                    vegetation
sign/symbol             pole           a sign is a static upright on a post (Cityscapes
                                       maps traffic signs to our pole as well)
fence                   building       static upright structure (Cityscapes fence/wall too)
car                     vehicle
pedestrian              person
bicyclist               two_wheeler    rider and bicycle are labelled as one region
void                    ignore (255)
======================  =============  ====================================================

CamVid has no terrain class; our ``terrain`` never occurs in its labels. Scores over "our classes
present in CamVid" (:data:`CAMVID_CLASSES_PRESENT`) therefore leave terrain out of the mean.

Terms: CC BY-NC 4.0 (research and personal use); a model trained on it inherits them.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np
import torch

from monostixels._checks import InputError
from monostixels.core.classes import CLASS_NAMES, IGNORE_LABEL
from monostixels.data.base import SourceAttributes

__all__ = [
    "CAMVID_CLASSES",
    "CAMVID_VOID",
    "CAMVID_TO_OURS",
    "CAMVID_CLASSES_PRESENT",
    "CAMVID_SPLITS",
    "CamVidItem",
    "CamVidSource",
    "map_camvid_labels",
    "read_camvid_split",
]

logger = logging.getLogger(__name__)

#: CamVid-11 class names, label values 0..10.
CAMVID_CLASSES: tuple[str, ...] = (
    "sky", "building", "pole", "road", "pavement", "tree", "sign_symbol", "fence", "car",
    "pedestrian", "bicyclist",
)
#: Label value of unlabelled (void) pixels.
CAMVID_VOID = 11
_OURS = {name: i for i, name in enumerate(CLASS_NAMES)}
#: CamVid label value (0..10) -> our class id (see the module docstring for the reasons).
CAMVID_TO_OURS: tuple[int, ...] = (
    _OURS["sky"], _OURS["building"], _OURS["pole"], _OURS["road"], _OURS["sidewalk"],
    _OURS["vegetation"], _OURS["pole"], _OURS["building"], _OURS["vehicle"], _OURS["person"],
    _OURS["two_wheeler"],
)
#: Our class ids that CamVid labels contain (terrain is the one it lacks).
CAMVID_CLASSES_PRESENT: tuple[int, ...] = tuple(sorted(set(CAMVID_TO_OURS)))
#: The SegNet split's list files.
CAMVID_SPLITS: tuple[str, ...] = ("train", "val", "test")

# 256-entry lookup table: CamVid value -> our id; void and anything unknown -> a marker checked below.
_BAD = 254
_LUT = np.full(256, _BAD, dtype=np.uint8)
_LUT[: len(CAMVID_TO_OURS)] = CAMVID_TO_OURS
_LUT[CAMVID_VOID] = IGNORE_LABEL


def map_camvid_labels(labels: np.ndarray, *, name: str = "labels") -> np.ndarray:
    """Map CamVid label values to our class ids.

    Args:
        labels: (H, W) integer CamVid values 0..10, 11 = void.
        name: the input's name (a file path) for error messages.

    Returns:
        (H, W) uint8 our class ids 0..9, ``IGNORE_LABEL`` (255) for void.

    Raises:
        InputError: values outside 0..11 (e.g. a colour-coded label image or another dataset's ids).
    """
    arr = np.asarray(labels)
    if arr.ndim != 2:
        raise InputError(f"{name}: CamVid labels must be a single-channel (H, W) image, got shape {arr.shape}")
    if arr.dtype.kind not in "ui" or arr.size and (int(arr.min()) < 0 or int(arr.max()) > CAMVID_VOID):
        bad = arr[(arr < 0) | (arr > CAMVID_VOID)] if arr.dtype.kind in "ui" else arr.ravel()
        example = bad.ravel()[0] if bad.size else arr.dtype
        raise InputError(
            f"{name}: CamVid label values must be 0..{CAMVID_VOID - 1} or {CAMVID_VOID} (void); "
            f"found {int(bad.size)} pixels outside (e.g. {example})"
        )
    return _LUT[arr.astype(np.int64)]


@dataclass(frozen=True)
class CamVidItem:
    """One labelled image of a split: paths of the image and of its label image."""

    image: Path
    labels: Path

    @property
    def name(self) -> str:
        return self.image.stem

    def load(self) -> tuple[np.ndarray, np.ndarray]:
        """(uint8 (H, W, 3) RGB image, uint8 (H, W) our class ids / 255) of this item.

        Raises:
            InputError: unreadable files, label values outside the mapping, or label and image
                sizes that differ.
        """
        bgr = cv2.imread(str(self.image), cv2.IMREAD_COLOR)
        if bgr is None:
            raise InputError(f"CamVid image {self.image}: cannot be read")
        raw = cv2.imread(str(self.labels), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise InputError(f"CamVid labels {self.labels}: cannot be read")
        if raw.shape[:2] != bgr.shape[:2]:
            raise InputError(
                f"CamVid labels {self.labels}: size {raw.shape[1]}x{raw.shape[0]} differs from its "
                f"image {self.image} ({bgr.shape[1]}x{bgr.shape[0]})"
            )
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), map_camvid_labels(raw, name=f"CamVid labels {self.labels}")


def read_camvid_split(root: str | Path, split: str) -> list[CamVidItem]:
    """The items of ``split`` listed in ``root/<split>.txt``.

    Args:
        root: the CamVid folder (holds ``train.txt``, ``val.txt``, ``test.txt``).
        split: ``train``, ``val`` or ``test``.

    Raises:
        InputError: missing root or list file, a malformed line, or a listed file that is missing.
    """
    if split not in CAMVID_SPLITS:
        raise InputError(f"data.split: CamVid split must be one of {', '.join(CAMVID_SPLITS)}, got {split!r}")
    if root is None or str(root) in ("", "???"):
        raise InputError("data.root: the CamVid folder is required (e.g. data.root=../shared/data/camvid)")
    root = Path(str(root)).expanduser()
    if not root.is_dir():
        raise InputError(f"data.root: CamVid folder {root} does not exist")
    listing = root / f"{split}.txt"
    if not listing.is_file():
        raise InputError(f"data.root: {listing} not found (the SegNet split's list of '{split}' images)")
    items: list[CamVidItem] = []
    for k, line in enumerate(listing.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 2:
            raise InputError(f"{listing}:{k}: expected 'image label', got {line!r}")
        # The SegNet lists carry absolute paths of its authors' machine; keep the last two parts.
        image, labels = (root / Path(p).parent.name / Path(p).name for p in parts)
        for path in (image, labels):
            if not path.is_file():
                raise InputError(f"{listing}:{k}: file {path} not found")
        items.append(CamVidItem(image=image, labels=labels))
    if not items:
        raise InputError(f"{listing}: lists no images")
    return items


class CamVidSource(SourceAttributes, Sequence[CamVidItem]):
    """A CamVid split for semantic evaluation (single images: no flow, motion or stixels).

    Args:
        root: the CamVid folder.
        split: ``train``, ``val`` or ``test``.
        frames: evaluate only the first ``frames`` images (None = all).
        step: take every ``step``-th image of the list.
    """

    def __init__(self, root: str | Path, *, split: str = "test", frames: int | None = None, step: int = 1) -> None:
        if int(step) < 1:
            raise InputError(f"data.step: must be >= 1, got {step}")
        items = read_camvid_split(root, split)[:: int(step)]
        if frames is not None:
            if int(frames) < 1:
                raise InputError(f"data.frames: must be >= 1 or null, got {frames}")
            items = items[: int(frames)]
        self.items, self.split, self.step = items, split, int(step)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i):  # type: ignore[override]
        return self.items[i]

    def __iter__(self) -> Iterator[CamVidItem]:
        return iter(self.items)

    @staticmethod
    def to_tensors(image: np.ndarray, labels: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """(3, H, W) float32 RGB [0, 1] and (H, W) int64 labels from :meth:`CamVidItem.load`."""
        img = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).float() / 255.0
        return img, torch.from_numpy(labels.astype(np.int64))
