#!/usr/bin/env python3
"""The Python peer of `psscan solve` (issue 18): what a user writes with rawpy (LibRaw) and
NumPy. Half resolution (LibRaw's half-size: one RGB pixel per 2x2 CFA cell), the all-off
frame subtracted, distant lights (the unit vector from the table centre to each LED, from the
set's rig.toml), `np.linalg.pinv(L) @ I` on the luminance, one 16-bit normal-map PNG
(OpenGL convention, `n * 0.5 + 0.5`). No hash check, no noise model, no other maps.

Usage: peer_rawpy.py SET OUT_PNG [--decode-only]. Prints one JSON line of stage times:
{"decode_s", "solve_s", "write_s", "total_s", "frames", "width", "height"}; with
--decode-only it only decodes the frames (LibRaw's lossless-JPEG decode, raw_image) and
prints {"decode_s", "frames"}.
"""
import json
import os
import struct
import sys
import time
import tomllib
import zlib

import numpy as np
import rawpy


def light_files(set_dir):
    manifest = tomllib.load(open(os.path.join(set_dir, "manifest.toml"), "rb"))
    lights = sorted(
        (f["light"], f["file"]) for f in manifest["frames"] if f.get("kind") == "light"
    )
    dark = [f["file"] for f in manifest["frames"] if f.get("kind") == "dark"]
    rig = tomllib.load(open(os.path.join(set_dir, manifest["rig_file"]), "rb"))
    return [f for _, f in lights], (dark[0] if dark else None), rig


def decode_half(path):
    with rawpy.imread(path) as raw:
        rgb = raw.postprocess(
            half_size=True,
            no_auto_bright=True,
            output_bps=16,
            gamma=(1, 1),
            use_camera_wb=False,
            user_wb=[1, 1, 1, 1],
            output_color=rawpy.ColorSpace.raw,
        )
    return rgb.astype(np.float32)


def write_png16(path, rgb16):
    h, w, _ = rgb16.shape
    rows = rgb16.astype(">u2").reshape(h, w * 3).tobytes()
    stride = w * 6
    raw = b"".join(b"\x00" + rows[y * stride:(y + 1) * stride] for y in range(h))

    def chunk(kind, data):
        c = struct.pack(">I", len(data)) + kind + data
        return c + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 16, 2, 0, 0, 0)
    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
                + chunk(b"IDAT", zlib.compress(raw, 1)) + chunk(b"IEND", b""))


def main():
    set_dir, out = sys.argv[1], sys.argv[2]
    files, dark, rig = light_files(set_dir)
    t0 = time.perf_counter()
    if "--decode-only" in sys.argv:
        for f in ([dark] if dark else []) + files:
            with rawpy.imread(os.path.join(set_dir, f)) as raw:
                raw.raw_image.sum(dtype=np.uint64)
        print(json.dumps({"decode_s": time.perf_counter() - t0,
                          "frames": len(files) + (1 if dark else 0)}))
        return
    frames = [decode_half(os.path.join(set_dir, f)) for f in files]
    if dark:
        d = decode_half(os.path.join(set_dir, dark))
        frames = [f - d for f in frames]
    t1 = time.perf_counter()
    h, w, _ = frames[0].shape
    lum = np.stack([f @ np.array([0.2126, 0.7152, 0.0722], np.float32) for f in frames])
    lum = lum.reshape(len(frames), -1)
    leds = np.array([led["position_m"] for led in rig["leds"]], np.float64)
    directions = leds / np.linalg.norm(leds, axis=1, keepdims=True)
    g = np.linalg.pinv(directions).astype(np.float32) @ lum
    n = g / np.maximum(np.linalg.norm(g, axis=0, keepdims=True), 1e-12)
    t2 = time.perf_counter()
    rgb16 = np.round((np.clip(n.T, -1, 1) * 0.5 + 0.5) * 65535).astype(np.uint16)
    write_png16(out, rgb16.reshape(h, w, 3))
    t3 = time.perf_counter()
    print(json.dumps({"decode_s": t1 - t0, "solve_s": t2 - t1, "write_s": t3 - t2,
                      "total_s": t3 - t0, "frames": len(files), "width": w, "height": h}))


if __name__ == "__main__":
    main()
