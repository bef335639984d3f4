//! One pass over a decoded RAW frame's samples that does everything a light frame needs
//! before the stack is developed: linearisation (black and white level, saturation flags),
//! the counts the set's plausibility check reads, and at half resolution the dark-frame
//! subtraction and the 2x2 binning too.
//!
//! Why one pass: at 16 MP a frame's linear mosaic is 80 MB (`f32` samples and their flags).
//! Linearising, counting, subtracting and binning in separate passes read it four times, and
//! at half resolution the full-size linear mosaic is thrown away right after binning. Fresh
//! memory is expensive on the machines psscan runs on (a page fault and the kernel's zeroing
//! per page), so the half-resolution pass never makes the full-size mosaic at all.
//!
//! Each pass gives the same values, bit for bit, as [`Mosaic::linearize`],
//! [`LinearMosaic::subtract_shared`] and [`LinearMosaic::bin2x2`] in a row (the same
//! operations in the same order); the tests below hold it to that.

use rayon::prelude::*;

use super::mosaic::{bin_rows, LinearMosaic, Mosaic, Resolution, SampleRow};
use crate::error::Result;
use crate::plane::{DnMosaic, LightFrame};

/// What a pass counted over a light frame's own samples (before any dark frame is
/// subtracted), for `develop::check_plausible`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SampleCounts {
    /// Samples in the frame.
    pub samples: usize,
    /// Samples at or near the white level.
    pub clipped: usize,
    /// Samples below the pass's `below_black_floor` (`None`: no floor was given).
    pub below_floor: Option<usize>,
}

impl SampleCounts {
    fn plus(self, other: SampleCounts) -> SampleCounts {
        SampleCounts {
            samples: self.samples + other.samples,
            clipped: self.clipped + other.clipped,
            below_floor: match (self.below_floor, other.below_floor) {
                (Some(a), Some(b)) => Some(a + b),
                (a, b) => a.or(b),
            },
        }
    }
}

/// What a pass does besides linearising.
#[derive(Clone, Copy, Debug, Default)]
pub struct LinearPass<'a> {
    /// Subtracted sample by sample; a sample saturated in it is saturated in the result.
    pub dark: Option<&'a LinearMosaic>,
    /// Linear level under which a sample is counted as impossibly far below black (see
    /// `develop::below_black_floor`).
    pub below_black_floor: Option<f32>,
}

/// Per CFA site, the black level and the scale to linear units; and the saturation level.
struct Sites {
    scales: [[(f32, f32); 2]; 2],
    threshold: f32,
}

impl Sites {
    fn of(mosaic: &Mosaic) -> Sites {
        Sites {
            scales: mosaic
                .black
                .map(|row| row.map(|b| (b, 1.0 / (mosaic.white - b)))),
            threshold: mosaic.saturation_threshold(),
        }
    }

    /// Sample `raw` of row parity `y2` and column `x` in linear units, and whether it is
    /// saturated; as `Mosaic::linearize` computes them.
    #[inline(always)]
    fn linear(&self, raw: u16, x: usize, y2: usize) -> (f32, bool) {
        let (offset, scale) = self.scales[y2][x % 2];
        ((raw as f32 - offset) * scale, raw as f32 >= self.threshold)
    }
}

// Both passes run row by row in three loops, each simple enough for the
// compiler to vectorise (a loop that linearised, counted and subtracted per sample, with
// the options tested inside, took 6 ns a sample: most of a second per 16 MP set).

/// Row `row` (parity `y2`) linearised into `values`, its saturation flags into `saturated`.
fn linear_row(sites: &Sites, y2: usize, row: &[u16], values: &mut [f32], saturated: &mut [bool]) {
    let [(o0, s0), (o1, s1)] = sites.scales[y2];
    let threshold = sites.threshold;
    let pairs = row.chunks_exact(2).zip(values.chunks_exact_mut(2));
    for ((raw, v), sat) in pairs.zip(saturated.chunks_exact_mut(2)) {
        let (a, b) = (raw[0] as f32, raw[1] as f32);
        (v[0], v[1]) = ((a - o0) * s0, (b - o1) * s1);
        (sat[0], sat[1]) = (a >= threshold, b >= threshold);
    }
    if row.len() % 2 == 1 {
        let x = row.len() - 1;
        (values[x], saturated[x]) = sites.linear(row[x], x, y2);
    }
}

