"""Semantic classes, stixel types and colours (paper Table I, docs/conventions.md, section 2)."""
from __future__ import annotations

__all__ = [
    "CLASS_NAMES",
    "NUM_CLASSES",
    "IGNORE_LABEL",
    "GROUND",
    "STATIC_OBJECT",
    "DYNAMIC_OBJECT",
    "SKY",
    "TYPE_NAMES",
    "NUM_TYPES",
    "TYPE_CLASSES",
    "CLASS_TYPE",
    "PALETTE",
    "TYPE_PALETTE",
]

#: The 10 classes, ids 0..9, in this order everywhere (scores, labels, ONNX outputs).
CLASS_NAMES: tuple[str, ...] = (
    "road", "sidewalk", "terrain", "building", "pole",
    "vegetation", "vehicle", "two_wheeler", "person", "sky",
)
NUM_CLASSES = len(CLASS_NAMES)
#: Label value of pixels without a class (never scored).
IGNORE_LABEL = 255

GROUND, STATIC_OBJECT, DYNAMIC_OBJECT, SKY = 0, 1, 2, 3
TYPE_NAMES: tuple[str, ...] = ("ground", "static_object", "dynamic_object", "sky")
NUM_TYPES = len(TYPE_NAMES)
#: Classes allowed for each stixel type (paper Table I).
TYPE_CLASSES: tuple[tuple[int, ...], ...] = ((0, 1, 2), (3, 4, 5), (6, 7, 8), (9,))
CLASS_TYPE: tuple[int, ...] = tuple(
    next(k for k, cs in enumerate(TYPE_CLASSES) if c in cs) for c in range(NUM_CLASSES)
)

#: Cityscapes palette (RGB) for our 10 classes.
PALETTE: tuple[tuple[int, int, int], ...] = (
    (128, 64, 128),   # road
    (244, 35, 232),   # sidewalk
    (152, 251, 152),  # terrain
    (70, 70, 70),     # building
    (153, 153, 153),  # pole
    (107, 142, 35),   # vegetation
    (0, 0, 142),      # vehicle (Cityscapes "car")
    (119, 11, 32),    # two_wheeler (Cityscapes "bicycle")
    (220, 20, 60),    # person
    (70, 130, 180),   # sky
)
#: Colours of the stixel types in overlays (RGB).
TYPE_PALETTE: tuple[tuple[int, int, int], ...] = (
    (128, 64, 128), (70, 70, 70), (0, 0, 230), (70, 130, 180),
)
