"""docs/img/scooping.png: frames of an ice-cream scooping run side by side (docs/tasks.md).

    python experiments/scooping_figure.py <run>/frames docs/img/scooping.png

The frames are the ones ``stage=simulate task=scooping`` renders (frames/NN_<phase>.png); by default the start, the
first scoop's tilt, the second's advance and the final clusters.
"""
import argparse
from pathlib import Path

import imageio.v2 as imageio
import numpy as np


def frame_strip(frames_dir, out, names=("00_", "scoop1_tilt", "scoop2_advance", "final")) -> None:
    """docs/img/scooping.png: the run's frames (frames/NN_<phase>.png) whose names contain ``names``, side by side."""
    files = sorted(Path(frames_dir).glob("*.png"))
    imgs = [imageio.imread(next(f for f in files if key in f.name))[..., :3] for key in names]
    h = min(i.shape[0] for i in imgs)
    row = np.concatenate([i[:h] for i in imgs], axis=1)
    ink = np.flatnonzero((row < 250).any(axis=(1, 2)))  # drop blank rows (titles and scenes stay)
    keep = np.unique(np.concatenate([np.arange(max(r - 4, 0), min(r + 5, h)) for r in ink]))
    imageio.imwrite(out, row[keep])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("frames_dir", help="the run's frames directory (<run>/frames)")
    ap.add_argument("out", help="the picture to write (.png)")
    args = ap.parse_args(argv)
    frame_strip(args.frames_dir, args.out)


if __name__ == "__main__":
    main()
