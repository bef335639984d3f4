#!/usr/bin/env python3
"""How well published demosaics recover a synthetic set's albedo colour (issue 13): the
ceiling of "demosaic the stack's sum, take the colour ratios from it".

It builds, from a synthetic set's ground truth (truth/albedo.exr, truth/normal.exr), the
white-balanced sum of the frames as a perfect sensor would record it (every pixel's albedo
times its summed shading under ten lights at 45 degrees, no noise), samples it as an RGGB
mosaic, demosaics that with each peer, and scores the albedo each pixel would get: its own
channel exact, the missing ones from the peer's colour ratios. The figure is the mean relative
albedo error over all pixels and channels, as `psscan solve` reports it against ground truth.

Peers: bilinear, Malvar (2004) and Menon (2007, DDFAPD) from colour-demosaicing, OpenCV's
bilinear, VNG and edge-aware (EA) demosaics. A dev script, not part of `make test`; needs
numpy, OpenEXR, opencv-python-headless and colour-demosaicing.

With a solve's output folder as well, it splits psscan's own albedo error by material (each
true chromaticity: its share of the pixels and of the error sum, and its largest patch) and by
whether a pixel's channel is observable at all: a channel is unobservable at a pixel when the connected
patch of the pixel's material (its true chromaticity: its thread, or a hole in the weave showing the ground)
holds no CFA site of that channel, so no sample anywhere in the patch measured it; any
demosaic then takes it from another material. Needs scipy too.

With a half-resolution solve's output folder as well (`psscan solve SET --resolution half`),
it scores the issue's other suggestion, the half-resolution chroma: each pixel's own channel
(exact, as for the peers) times the colour ratios of the half-resolution albedo, bilinearly
upsampled to the pixel (the 2x2 cell's centre is its sample position).

Usage: demosaic_peers.py SET [SOLVE_OUT [HALF_OUT]]   (SET written by `psscan synth`, any
encoding)
"""
import sys
import warnings

import numpy as np
import OpenEXR
import Imath


def load(path):
    f = OpenEXR.InputFile(path)
    dw = f.header()["dataWindow"]
    w, h = dw.max.x - dw.min.x + 1, dw.max.y - dw.min.y + 1
    chan = lambda c: np.frombuffer(f.channel(c, Imath.PixelType(Imath.PixelType.FLOAT)),
                                   dtype=np.float32).reshape(h, w)
    return np.stack([chan(c) for c in "RGB"], -1).astype(np.float64)


def main():
    warnings.filterwarnings("ignore")
    import colour_demosaicing as cd
    import cv2

    set_dir = sys.argv[1]
    albedo = load(f"{set_dir}/truth/albedo.exr")
    normal = load(f"{set_dir}/truth/normal.exr")
    h, w, _ = albedo.shape
    azimuth = np.radians(np.arange(10) * 36.0)
    elevation = np.radians(45.0)
    lights = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                       np.full(10, np.sin(elevation))], -1)
    shading = np.clip(normal @ lights.T, 0, None).sum(-1)
    stack_sum = albedo * shading[..., None]
    site = np.zeros((h, w), int)  # RGGB
    site[0::2, 1::2] = 1
    site[1::2, 0::2] = 1
    site[1::2, 1::2] = 2
    mosaic = np.take_along_axis(stack_sum, site[..., None], -1)[..., 0]
    own = np.take_along_axis(albedo, site[..., None], -1)[..., 0]

    def score(rgb):
        rgb = np.asarray(rgb, np.float64)
        own_channel = np.take_along_axis(rgb, site[..., None], -1)
        estimate = own[..., None] * rgb / own_channel
        error = np.abs(estimate / albedo - 1)
        error[~np.isfinite(error)] = 0
        return error.mean()

    m16 = np.clip(mosaic / mosaic.max() * 65535, 0, 65535).astype(np.uint16)
    peers = {
        "bilinear (colour-demosaicing)": lambda: cd.demosaicing_CFA_Bayer_bilinear(mosaic, "RGGB"),
        "Malvar 2004": lambda: cd.demosaicing_CFA_Bayer_Malvar2004(mosaic, "RGGB"),
        "Menon 2007 (DDFAPD)": lambda: cd.demosaicing_CFA_Bayer_Menon2007(mosaic, "RGGB"),
        "OpenCV bilinear": lambda: cv2.cvtColor(m16, cv2.COLOR_BayerRGGB2RGB),
        "OpenCV VNG (8-bit)": lambda: cv2.cvtColor((m16 >> 8).astype(np.uint8),
                                                   cv2.COLOR_BayerRGGB2RGB_VNG),
        "OpenCV edge-aware": lambda: cv2.cvtColor(m16, cv2.COLOR_BayerRGGB2RGB_EA),
    }
    print(f"{set_dir}: {w}x{h}, noise-free RGGB mosaic of the stack's sum")
    for name, run in peers.items():
        print(f"  {name:<32} mean relative albedo error {100 * score(run()):6.2f} %")
    if len(sys.argv) > 2:
        observability(albedo, site, load(f"{sys.argv[2]}/albedo.exr"))
    if len(sys.argv) > 3:
        # Bilinear at exactly twice the size (cell i's value at pixel 2 i + 0.5, held beyond
        # the outer cell centres), cropped to the full size where the last cell is partial.
        cells = load(f"{sys.argv[3]}/albedo.exr")
        half = cv2.resize(cells, None, fx=2, fy=2, interpolation=cv2.INTER_LINEAR)[:h, :w]
        print(f"  psscan's half-resolution colour ratios, bilinear: mean relative albedo error "
              f"{100 * score(half):.2f} %")


