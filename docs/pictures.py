"""Regenerate the pictures of README.md and docs/ from the shared data samples.

    python docs/pictures.py                  # needs ../shared/data (KITTI raw, DDAD); a few minutes

Each picture is `monostixels run`'s (or `demo`'s) own output for one frame, scaled down:

- docs/kitti_figure.png: KITTI raw drive 0028, frame 1111, `run`'s defaults (figure.png);
- docs/ddad_figure.png: the DDAD scene, first pair, where the camera stands still (figure.png);
- docs/demo_figure.png: `monostixels demo` (figure.png, like the paper's).
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2

DOCS = Path(__file__).resolve().parent
RUNS = {
    "kitti_figure.png": (["run", "data=kitti_raw", "data.root=../shared/data/kitti_raw", "data.only_labelled=true",
                          "data.frames=1"], 1600),
    "ddad_figure.png": (["run", "data=ddad", "data.root=../shared/data/ddad_dgp", "data.frames=1"], 1400),
    "demo_figure.png": (["demo"], 2400),
}


def _figure(args: list[str], out: Path) -> Path:
    """Run ``monostixels ARGS outputs=OUT`` and return the figure.png it wrote."""
    subprocess.run([sys.executable, "-m", "monostixels.cli", *args, f"outputs={out}"], check=True,
                   cwd=DOCS.parent)
    (fig,) = sorted(out.rglob("figure.png"))
    return fig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", nargs="*", default=list(RUNS), choices=list(RUNS), help="pictures to make")
    names = ap.parse_args().only
    for name in names:
        args, width = RUNS[name]
        with tempfile.TemporaryDirectory() as tmp:
            img = cv2.imread(str(_figure(args, Path(tmp))))
        if img.shape[1] > width:  # scaled down for the page; INTER_AREA keeps the thin borders readable
            img = cv2.resize(img, (width, round(img.shape[0] * width / img.shape[1])), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(DOCS / name), img)
        print(f"wrote {DOCS / name} ({img.shape[1]}x{img.shape[0]})")


if __name__ == "__main__":
    main()