/// Adds a linearised row's clipped samples, and those below `floor` where given, to `counts`.
fn count_row(counts: &mut SampleCounts, values: &[f32], saturated: &[bool], floor: Option<f32>) {
    counts.clipped += saturated.iter().map(|&s| s as usize).sum::<usize>();
    if let (Some(below), Some(floor)) = (counts.below_floor.as_mut(), floor) {
        *below += values.iter().map(|&v| (v < floor) as usize).sum::<usize>();
    }
}

/// Subtracts a dark frame's row from a linearised row; a sample saturated in either is.
fn subtract_row(values: &mut [f32], saturated: &mut [bool], dark: &[f32], dark_saturated: &[bool]) {
    for (v, d) in values.iter_mut().zip(dark) {
        *v -= d;
    }
    for (s, d) in saturated.iter_mut().zip(dark_saturated) {
        *s |= d;
    }
}

fn empty_counts(pass: &LinearPass, samples: usize) -> SampleCounts {
    SampleCounts {
        samples,
        clipped: 0,
        below_floor: pass.below_black_floor.map(|_| 0),
    }
}

fn check_dark(mosaic: &Mosaic, dark: Option<&LinearMosaic>) -> Result<()> {
    match dark {
        Some(d) => d.check_same_layout(mosaic.width, mosaic.height, mosaic.pattern),
        None => Ok(()),
    }
}

impl Mosaic {
    /// The samples as linear values (per-site black subtracted, 1.0 at the white level) with
    /// their saturation flags: this module's `linearize` with nothing else to do. (Defined
    /// here, beside the pass that computes it, so `mosaic` need not import this module.)
    pub fn linearize(&self) -> Result<LinearMosaic> {
        Ok(linearize(self, LinearPass::default())?.0)
    }
}

/// Linearises `mosaic` and counts its samples for the plausibility check, subtracting
/// `pass.dark` where given: `mosaic.linearize()` then `LinearMosaic::subtract_shared`, in one
/// pass.
pub fn linearize(mosaic: &Mosaic, pass: LinearPass) -> Result<(LinearMosaic, SampleCounts)> {
    mosaic.validate()?;
    check_dark(mosaic, pass.dark)?;
    let sites = Sites::of(mosaic);
    let w = mosaic.width;
    let mut values = vec![0.0f32; mosaic.samples.len()];
    let mut saturated = vec![false; mosaic.samples.len()];
    let counts = values
        .par_chunks_mut(w)
        .zip(saturated.par_chunks_mut(w))
        .zip(mosaic.samples.par_chunks(w))
        .enumerate()
        .map(|(y, ((v, sat), row))| {
            let mut counts = empty_counts(&pass, w);
            linear_row(&sites, y % 2, row, v, sat);
            count_row(&mut counts, v, sat, pass.below_black_floor);
            if let Some(d) = pass.dark {
                let at = y * w..(y + 1) * w;
                subtract_row(v, sat, &d.values[at.clone()], &d.saturated[at]);
            }
            counts
        })
        .reduce(|| empty_counts(&pass, 0), SampleCounts::plus);
    let linear = LinearMosaic {
        width: mosaic.width,
        height: mosaic.height,
        pattern: mosaic.pattern,
        values,
        saturated,
        dn: None,
    };
    Ok((linear, counts))
}

