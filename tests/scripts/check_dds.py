#!/usr/bin/env python3
"""Independent check of psscan's DDS output: parses the DDS header and mip layout itself,
decodes every level with Pillow's BCn decoder, and compares the normals with its own NumPy
box-filtered, renormalised mips of the 16-bit normal.png psscan wrote beside them.

usage: check_dds.py DERIVE_DIR   (prints one JSON line; exit 0 pass, 1 fail, 77 skip)
"""
import json
import math
import struct
import sys

try:
    import numpy as np
    from PIL import Image
except ImportError as e:  # the Rust test turns this into a skip message
    print(json.dumps({"skip": f"needs numpy and Pillow: {e}"}))
    sys.exit(77)

DXGI = {80: ("BC4_UNORM", 8, 4), 83: ("BC5_UNORM", 16, 5), 99: ("BC7_UNORM_SRGB", 16, 7)}


def read_dds(path):
    data = open(path, "rb").read()
    if data[:4] != b"DDS ":
        raise ValueError(f"{path}: not a DDS file")
    height, width = struct.unpack_from("<II", data, 12)
    mips = struct.unpack_from("<I", data, 28)[0] or 1
    fourcc = data[84:88]
    if fourcc != b"DX10":
        raise ValueError(f"{path}: expected a DX10 header, got {fourcc!r}")
    dxgi = struct.unpack_from("<I", data, 128)[0]
    name, block, n = DXGI[dxgi]
    offset = 148
    levels = []
    for level in range(mips):
        w, h = max(1, width >> level), max(1, height >> level)
        bw, bh = (w + 3) // 4, (h + 3) // 4
        size = bw * bh * block
        raw = data[offset:offset + size]
        if len(raw) != size:
            raise ValueError(f"{path}: level {level} truncated")
        # Decode whole blocks, then crop to the level's size.
        img = Image.frombytes({4: "L", 5: "RGB", 7: "RGBA"}[n], (bw * 4, bh * 4), raw, "bcn", (n,))
        levels.append(np.asarray(img)[:h, :w])
        offset += size
    if offset != len(data):
        raise ValueError(f"{path}: {len(data) - offset} bytes after the last level")
    return name, width, height, levels


def box_mips(n):
    out = [n]
    while out[-1].shape[0] > 1 or out[-1].shape[1] > 1:
        a = out[-1]
        h, w = a.shape[:2]
        nh, nw = max(1, h // 2), max(1, w // 2)
        a = a[: nh * 2 if h > 1 else 1, : nw * 2 if w > 1 else 1]
        a = a.reshape(nh, a.shape[0] // nh, nw, a.shape[1] // nw, 3).mean(axis=(1, 3))
        out.append(a)
    return [m / np.linalg.norm(m, axis=2, keepdims=True) for m in out]


def angle_error_deg(xc, yc, ref):
    """Mean angle between unit normals rebuilt from X/Y codes (Z = sqrt(1 - x^2 - y^2), as a
    shader does) and the reference normals."""
    return float(angle_errors_deg(xc, yc, ref).mean())


def angle_errors_deg(xc, yc, ref):
    """Per-pixel angle, degrees, between normals rebuilt from X/Y codes and the reference."""
    x = xc / 255.0 * 2 - 1
    y = yc / 255.0 * 2 - 1
    z = np.sqrt(np.clip(1 - x * x - y * y, 0, 1))
    n = np.stack([x, y, z], axis=2)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    cos = np.clip((n * ref).sum(axis=2), -1, 1)
    return np.degrees(np.arccos(cos))


def bc5_bound_deg(ref):
    """Mean over pixels of the worst angle BC5 may cost there: each 4x4 block stores each of
    X and Y as two endpoints and six values between them (BC4), so a value may be off by half
    a palette step, (block max - block min) / 14, plus half a code for the 8-bit endpoints.
    The worst corner of that X/Y box, rebuilt with Z as a shader does, against the reference."""
    codes = (ref[..., :2] * 0.5 + 0.5) * 255.0
    h, w = codes.shape[:2]
    half = np.zeros_like(codes)
    for by in range(0, h, 4):
        for bx in range(0, w, 4):
            block = codes[by:by + 4, bx:bx + 4]
            span = block.max(axis=(0, 1)) - block.min(axis=(0, 1))
            half[by:by + 4, bx:bx + 4] = span / 14.0 + 0.5
    worst = np.zeros((h, w))
    for sx in (-1, 1):
        for sy in (-1, 1):
            xc = np.clip(codes[..., 0] + sx * half[..., 0], 0, 255)
            yc = np.clip(codes[..., 1] + sy * half[..., 1], 0, 255)
            worst = np.maximum(worst, angle_errors_deg(xc, yc, ref))
    return float(worst.mean())


def main(folder):
    result = {}
    png = np.asarray(Image.open(f"{folder}/normal.png")).astype(np.float64)
    scale = 65535.0 if png.max() > 255 else 255.0
    source = png[..., :3] / scale * 2.0 - 1.0
    name, w, h, levels = read_dds(f"{folder}/normal.dds")
    expected = box_mips(source)
    want_levels = int(math.floor(math.log2(max(w, h)))) + 1
    errors = []
    # The same reconstruction from the reference's own 8-bit X/Y codes (no block
    # compression): separates storage quantisation from BC5's block error.
    quantised = []
    # Each level must be within 1.5 deg mean (the figure) or, where the map's 4x4
    # blocks vary too much for BC5 to hold that, within BC5's own worst case for them.
    allowed = []
    for lvl, (dec, ref) in enumerate(zip(levels, expected)):
        errors.append(angle_error_deg(dec[..., 0], dec[..., 1], ref))
        codes = np.round((ref[..., :2] * 0.5 + 0.5) * 255.0)
        quantised.append(angle_error_deg(codes[..., 0], codes[..., 1], ref))
        allowed.append(max(1.5, bc5_bound_deg(ref)))
    result["normal"] = {"format": name, "size": [w, h], "levels": len(levels),
                        "levels_expected": want_levels, "mean_error_deg": errors,
                        "mean_error_8bit_only_deg": quantised, "allowed_deg": allowed}
    name, aw, ah, alevels = read_dds(f"{folder}/albedo.dds")
    ref = np.asarray(Image.open(f"{folder}/albedo.png")).astype(np.float64)
    ref = ref[..., :3] / (65535.0 if ref.max() > 255 else 255.0)
    diff = float(np.abs(alevels[0][..., :3] / 255.0 - ref).mean())
    result["albedo"] = {"format": name, "levels": len(alevels), "mean_abs_error": diff}
    ok = (len(levels) == want_levels and all(e < a for e, a in zip(errors, allowed))
          and len(alevels) == want_levels and diff < 3.0 / 255.0)
    result["pass"] = ok
    print(json.dumps(result))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