def observability(albedo, site, solved):
    """psscan's albedo error split by whether each pixel's channel is observable."""
    from scipy.ndimage import label

    error = np.abs(solved / albedo - 1)
    error[~np.isfinite(error)] = 0
    # Patches of one material (4-connected): one chromaticity (the fibre texture scales a
    # material's channels together), compared to 1 %.
    chroma = albedo / np.maximum(albedo.sum(-1, keepdims=True), 1e-12)
    key = np.round(chroma / 0.01).astype(np.int64)
    colour_id = np.unique(key.reshape(-1, 3), axis=0, return_inverse=True)[1].reshape(site.shape)
    observable = np.zeros(albedo.shape, bool)
    for cid in np.unique(colour_id):
        patches, n = label(colour_id == cid)
        if n == 0:
            continue
        for c in range(3):
            seen = np.zeros(n + 1, bool)
            seen[np.unique(patches[(patches > 0) & (site == c)])] = True
            observable[..., c] |= (patches > 0) & seen[patches]
    total = error.sum()
    blind = ~observable
    print(f"  psscan: mean relative albedo error {100 * error.mean():.2f} %")
    print(f"    channels never sampled in their patch: {100 * blind.mean():.2f} % of "
          f"pixel-channels, {100 * error[blind].sum() / total:.0f} % of the error sum "
          f"(their mean error {100 * error[blind].mean():.0f} %)")
    print(f"    over the observable ones the mean is {100 * error[observable].mean():.2f} %")
    by_material(albedo, colour_id, error)


def by_material(albedo, colour_id, error):
    """psscan's albedo error split by material (one true chromaticity): a material seen only
    through one- and two-pixel holes has channels no sample of it measured, and its share of
    the error shows how much of the mean any local demosaic can win back."""
    from scipy.ndimage import label

    total = error.sum()
    print("    by material (true albedo, its pixels' share of the image, its mean error, its "
          "share of the error sum, its largest 4-connected patch):")
    ids, counts = np.unique(colour_id, return_counts=True)
    for cid in ids[np.argsort(-counts)]:
        mask = colour_id == cid
        if mask.mean() < 0.001:
            continue
        patches, n = label(mask)
        largest = np.bincount(patches.ravel())[1:].max() if n else 0
        mean_albedo = albedo[mask].mean(0)
        print(f"      ({mean_albedo[0]:.3f}, {mean_albedo[1]:.3f}, {mean_albedo[2]:.3f}) "
              f"{100 * mask.mean():5.1f} % of pixels, error {100 * error[mask].mean():6.2f} %, "
              f"{100 * error[mask].sum() / total:3.0f} % of the error sum, "
              f"largest patch {largest} px")


if __name__ == "__main__":
    main()
