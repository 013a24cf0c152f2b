"""The shipped network weights (see MODEL_CARD.md), installed with the package as ``monostixels.models``."""
