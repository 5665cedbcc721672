"""Time to load a capture: the 96 16-bit RGB PNG files of the DiLiGenT ball (issue 11).

Issue 11 measured about 44 s for this load when PNG files were unfiltered in pure Python; the
decoder has since moved to Rust (several files in parallel, GIL released). This prints the
median over ``--repeats`` runs of the whole ``captures.load_diligent(..., load=True)`` (decode,
float32 conversion into one preallocated stack, light intensities) and of the decode alone::

    python benchmarks/loading.py [--repeats 5] [--folder ../shared/data/diligent_ball/ballPNG]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import nplps
from nplps import captures

DEFAULT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "diligent_ball" / "ballPNG"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", type=Path, default=DEFAULT)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    files = sorted(p for p in args.folder.glob("[0-9]*.png"))
    whole, decode = [], []
    for _ in range(args.repeats):
        t = time.perf_counter()
        capture = captures.load_diligent(args.folder, load=True)
        whole.append(time.perf_counter() - t)
        t = time.perf_counter()
        nplps._core.read_pngs([str(f) for f in files], 1 << 28)
        decode.append(time.perf_counter() - t)
    assert capture.images is not None
    k, h, w = capture.images.shape[:3]
    print(f"{k} images of {w} x {h} pixels, {capture.images.nbytes / 1e6:.0f} MB as float32")
    for name, times in (("load_diligent(load=True)", whole), ("PNG decode alone", decode)):
        spread = f"min {min(times):.2f}, max {max(times):.2f}"
        print(f"{name + ':':26s} median {statistics.median(times):.2f} s ({spread})")
    print(f"against the 44 s of issue 11: {44.0 / statistics.median(whole):.0f}x")


if __name__ == "__main__":
    main()
