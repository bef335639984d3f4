#!/usr/bin/env python3
"""Independent reference for psscan's DiLiGenT test (tests/diligent.rs): per-pixel least
squares on the Rec. 709 luminance with numpy, over all lights (the README's L2 column) and
over the lights whose luminance is above zero (what psscan's dark-measurement rule keeps on
these noise-free 16-bit renders). Prints the mean angular error over the mask in degrees.

    python3 benches/diligent_reference.py ../shared/data/bunny-diligent/bunny_lambert

Needs numpy, pillow and pypng. Reads Normal_gt.mat (MATLAB v5, uncompressed double) itself.
"""
import struct
import sys

import numpy as np
import png
from PIL import Image


def read_png16(path):
    width, height, rows, info = png.Reader(filename=path).asDirect()
    data = np.vstack([np.array(row, dtype=np.float64) for row in rows])
    return data.reshape(height, width, info["planes"])


def read_normal_gt(path, height, width):
    raw = open(path, "rb").read()
    tag = struct.pack("<II", 9, height * width * 3 * 8)  # miDOUBLE, byte count
    start = raw.index(tag) + 8
    values = np.frombuffer(raw[start:start + height * width * 3 * 8], dtype="<f8")
    return values.reshape(3, width, height).transpose(2, 1, 0)  # MATLAB is column-major


def mean_error(normals, truth):
    normals = normals / np.linalg.norm(normals, axis=0, keepdims=True)
    cos = np.clip((normals * truth).sum(axis=0), -1.0, 1.0)
    return np.degrees(np.arccos(cos)).mean()


def main(folder):
    names = open(f"{folder}/filenames.txt").read().split()
    lights = np.loadtxt(f"{folder}/light_directions.txt")
    images = np.stack([read_png16(f"{folder}/{n}") for n in names])
    mask = np.array(Image.open(f"{folder}/mask.png")) > 0
    height, width = mask.shape
    truth = read_normal_gt(f"{folder}/Normal_gt.mat", height, width)[mask].T
    weights = np.array([0.2126, 0.7152, 0.0722])
    lum = (images * weights).sum(axis=3)[:, mask]
    every = np.linalg.lstsq(lights, lum, rcond=None)[0]
    lit = np.zeros_like(every)
    for i in range(lum.shape[1]):
        keep = lum[:, i] > 0
        lit[:, i] = np.linalg.lstsq(lights[keep], lum[keep, i], rcond=None)[0]
    print(f"all lights {mean_error(every, truth):.4f} deg, lit lights only {mean_error(lit, truth):.4f} deg")


if __name__ == "__main__":
    main(sys.argv[1])