/// [`linearize`] for a light frame of a full-resolution stack: the samples stay the DN they
/// were decoded as (moved out of `mosaic`), linearised where they are read ([`DnMosaic`], the
/// same arithmetic, so the same bits). Only the counts are taken here, and the saturation
/// flags written where some sample is saturated (a frame that clips nowhere gets none, see
/// [`LinearMosaic::saturated`]). A dark frame is subtracted later
/// (`LinearMosaic::subtract_shared`), so `pass.dark` must be `None`.
pub fn keep_dn(mosaic: Mosaic, pass: LinearPass) -> Result<(LinearMosaic, SampleCounts)> {
    mosaic.validate()?;
    assert!(
        pass.dark.is_none(),
        "a frame kept as DN subtracts its dark frame where read"
    );
    let sites = Sites::of(&mosaic);
    let w = mosaic.width;
    let dn = DnMosaic {
        width: mosaic.width,
        height: mosaic.height,
        dn: mosaic.samples,
        sites: sites.scales,
        dark: None,
    };
    let saturated_row = |y: usize, flags: &mut [bool]| {
        let row = &dn.dn[y * w..(y + 1) * w];
        for (s, &raw) in flags.iter_mut().zip(row) {
            *s = raw as f32 >= sites.threshold;
        }
    };
    // Counted without writing anything; the flags are written only if something clipped.
    if let Some(limits) = DnLimits::of(&sites, pass.below_black_floor) {
        let counts = (dn.dn.par_chunks(w.max(1)).enumerate())
            .map(|(y, row)| limits.count_row(row, y % 2, &pass))
            .reduce(|| empty_counts(&pass, 0), SampleCounts::plus);
        let saturated = saturation_flags(&dn, counts.clipped, &saturated_row);
        return Ok((linear_kept(&mosaic.pattern, dn, saturated), counts));
    }
    let counts = (0..mosaic.height)
        .into_par_iter()
        .map_init(
            || (Vec::new(), Vec::new()),
            |(values, flags), y| {
                let mut counts = empty_counts(&pass, w);
                flags.resize(w, false);
                saturated_row(y, flags);
                if pass.below_black_floor.is_some() {
                    values.resize(w, 0.0);
                    dn.row_into(y, values);
                }
                count_row(&mut counts, values, flags, pass.below_black_floor);
                counts
            },
        )
        .reduce(|| empty_counts(&pass, 0), SampleCounts::plus);
    let saturated = saturation_flags(&dn, counts.clipped, &saturated_row);
    Ok((linear_kept(&mosaic.pattern, dn, saturated), counts))
}

/// The saturation flags of a frame kept as DN: none when no sample clipped.
fn saturation_flags(
    dn: &DnMosaic,
    clipped: usize,
    saturated_row: &(impl Fn(usize, &mut [bool]) + Sync),
) -> Vec<bool> {
    if clipped == 0 {
        return Vec::new();
    }
    let mut saturated = vec![false; dn.dn.len()];
    (saturated.par_chunks_mut(dn.width.max(1)).enumerate())
        .for_each(|(y, flags)| saturated_row(y, flags));
    saturated
}

fn linear_kept(pattern: &[[u8; 2]; 2], dn: DnMosaic, saturated: Vec<bool>) -> LinearMosaic {
    LinearMosaic {
        width: dn.width,
        height: dn.height,
        pattern: *pattern,
        values: Vec::new(),
        saturated,
        dn: Some(dn),
    }
}

/// The counts of [`keep_dn`] as limits on the stored values: a site's linear value
/// `(dn - offset) * scale` and the test `dn as f32 >= threshold` only grow with `dn`, so the
/// samples under the floor are those under one DN per site, and the clipped ones those from
/// one DN up. Found by testing every 16-bit value once, so the counts are the linear tests'
/// exactly; and integer tests on the stored row count it without converting it (the
/// conversion was most of the count's 0.15 s of CPU per 16 MP set).
struct DnLimits {
    /// Per row parity and column parity: the values `0..below` lie under the floor (0 without
    /// a floor).
    below: [[u32; 2]; 2],
    /// The values from `clip` up are saturated.
    clip: u32,
}

impl DnLimits {
    /// `None` where a site's test is not a prefix of the 16-bit values (a NaN or a negative
    /// scale): the caller then tests each linear value.
    fn of(sites: &Sites, floor: Option<f32>) -> Option<DnLimits> {
        // The tests of `Sites::linear` itself (the flag negated: with a NaN threshold no
        // value is saturated), so the limits cannot drift from the linear values.
        let clip = prefix(|d| !sites.linear(d, 0, 0).1)?;
        let mut below = [[0u32; 2]; 2];
        if let Some(floor) = floor {
            for (y2, limits) in below.iter_mut().enumerate() {
                for (x2, limit) in limits.iter_mut().enumerate() {
                    *limit = prefix(|d| sites.linear(d, x2, y2).0 < floor)?;
                }
            }
        }
        Some(DnLimits { below, clip })
    }

