//! A dn16 frame kept as the 16-bit digital numbers it was stored as, linearised where it is
//! read: half the memory of `f32` planes (and a RAW frame's CFA samples kept the same way,
//! [`DnMosaic`]). At 16 MP an 11-frame dn16 set held 2.1 GB of `f32` planes, and on a virtual
//! machine most of decoding it was the kernel zeroing those fresh pages (perf: a quarter of
//! the whole solve's CPU samples in `clear_page_erms`).

use std::sync::Arc;

use super::{prefetch_at, RgbPlanes};

/// The three DN planes of one frame and what turns them into linear values: channel `c` of
/// pixel `i` is `(dn - black) / (white - black)` in `f32`, less the dark frame's linear value
/// there when one is attached. Every bit equals what linearising into `f32` planes and then
/// subtracting the dark frame's planes gives.
#[derive(Clone, Debug)]
pub struct DnSamples {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// R, G and B in DN, `width * height` each, row after row.
    pub dn: [Vec<u16>; 3],
    /// The DN of linear 0.
    black: f64,
    /// `1 / (white - black)`.
    scale: f64,
    /// The dark frame, subtracted as the values are read; shared by the frames of a set.
    pub dark: Option<Arc<Dark>>,
}

/// A dark frame as the light frames subtract it: kept as its DN like them, or as `f32`
/// planes (a dark frame decoded the long way).
#[derive(Clone, Debug)]
pub enum Dark {
    /// Linear R, G and B planes.
    Planes(RgbPlanes),
    /// 16-bit samples, linearised where read (with no dark frame of their own).
    Dn(DnSamples),
}

impl Dark {
    /// Width and height in pixels.
    pub fn size(&self) -> (usize, usize) {
        match self {
            Dark::Planes(p) => (p.width(), p.height()),
            Dark::Dn(d) => (d.width, d.height),
        }
    }

    /// Channel `c` of pixel `i`, linear.
    #[inline(always)]
    pub fn value(&self, c: usize, i: usize) -> f32 {
        match self {
            Dark::Planes(p) => p.channels()[c].data[i],
            Dark::Dn(d) => d.value(c, i),
        }
    }

    /// Starts loading the cache lines at pixel `i` of every channel.
    #[inline(always)]
    pub fn prefetch(&self, i: usize) {
        match self {
            Dark::Planes(p) => p.channels().iter().for_each(|p| prefetch_at(&p.data, i)),
            Dark::Dn(d) => d.prefetch(i),
        }
    }
}

impl DnSamples {
    /// A `width x height` frame of zero DN, linearised by the `black` and `white` levels.
    pub fn new(width: usize, height: usize, black: f64, white: f64) -> Self {
        DnSamples {
            width,
            height,
            dn: std::array::from_fn(|_| vec![0; width * height]),
            black,
            scale: 1.0 / (white - black),
            dark: None,
        }
    }

    /// The linear value of `dn`, before any dark frame: the arithmetic `raw::linear` uses
    /// for `f32` planes, so every bit is the same.
    #[inline(always)]
    pub fn linear(&self, dn: u16) -> f32 {
        ((dn as f64 - self.black) * self.scale) as f32
    }

    /// Channel `c` of pixel `i`, the dark frame subtracted.
    #[inline(always)]
    pub fn value(&self, c: usize, i: usize) -> f32 {
        let v = self.linear(self.dn[c][i]);
        match &self.dark {
            Some(dark) => v - dark.value(c, i),
            None => v,
        }
    }

    /// Starts loading the cache lines at pixel `i` of every channel (not the dark frame's,
    /// which the frames of a set share).
    #[inline(always)]
    pub fn prefetch(&self, i: usize) {
        self.dn.iter().for_each(|p| prefetch_at(p, i));
    }

    /// The frame as three `f32` planes, the dark frame subtracted.
    pub fn to_planes(&self) -> RgbPlanes {
        let mut out = RgbPlanes::new(self.width, self.height);
        let w = self.width;
        out.par_rows_mut(|y, rows| {
            for (c, row) in rows.into_iter().enumerate() {
                for (x, v) in row.iter_mut().enumerate() {
                    *v = self.value(c, y * w + x);
                }
            }
        });
        out
    }

    /// Checks the planes' lengths (and the dark frame's size) against the frame's size.
    pub fn check_size(&self) -> std::result::Result<(), String> {
        let n = self.width * self.height;
        if let Some(len) = self.dn.iter().map(Vec::len).find(|&len| len != n) {
            return Err(format!(
                "has {len} samples in a channel, its size {}x{} needs {n}",
                self.width, self.height
            ));
        }
        let Some(dark) = &self.dark else {
            return Ok(());
        };
        let whole = match &**dark {
            Dark::Planes(p) => p.channels().iter().all(|p| p.len() == n),
            Dark::Dn(d) => d.check_size().is_ok(),
        };
        let (w, h) = dark.size();
        if (w, h) != (self.width, self.height) || !whole {
            return Err(format!(
                "has a {w}x{h} dark frame, its size is {}x{}",
                self.width, self.height
            ));
        }
        Ok(())
    }
}

