#!/usr/bin/env python3
"""LibRaw's RAW decode time on a set's DNG files, for comparison with psscan's (issue 18).

Decodes every `*.dng` in SET_DIR with LibRaw (through rawpy: `raw_image`, the undeveloped
samples, which is what psscan's rawler decode produces), one file after another on one thread,
three rounds, and prints the best round's time per frame. psscan's own figure is the `decode`
row of `psscan solve SET_DIR --out OUT --timings` (its "busy" seconds over the frame count is
the per-frame time on one thread).

Usage: libraw_decode.py SET_DIR      (needs rawpy: pip install rawpy)
"""
import glob
import os
import sys
import time

import rawpy


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    files = sorted(glob.glob(os.path.join(sys.argv[1], "*.dng")))
    if not files:
        sys.exit(f"libraw_decode: no .dng files in {sys.argv[1]}")
    best = None
    for _ in range(3):
        start = time.perf_counter()
        for path in files:
            with rawpy.imread(path) as raw:
                samples = raw.raw_image.copy()
        elapsed = time.perf_counter() - start
        best = elapsed if best is None else min(best, elapsed)
    print(f"LibRaw (rawpy) decode of {len(files)} DNGs on one thread: best of 3 rounds "
          f"{best:.3f} s, {best / len(files) * 1000:.0f} ms per frame "
          f"({samples.shape[1]}x{samples.shape[0]} samples)")


if __name__ == "__main__":
    main()