    /// The counts of one stored row of parity `y2`.
    fn count_row(&self, row: &[u16], y2: usize, pass: &LinearPass) -> SampleCounts {
        let [b0, b1] = self.below[y2];
        let (mut below, mut clipped) = (0u32, 0u32);
        for pair in row.chunks_exact(2) {
            let (a, b) = (pair[0] as u32, pair[1] as u32);
            below += (a < b0) as u32 + (b < b1) as u32;
            clipped += (a >= self.clip) as u32 + (b >= self.clip) as u32;
        }
        if let Some(&last) = row.chunks_exact(2).remainder().first() {
            below += ((last as u32) < b0) as u32;
            clipped += (last as u32 >= self.clip) as u32;
        }
        let mut counts = empty_counts(pass, row.len());
        counts.clipped = clipped as usize;
        if let Some(b) = counts.below_floor.as_mut() {
            *b = below as usize;
        }
        counts
    }
}

/// How many 16-bit values from 0 up pass `test`, when those that pass are a prefix of them.
fn prefix(test: impl Fn(u16) -> bool) -> Option<u32> {
    let n = (0..=u16::MAX).take_while(|&d| test(d)).count();
    let rest_fail = (n..=u16::MAX as usize).all(|d| !test(d as u16));
    rest_fail.then_some(n as u32)
}