/// A RAW frame's CFA samples (one per pixel, whatever its channel) kept as the DN they were
/// decoded as, linearised where read: 2 bytes a sample where `f32` samples took 4, and no
/// second pass over the frame to write them. At 16 MP an 11-frame DNG stack held 700 MB of
/// `f32` samples, all of it fresh memory (see `alloc`).
///
/// Sample (`x`, `y`) is `(dn - black) * scale` with its CFA site's `black` and `scale`, in
/// `f32`, less the dark frame's linear sample there when one is attached: every bit what
/// `raw::pass` computes into `f32` samples and then subtracts.
#[derive(Clone, Debug, PartialEq)]
pub struct DnMosaic {
    /// Width in samples.
    pub width: usize,
    /// Height in samples.
    pub height: usize,
    /// The samples in DN, row after row.
    pub dn: Vec<u16>,
    /// Per CFA site (`[row parity][column parity]`): the DN of linear 0, and
    /// `1 / (white - black)`.
    pub sites: [[(f32, f32); 2]; 2],
    /// The dark frame's linear samples, subtracted where read; shared by a stack's frames.
    pub dark: Option<Arc<Vec<f32>>>,
}

impl DnMosaic {
    /// The linear value of `dn` at (`x`, `y`), before any dark frame.
    #[inline(always)]
    pub fn linear(&self, dn: u16, x: usize, y: usize) -> f32 {
        let (black, scale) = self.sites[y & 1][x & 1];
        (dn as f32 - black) * scale
    }

    /// Sample (`x`, `y`), the dark frame subtracted.
    #[inline(always)]
    pub fn value(&self, x: usize, y: usize) -> f32 {
        let i = y * self.width + x;
        let v = self.linear(self.dn[i], x, y);
        match &self.dark {
            Some(dark) => v - dark[i],
            None => v,
        }
    }

    /// Row `y`'s samples, the dark frame subtracted, into `out` (`width` long). Pairs of
    /// sites at a time, so that the loop vectorises.
    pub fn row_into(&self, y: usize, out: &mut [f32]) {
        let w = self.width;
        let row = &self.dn[y * w..(y + 1) * w];
        let [(b0, s0), (b1, s1)] = self.sites[y & 1];
        for (v, dn) in out.chunks_exact_mut(2).zip(row.chunks_exact(2)) {
            (v[0], v[1]) = ((dn[0] as f32 - b0) * s0, (dn[1] as f32 - b1) * s1);
        }
        if w % 2 == 1 {
            out[w - 1] = self.linear(row[w - 1], w - 1, y);
        }
        if let Some(dark) = &self.dark {
            for (v, d) in out[..w].iter_mut().zip(&dark[y * w..(y + 1) * w]) {
                *v -= d;
            }
        }
    }

    /// Starts loading the cache lines at sample `i` (not the dark frame's, which the frames
    /// of a stack share).
    #[inline(always)]
    pub fn prefetch(&self, i: usize) {
        prefetch_at(&self.dn, i);
    }

    /// Checks the samples' count (and the dark frame's) against the size.
    pub fn check_size(&self) -> std::result::Result<(), String> {
        let n = self.width * self.height;
        if self.dn.len() != n {
            return Err(format!(
                "has {} samples, its size {}x{} needs {n}",
                self.dn.len(),
                self.width,
                self.height
            ));
        }
        match &self.dark {
            Some(dark) if dark.len() != n => Err(format!(
                "has a dark frame of {} samples, its size {}x{} needs {n}",
                dark.len(),
                self.width,
                self.height
            )),
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_are_the_f32_planes_less_the_dark_bit_for_bit() {
        let (w, h) = (5, 3);
        let mut dn = DnSamples::new(w, h, 600.0, 15600.0);
        for (c, plane) in dn.dn.iter_mut().enumerate() {
            for (i, v) in plane.iter_mut().enumerate() {
                *v = (i * 977 + c * 5003) as u16 % 16000;
            }
        }
        let mut dark = RgbPlanes::new(w, h);
        dark.par_rows_mut(|y, rows| {
            for (c, row) in rows.into_iter().enumerate() {
                for (x, v) in row.iter_mut().enumerate() {
                    *v = 1e-3 * (x + 2 * y + c) as f32 - 2e-3;
                }
            }
        });
        let plain = dn.to_planes();
        // The dark frame as planes, and as DN (whose linear values are `plain`'s).
        let mut dark_dn = dn.clone();
        dark_dn
            .dn
            .iter_mut()
            .flatten()
            .for_each(|v| *v = (*v / 7).max(590));
        let dark_dn_planes = dark_dn.to_planes();
        dn.dark = Some(Arc::new(Dark::Dn(dark_dn)));
        let from_dn_dark = dn.to_planes();
        dn.dark = Some(Arc::new(Dark::Planes(dark.clone())));
        let planes = dn.to_planes();
        for c in 0..3 {
            for i in 0..w * h {
                let linear = ((dn.dn[c][i] as f64 - 600.0) * (1.0 / 15000.0)) as f32;
                assert_eq!(plain.channels()[c].data[i].to_bits(), linear.to_bits());
                let want = linear - dark.channels()[c].data[i];
                assert_eq!(planes.channels()[c].data[i].to_bits(), want.to_bits());
                assert_eq!(dn.value(c, i).to_bits(), want.to_bits());
                let want = linear - dark_dn_planes.channels()[c].data[i];
                assert_eq!(from_dn_dark.channels()[c].data[i].to_bits(), want.to_bits());
            }
        }
        assert!(dn.check_size().is_ok());
        dn.dn[1].pop();
        assert!(dn.check_size().unwrap_err().contains("14 samples"));
    }
}
