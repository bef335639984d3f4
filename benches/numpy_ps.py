#!/usr/bin/env python3
"""NumPy peer for `psscan bench`: the same four least-squares solves (R, G, B, luminance) with
distant lights, as a NumPy user writes them: `np.linalg.pinv(L) @ I`.

Usage: numpy_ps.py DIR. DIR holds `meta.json` ({"width", "height", "lights", "directions",
"intensities", "weights", "repeats"}) and `frames.f32`: float32 planes in the order channel
(R, G, B), light, pixel (so `I[c]` is a contiguous lights x pixels matrix). Writes the unit
normals of the last run to `DIR/normal.f32` (3 x pixels) and prints one JSON line:
{"solve_s": median time of the four solves, "total_s": median time of solves + normalising +
albedo, "numpy": version, "threads": ...}. The file read is not timed.
"""
import json
import os
import sys
import time

import numpy as np


def main():
    d = sys.argv[1]
    meta = json.load(open(os.path.join(d, "meta.json")))
    k, n = meta["lights"], meta["width"] * meta["height"]
    frames = np.fromfile(os.path.join(d, "frames.f32"), dtype=np.float32).reshape(3, k, n)
    directions = np.asarray(meta["directions"], dtype=np.float64)
    intensities = np.asarray(meta["intensities"], dtype=np.float64)
    w = np.asarray(meta["weights"], dtype=np.float32)
    # Per channel, the light intensities fold into the pseudo-inverse: I'_k = I_k / e_k.
    pinv = np.linalg.pinv(directions)  # 3 x K
    p = [(pinv / intensities[:, c][None, :]).astype(np.float32) for c in range(3)]
    p_lum = sum(w[c] * p[c] for c in range(3)).astype(np.float32)
    solve_times, total_times = [], []
    normal = None
    for _ in range(meta["repeats"]):
        t0 = time.perf_counter()
        n_rgb = [p[c] @ frames[c] for c in range(3)]
        lum = w[0] * frames[0] + w[1] * frames[1] + w[2] * frames[2]
        n_lum = p_lum @ lum
        t1 = time.perf_counter()
        length = np.linalg.norm(n_lum, axis=0)
        normal = n_lum / np.maximum(length, 1e-12)
        albedo = [np.einsum("ij,ij->j", n_rgb[c], normal) for c in range(3)]
        t2 = time.perf_counter()
        del albedo
        solve_times.append(t1 - t0)
        total_times.append(t2 - t0)
    normal.astype(np.float32).tofile(os.path.join(d, "normal.f32"))
    print(json.dumps({
        "solve_s": float(np.median(solve_times)),
        "total_s": float(np.median(total_times)),
        "numpy": np.__version__,
        "threads": os.cpu_count(),
    }))


if __name__ == "__main__":
    main()
