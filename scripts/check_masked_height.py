#!/usr/bin/env python3
"""Peer for psscan derive's masked height: the least-squares surface over the solved pixels
(differences between linked 4-neighbours = mean of their slopes, slopes clamped to 2 as psscan
does), by SciPy's sparse direct solve, compared with psscan's height.exr over the largest
connected part of the mask (offset removed). Needs numpy, scipy and OpenEXR.

usage: check_masked_height.py SOLVE_DIR DERIVE_DIR   (prints one JSON line)
"""
import sys, json, numpy as np, OpenEXR, scipy.sparse as sp, scipy.sparse.linalg as spl
from scipy.sparse.csgraph import connected_components
def load(p, names):
    f = OpenEXR.InputFile(p); h = f.header(); dw = h['dataWindow']
    w, hh = dw.max.x + 1, dw.max.y + 1
    return [np.frombuffer(f.channel(n), dtype=np.float32).reshape(hh, w).astype(np.float64) for n in names]
solve, derived = sys.argv[1], sys.argv[2]
nx, ny, nz = load(f"{solve}/normal.exr", "RGB")
status, = load(f"{solve}/confidence.exr", ["status"])
z_ps, = load(f"{derived}/height.exr", ["height"])
solved = status == 0
H, W = solved.shape
zc = np.maximum(nz, 1e-3)
p = np.clip(-nx / zc, -2, 2); q = np.clip(ny / zc, -2, 2)
idx = -np.ones((H, W), int); idx[solved] = np.arange(solved.sum())
rows, cols, vals, rhs = [], [], [], []
eq = 0
for (dy, dx, s) in [(0, 1, p), (1, 0, q)]:
    a = solved[:H - dy, :W - dx] & solved[dy:, dx:]
    i = idx[:H - dy, :W - dx][a]; j = idx[dy:, dx:][a]
    g = 0.5 * (s[:H - dy, :W - dx][a] + s[dy:, dx:][a])
    n = len(i); e = np.arange(eq, eq + n)
    rows += [e, e]; cols += [j, i]; vals += [np.ones(n), -np.ones(n)]; rhs.append(g); eq += n
D = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(eq, solved.sum()))
b = np.concatenate(rhs)
L = (D.T @ D).tocsr(); r = D.T @ b
ncomp, labels = connected_components(L, directed=False)
# Pin one pixel per component (the null space), solve directly.
pins = [np.argmax(labels == c) for c in range(ncomp)]
L = L.tolil()
for k in pins:
    L[k, :] = 0; L[k, k] = 1; r[k] = 0
z = spl.spsolve(L.tocsr(), r)
err = []
for c in range(ncomp):
    m = labels == c
    d = z_ps[solved][m] - z[m]
    err.append((m.sum(), d - d.mean()))
big = max(err, key=lambda e: e[0])
zr = z[labels == np.argmax(np.bincount(labels))]
print(json.dumps({"components": int(ncomp), "largest": int(big[0]), "rms_px": float(np.sqrt((big[1]**2).mean())),
                  "max_px": float(np.abs(big[1]).max()), "peer_range_px": float(zr.max() - zr.min()),
                  "psscan_range_px": float(z_ps[solved].max() - z_ps[solved].min())}))