/// Linearises `mosaic`, counts its samples for the plausibility check, subtracts
/// `pass.dark` where given and bins the result 2x2 (R and B of each cell, the mean of its two
/// G): `linearize`, `LinearMosaic::subtract_shared` and `LinearMosaic::bin2x2` in one pass, with no
/// full-size linear mosaic made. Samples of an odd last row or column are counted, not binned.
///
/// Each sample row is linearised, counted and dark-subtracted with the full-resolution
/// pass's row loops (which the compiler vectorises), then binned (`mosaic::bin_rows`): a
/// closure per sample, reading the dark frame sample by sample, took 140 ms a 16 MP frame.
pub fn bin2x2(mosaic: &Mosaic, pass: LinearPass) -> Result<(LightFrame, SampleCounts)> {
    mosaic.validate()?;
    check_dark(mosaic, pass.dark)?;
    let sites = Sites::of(mosaic);
    let (width, height) = (mosaic.width, mosaic.height);
    // Sample row `y` linearised, counted and dark-subtracted into `row`.
    let fill_row = |y: usize, row: &mut SampleRow, counts: &mut SampleCounts| {
        row.values.resize(width, 0.0);
        row.saturated.resize(width, false);
        let at = y * width..(y + 1) * width;
        linear_row(
            &sites,
            y % 2,
            &mosaic.samples[at],
            &mut row.values,
            &mut row.saturated,
        );
        count_row(counts, &row.values, &row.saturated, pass.below_black_floor);
        if let Some(d) = pass.dark {
            // Any dark mosaic serves: linear or kept as DN, with or without saturation flags.
            let dark = d.row(y, &mut row.scratch);
            match d.saturated_row(y) {
                Some(flags) => subtract_row(&mut row.values, &mut row.saturated, dark, flags),
                None => subtract_row(&mut row.values, &mut [], dark, &[]),
            }
        }
    };
    let (frame, rows) = bin_rows(
        (width, height),
        mosaic.pattern,
        || empty_counts(&pass, 2 * width),
        fill_row,
    );
    // The odd last row is not binned, but it is counted.
    let h = Resolution::Half.size(width, height).1;
    let mut rest = empty_counts(&pass, (height - 2 * h) * width);
    let mut scratch = SampleRow::default();
    for y in 2 * h..height {
        fill_row(y, &mut scratch, &mut rest);
    }
    let counts = rows.into_iter().fold(rest, SampleCounts::plus);
    Ok((frame, counts))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A mosaic with samples spread over the whole range (some clipped, some below black),
    /// per-site black levels and an odd size.
    fn mosaic(width: usize, height: usize, pattern: &str, seed: u32) -> Mosaic {
        let mut state = seed;
        Mosaic {
            width,
            height,
            pattern: Mosaic::parse_pattern(pattern).unwrap(),
            black: [[100.0, 104.0], [98.0, 101.0]],
            white: 4000.0,
            samples: (0..width * height)
                .map(|_| {
                    state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    (state >> 20) as u16 // 0..4095: below black, in range and clipped
                })
                .collect(),
        }
    }

    /// The counts the separate passes would give.
    fn counts_of(linear: &LinearMosaic, floor: Option<f32>) -> SampleCounts {
        SampleCounts {
            samples: linear.values.len(),
            clipped: linear.saturated.iter().filter(|&&s| s).count(),
            below_floor: floor.map(|f| linear.values.iter().filter(|&&v| v < f).count()),
        }
    }

    #[test]
    fn one_pass_equals_linearize_subtract_and_bin_bit_for_bit() {
        for (w, h) in [(34, 30), (33, 31), (2, 3)] {
            for pattern in ["RGGB", "GBRG"] {
                let light = mosaic(w, h, pattern, 7);
                let dark = mosaic(w, h, pattern, 11).linearize().unwrap();
                for (dark, floor) in [(None, None), (Some(&dark), Some(-0.01f32))] {
                    let pass = LinearPass {
                        dark,
                        below_black_floor: floor,
                    };
                    let separate = light.linearize().unwrap();
                    // Linear values by the formula, sample by sample.
                    for (i, &raw) in light.samples.iter().enumerate() {
                        let (x, y) = (i % w, i / w);
                        let black = light.black[y % 2][x % 2];
                        let scale = 1.0 / (light.white - black);
                        assert_eq!(separate.values[i], (raw as f32 - black) * scale);
                        let threshold = light.saturation_threshold();
                        assert_eq!(separate.saturated[i], raw as f32 >= threshold);
                    }
                    let expected_counts = counts_of(&separate, floor);
                    if w * h >= 1000 {
                        assert!(expected_counts.clipped > 0, "the test mosaic clips");
                        assert_ne!(expected_counts.below_floor, Some(0), "and goes below black");
                    }
                    let mut subtracted = separate.clone();
                    if let Some(d) = dark {
                        let shared = super::super::mosaic::SharedDark::of(d.clone()).unwrap();
                        subtracted.subtract_shared(&shared).unwrap();
                    }
                    let (linear, counts) = linearize(&light, pass).unwrap();
                    assert_eq!(counts, expected_counts, "{w}x{h} {pattern}");
                    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(&linear.values), bits(&subtracted.values));
                    assert_eq!(linear.saturated, subtracted.saturated);

                    let (binned, counts) = bin2x2(&light, pass).unwrap();
                    assert_eq!(counts, expected_counts, "{w}x{h} {pattern} binned");
                    let expected = subtracted.bin2x2();
                    for c in 0..3 {
                        assert_eq!(
                            bits(&binned.rgb.channels()[c].data),
                            bits(&expected.rgb.channels()[c].data)
                        );
                    }
                    assert_eq!(binned.saturated, expected.saturated);
                }
            }
        }
    }

    /// A frame kept as DN reads, sample by sample and row by row, the bits `linearize` writes,
    /// with the same saturation flags and counts, before and after a shared dark frame is
    /// subtracted.
    #[test]
    fn a_frame_kept_as_dn_reads_what_linearize_writes_bit_for_bit() {
        use super::super::mosaic::SharedDark;
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for (w, h) in [(34, 30), (33, 31), (2, 3)] {
            for pattern in ["RGGB", "GBRG"] {
                let light = mosaic(w, h, pattern, 7);
                let dark = SharedDark::of(mosaic(w, h, pattern, 11).linearize().unwrap()).unwrap();
                for floor in [None, Some(-0.01f32)] {
                    let pass = LinearPass {
                        dark: None,
                        below_black_floor: floor,
                    };
                    let (linear, counts) = linearize(&light, pass).unwrap();
                    let (kept, kept_counts) = keep_dn(light.clone(), pass).unwrap();
                    assert!(kept.values.is_empty() && kept.dn.is_some());
                    assert_eq!(kept_counts, counts, "{w}x{h} {pattern}");
                    for subtract in [false, true] {
                        let (mut linear, mut kept) = (linear.clone(), kept.clone());
                        if subtract {
                            linear.subtract_shared(&dark).unwrap();
                            kept.subtract_shared(&dark).unwrap();
                        }
                        let flags = |m: &LinearMosaic| {
                            (0..w * h).map(|i| m.saturated_at(i)).collect::<Vec<_>>()
                        };
                        assert_eq!(flags(&kept), flags(&linear));
                        let mut scratch = Vec::new();
                        for y in 0..h {
                            let want = bits(&linear.values[y * w..(y + 1) * w]);
                            assert_eq!(bits(kept.row(y, &mut scratch)), want, "row {y}");
                            let each: Vec<f32> = (0..w).map(|x| kept.value(y * w + x)).collect();
                            assert_eq!(bits(&each), want, "row {y}, sample by sample");
                        }
                    }
                }
            }
        }
    }

    /// The counts of a frame kept as DN, taken as limits on the stored values, are the linear
    /// tests' exactly: with floors on the linear values of stored ones (the test is strict),
    /// between them, and not finite.
    #[test]
    fn a_frame_kept_as_dn_counts_as_the_linear_tests_at_every_floor() {
        let light = mosaic(33, 31, "RGGB", 5);
        let mut floors: Vec<f32> = vec![f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 0.0, -0.0];
        for dn in 90..112u16 {
            for black in [98.0f32, 100.0, 101.0, 104.0] {
                let v = (dn as f32 - black) * (1.0 / (light.white - black));
                floors.extend([v, v.next_up(), v.next_down()]);
            }
        }
        for floor in floors {
            let pass = LinearPass {
                dark: None,
                below_black_floor: Some(floor),
            };
            let (_, counts) = linearize(&light, pass).unwrap();
            let (_, kept_counts) = keep_dn(light.clone(), pass).unwrap();
            assert_eq!(kept_counts, counts, "floor {floor:e}");
        }
    }

    /// A frame kept as DN that clips nowhere writes no flags; a dark frame subtracted from it
    /// brings its own.
    #[test]
    fn a_frame_kept_as_dn_that_clips_nowhere_has_no_flags_until_a_dark_frame_brings_some() {
        use super::super::mosaic::SharedDark;
        let (w, h) = (33, 31);
        let mut light = mosaic(w, h, "RGGB", 7);
        light.samples.iter_mut().for_each(|v| *v = (*v).min(3000));
        let pass = LinearPass::default();
        let (kept, counts) = keep_dn(light.clone(), pass).unwrap();
        assert_eq!(counts.clipped, 0);
        assert!(kept.saturated.is_empty() && kept.saturated_row(0).is_none());
        let dark = mosaic(w, h, "RGGB", 11).linearize().unwrap();
        let clipped: Vec<usize> = (0..w * h).filter(|&i| dark.saturated[i]).collect();
        assert!(!clipped.is_empty(), "the test's dark frame clips");
        let mut kept = kept;
        kept.subtract_shared(&SharedDark::of(dark).unwrap())
            .unwrap();
        let flagged: Vec<usize> = (0..w * h).filter(|&i| kept.saturated_at(i)).collect();
        assert_eq!(flagged, clipped);
    }

    /// The binning pass reads any dark mosaic: one kept as DN with no saturation flags (it
    /// clips nowhere) gives the bits and counts of the same frame linearised with its flags.
    #[test]
    fn binning_subtracts_a_dark_frame_kept_as_dn_as_a_linear_one() {
        let light = mosaic(34, 31, "GBRG", 5);
        let mut dark = mosaic(34, 31, "GBRG", 9);
        dark.samples.iter_mut().for_each(|s| *s %= 200); // around black: nothing clips
        let linear = dark.linearize().unwrap();
        let (kept, _) = keep_dn(dark, LinearPass::default()).unwrap();
        assert!(kept.saturated.is_empty() && kept.values.is_empty());
        let binned = |dark: &LinearMosaic| {
            let pass = LinearPass {
                dark: Some(dark),
                below_black_floor: Some(-0.01),
            };
            bin2x2(&light, pass).unwrap()
        };
        let ((from_linear, a), (from_dn, b)) = (binned(&linear), binned(&kept));
        assert_eq!(a, b);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for c in 0..3 {
            let (x, y) = (from_linear.rgb.channels()[c], from_dn.rgb.channels()[c]);
            assert_eq!(bits(&x.data), bits(&y.data));
        }
        assert_eq!(from_linear.saturated, from_dn.saturated);
    }

    #[test]
    fn a_dark_frame_of_another_layout_is_refused() {
        let light = mosaic(8, 6, "RGGB", 1);
        let dark = mosaic(8, 6, "BGGR", 2).linearize().unwrap();
        let pass = LinearPass {
            dark: Some(&dark),
            below_black_floor: None,
        };
        let err = bin2x2(&light, pass).unwrap_err().to_string();
        assert!(err.contains("dark frame"), "{err}");
        assert!(linearize(&light, pass).is_err());
    }
}
