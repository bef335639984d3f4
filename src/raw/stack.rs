//! Developing a stack of frames of one static scene (one frame per light) at full resolution:
//! every pixel keeps its own CFA sample, and its missing channels are that sample times colour
//! ratios that are the same in every frame.

use std::sync::Arc;

use rayon::prelude::*;

use super::hue::{colour_ratios, Backing};
use super::mosaic::{bilinear, LinearMosaic, Mosaic, Resolution};
use super::shading::{ShadingField, SiteFitter};
use crate::error::{Error, Result};
use crate::plane::{CfaColour, LightFrame, Plane, RgbPlanes};

/// Develops a stack of frames of one static scene, each lit by an illuminant of colour
/// `illuminants[k]` (the raw R, G, B response to it; `None`: all the same colour).
///
/// **Half resolution** bins each frame on its own (2x2 CFA binning).
///
/// **Full resolution** keeps each pixel's own sample and fills its two missing channels with
/// that sample times the pixel's colour ratios, taken from the whole stack: under illuminants
/// of known colour a pixel's R : G : B (after dividing by the illuminant's colour) is its
/// reflectance's, the same in every frame, while its brightness (the shading) changes from
/// frame to frame. So
///
/// ```text
/// X_k,c'(p) = v_k(p) * T_c'(p) / T_c(p) * g_k,c' / g_k,c
/// ```
///
/// with `v_k(p)` the own sample (channel `c`), `g_k` frame k's illuminant colour and `T` a
/// bilinear demosaic of what every site says about its own channel's reflectance:
///
/// - with the frames' `shading` vectors (see [`ShadingField`]), each site's albedo, fitted to
///   its samples with the shading divided out. Neighbours shaded unlike the pixel (the other
///   flank of a thread, the gap beside it) then give their colour, not their shading;
/// - without them, the stack's white-balanced sum `sum_k v_k / g_k`, which carries each
///   site's summed shading as well (right where the shading changes slowly).
///
/// Every channel of
/// `X_k(p)` is proportional to the pixel's own shading in frame k, so photometric stereo sees
/// each pixel's true shading (a plain demosaic mixes in the neighbours' shading, which on a
/// textile whose normals change within a few pixels costs degrees); interpolation only enters
/// the colour ratios, which are the same in every frame. The channels then share the own
/// sample's noise (`NoiseModel::shared_cfa_sample`). A pixel is saturated in a frame when its
/// own sample is. With a stack of one frame this is the classic constant-hue demosaic.
pub fn develop_stack(
    frames: Vec<LinearMosaic>,
    illuminants: Option<&[[f64; 3]]>,
    shading: Option<&ShadingField>,
    resolution: Resolution,
) -> Result<Developed> {
    let Some(first) = frames.first() else {
        return Ok(Developed::default());
    };
    let (w, h, pattern) = (first.width, first.height, first.pattern);
    if let Some(odd) = frames
        .iter()
        .find(|f| (f.width, f.height, f.pattern) != (w, h, pattern))
    {
        return Err(Error::Invalid(format!(
            "a stack mixes a {}x{} mosaic with a {w}x{h} one (or CFA patterns)",
            odd.width, odd.height
        )));
    }
    let colours: Vec<[f32; 3]> = match illuminants {
        None => vec![[1.0; 3]; frames.len()],
        Some(list) if list.len() == frames.len() => {
            if list.iter().flatten().any(|g| !(g.is_finite() && *g > 0.0)) {
                return Err(Error::Invalid(format!(
                    "illuminant colours must be positive, got {list:?}"
                )));
            }
            list.iter().map(|g| g.map(|v| v as f32)).collect()
        }
        Some(list) => {
            return Err(Error::Invalid(format!(
                "{} illuminant colours for {} frames",
                list.len(),
                frames.len()
            )))
        }
    };
    match resolution {
        Resolution::Half => Ok(Developed {
            frames: frames.iter().map(LinearMosaic::bin2x2).collect(),
            backing: None,
        }),
        Resolution::Full => {
            if let Some(field) = shading.filter(|f| f.frames() != frames.len()) {
                return Err(Error::Invalid(format!(
                    "shading vectors for {} frames, a stack of {}",
                    field.frames(),
                    frames.len()
                )));
            }
            Ok(develop_full(frames, &colours, shading))
        }
    }
}

/// A developed stack: its frames, and the material the full-resolution demosaic found seen
/// through the holes of the weave (see `hue::backing`), if any.
#[derive(Default)]
pub struct Developed {
    /// The light frames, in the stack's order.
    pub frames: Vec<LightFrame>,
    /// The material seen through the holes, where the isolated pixels agreed on one.
    pub backing: Option<Backing>,
}

fn develop_full(
    frames: Vec<LinearMosaic>,
    colours: &[[f32; 3]],
    shading: Option<&ShadingField>,
) -> Developed {
    let first = &frames[0];
    let (w, h, pattern) = (first.width, first.height, first.pattern);
    // The white-balanced sum of the stack, and its colour at every pixel.
    let mut sum = vec![0.0f32; w * h];
    sum.par_chunks_mut(w)
        .enumerate()
        .for_each_init(Vec::new, |scratch, (y, row)| {
            for (k, frame) in frames.iter().enumerate() {
                let values = frame.row(y, scratch);
                let inv = colours[k].map(|g| 1.0 / g);
                for x in 0..w {
                    row[x] += values[x] * inv[pattern[y % 2][x % 2] as usize];
                }
            }
        });
    // Below this the stack's own-channel sum is noise (a fraction of a DN per frame): the
    // pixel is black in every frame and its colour ratios mean nothing.
    let floor = 1e-5 * frames.len() as f32;
    let (ratios, backing) = match shading {
        Some(field) => {
            let sites = SiteFitter::new(&frames, colours, field, &sum, floor);
            colour_ratios(w, h, pattern, &sites)
        }
        None => (bilinear_ratios(w, h, pattern, &sum, floor), None),
    };
    // Every frame keeps its samples and shares the ratios: its missing channels are computed
    // where they are read (`CfaColour::rgb`), so the stack takes one plane per frame, not three.
    let ratios = Arc::new(ratios);
    let frames = frames
        .into_iter()
        .zip(colours)
        .map(|(frame, colour)| {
            let saturated = LinearMosaic::saturated_mask(frame.saturated, w, h);
            let cfa = CfaColour {
                pattern,
                ratios: Arc::clone(&ratios),
                colour: *colour,
            };
            match frame.dn {
                Some(dn) => LightFrame::from_cfa_dn(dn, saturated, cfa),
                None => LightFrame::from_cfa(
                    Plane::from_vec(w, h, frame.values).expect("a mosaic's samples fill it"),
                    saturated,
                    cfa,
                ),
            }
        })
        .collect();
    Developed { frames, backing }
}

/// Every pixel's channel ratios (to its own channel) from a plain bilinear demosaic of the
/// stack's white-balanced `sum`; 0 where the pixel's own sum is at most `floor`.
fn bilinear_ratios(
    w: usize,
    h: usize,
    pattern: [[u8; 2]; 2],
    sum: &[f32],
    floor: f32,
) -> RgbPlanes {
    let mut totals = bilinear(w, h, pattern, sum);
    totals.par_rows_mut(|y, rows| {
        for x in 0..w {
            let own = pattern[y % 2][x % 2] as usize;
            let own_total = rows[own][x];
            for c in 0..3 {
                if c != own {
                    rows[c][x] = if own_total > floor {
                        rows[c][x] / own_total
                    } else {
                        0.0
                    };
                }
            }
            rows[own][x] = 1.0;
        }
    });
    totals
}

/// `develop` lives beside `develop_stack`, which it calls, so that `mosaic` does not import
/// the stack that builds on it.
impl Mosaic {
    /// This frame developed on its own (at full resolution its colour ratios come from its own
    /// neighbourhood; see [`develop_stack`]).
    pub fn develop(&self, resolution: Resolution) -> Result<LightFrame> {
        let mut frames = develop_stack(vec![self.linearize()?], None, None, resolution)?.frames;
        let frame = frames.pop().expect("one frame in, one out");
        // One frame shares its ratios with nothing: three planes are what its users want.
        Ok(LightFrame::from_rgb(
            frame.to_planes().into_owned(),
            frame.saturated,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raw::Mosaic;

    /// A stack of frames of a scene of smooth colour whose shading changes from pixel to pixel
    /// and from frame to frame (what a textile under ten LEDs is), under illuminants of
    /// different colours.
    /// Frames, their illuminant colours, and each frame's true RGB per pixel.
    type Stack = (Vec<LinearMosaic>, Vec<[f64; 3]>, Vec<Vec<[f32; 3]>>);

    fn shaded_stack(w: usize, h: usize) -> Stack {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(5);
        let pattern = Mosaic::parse_pattern("GBRG").unwrap();
        let illuminants = vec![[0.55, 1.0, 0.72], [0.6, 1.0, 0.7], [0.5, 0.9, 0.8]];
        let mut frames = Vec::new();
        let mut truth = Vec::new();
        let mut previous: Vec<f32> = Vec::new();
        for (k, g) in illuminants.iter().enumerate() {
            let mut values = Vec::new();
            let mut rgb = Vec::new();
            for i in 0..w * h {
                let (x, y) = (i % w, i / w);
                // Colour varies slowly (linear ramps), shading wildly.
                let albedo = [
                    0.2 + 0.002 * x as f32,
                    0.5 - 0.001 * y as f32,
                    0.3 + 0.001 * (x + y) as f32,
                ];
                // Per-pixel shading that changes from frame to frame but whose sum over the
                // stack is the same everywhere (so the stack's colour is exact to test against).
                let t: f32 = if k == 0 {
                    rng.gen_range(0.05..0.95)
                } else {
                    0.0
                };
                let shading = match k {
                    0 => t,
                    1 => 1.0 - previous[i],
                    _ => 0.5,
                };
                if k == 0 {
                    previous.push(t);
                }
                let px: [f32; 3] = std::array::from_fn(|c| albedo[c] * g[c] as f32 * shading);
                values.push(px[pattern[y % 2][x % 2] as usize]);
                rgb.push(px);
            }
            frames.push(LinearMosaic {
                width: w,
                height: h,
                pattern,
                saturated: vec![false; values.len()],
                values,
                dn: None,
            });
            truth.push(rgb);
        }
        (frames, illuminants, truth)
    }

    /// A stack whose frames keep their DN develops, with the shading-preserving demosaic and
    /// a shared dark frame, into the frames the same stack linearised to `f32` gives, bit for
    /// bit: the same ratios, samples and saturation flags.
    #[test]
    fn a_stack_kept_as_dn_develops_as_its_linear_samples_do() {
        use super::super::mosaic::SharedDark;
        use super::super::pass::{keep_dn, linearize, LinearPass};
        let (w, h) = (45, 70);
        let lights = 6;
        let mut state = 3u32;
        let mut mosaic = |base: u16, spread: u32| Mosaic {
            width: w,
            height: h,
            pattern: Mosaic::parse_pattern("GRBG").unwrap(),
            black: [[600.0, 604.0], [598.0, 601.0]],
            white: 15600.0,
            samples: (0..w * h)
                .map(|_| {
                    state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    base + ((state >> 8) % spread) as u16
                })
                .collect(),
        };
        // Lights reading up to the white level (some samples clip) and lights that clip nowhere,
        // and a dark frame.
        let clipping: Vec<Mosaic> = (0..lights).map(|_| mosaic(590, 15200)).collect();
        let unclipped: Vec<Mosaic> = (0..lights).map(|_| mosaic(590, 12000)).collect();
        let dark = SharedDark::of(mosaic(596, 9).linearize().unwrap()).unwrap();
        let field = ShadingField::sample(w, h, 8, |x, y| {
            Ok((0..lights)
                .map(|k| {
                    let phi = k as f64;
                    [
                        0.5 * phi.cos() - 0.002 * x,
                        0.5 * phi.sin() + 0.001 * y,
                        0.8,
                    ]
                })
                .collect())
        })
        .unwrap();
        let illuminants: Vec<[f64; 3]> = (0..lights)
            .map(|k| [0.6 + 0.02 * k as f64, 1.0, 0.7 - 0.01 * k as f64])
            .collect();
        let develop = |raw: &[Mosaic], keep: bool| {
            let frames: Vec<LinearMosaic> = (raw.iter())
                .map(|m| {
                    let pass = LinearPass::default();
                    let mut f = match keep {
                        true => keep_dn(m.clone(), pass).unwrap().0,
                        false => linearize(m, pass).unwrap().0,
                    };
                    f.subtract_shared(&dark).unwrap();
                    f
                })
                .collect();
            develop_stack(frames, Some(&illuminants), Some(&field), Resolution::Full)
                .unwrap()
                .frames
        };
        for (raw, clips) in [(&clipping, true), (&unclipped, false)] {
            let (kept, linear) = (develop(raw, true), develop(raw, false));
            assert!(kept.iter().all(|f| f.cfa_dn.is_some()));
            assert!(linear.iter().all(|f| f.cfa_dn.is_none()));
            for (k, (a, b)) in kept.iter().zip(&linear).enumerate() {
                // A frame kept as DN that clips nowhere has no flags at all.
                let flags = b.saturated.as_ref().unwrap();
                assert_eq!(flags.data.contains(&true), clips, "frame {k}");
                match clips {
                    true => assert_eq!(a.saturated.as_ref(), Some(flags), "frame {k}"),
                    false => assert_eq!(a.saturated, None, "frame {k}"),
                }
                for y in 0..h {
                    for x in 0..w {
                        let bits = |f: &LightFrame| f.rgb_at(x, y).map(f32::to_bits);
                        assert_eq!(bits(a), bits(b), "frame {k} ({x},{y})");
                    }
                }
            }
        }
    }

    #[test]
    fn the_stack_demosaic_keeps_every_pixels_own_shading() {
        let (w, h) = (40, 30);
        let (frames, illuminants, truth) = shaded_stack(w, h);
        let developed = develop_stack(frames.clone(), Some(&illuminants), None, Resolution::Full)
            .unwrap()
            .frames;
        for (k, frame) in developed.iter().enumerate() {
            // Each frame keeps one sample per pixel and shares the stack's ratios.
            assert!(frame.cfa.is_some() && frame.rgb.r.data.is_empty());
            let planes = frame.to_planes();
            for y in 1..h - 1 {
                for x in 1..w - 1 {
                    let i = y * w + x;
                    assert_eq!(
                        frame.rgb_at(x, y),
                        [0, 1, 2].map(|c| planes.channels()[c].data[i])
                    );
                    for (c, plane) in planes.channels().iter().enumerate() {
                        let t = truth[k][i][c];
                        // Only the slow colour ramps are interpolated; the shading is exact.
                        assert!(
                            (plane.data[i] - t).abs() <= 2e-3 * t,
                            "frame {k} ({x},{y}) channel {c}: {} vs {t}",
                            plane.data[i]
                        );
                    }
                }
            }
        }
        // Whatever the shading, every channel of a pixel is its own sample times a ratio that
        // is the same in every frame (after the illuminant's colour): what photometric stereo
        // needs from the pixel is its own.
        use rand::{Rng, SeedableRng};
        let mut rng = rand_xoshiro::Xoshiro256PlusPlus::seed_from_u64(9);
        let mut shuffled = frames.clone();
        for f in &mut shuffled {
            for v in &mut f.values {
                *v *= rng.gen_range(0.1f32..1.0);
            }
        }
        let developed = develop_stack(shuffled.clone(), Some(&illuminants), None, Resolution::Full)
            .unwrap()
            .frames;
        for i in (0..w * h).step_by(7) {
            let (x, y) = (i % w, i / w);
            let own = shuffled[0].channel(x, y);
            for c in 0..3 {
                let ratio = |k: usize| {
                    developed[k].rgb_at(x, y)[c] / shuffled[k].values[i]
                        * (illuminants[k][own] / illuminants[k][c]) as f32
                };
                for k in 1..3 {
                    assert!((ratio(k) / ratio(0) - 1.0).abs() < 1e-5, "({x},{y}) c {c}");
                }
            }
        }
        // A plain bilinear demosaic of the same frames mixes the neighbours' shading in.
        let plain = bilinear(w, h, frames[0].pattern, &frames[0].values);
        let worst = (0..w * h)
            .filter(|i| (1..h - 1).contains(&(i / w)) && (1..w - 1).contains(&(i % w)))
            .map(|i| {
                (0..3)
                    .map(|c| (plain.channels()[c].data[i] / truth[0][i][c] - 1.0).abs())
                    .fold(0.0f32, f32::max)
            })
            .fold(0.0f32, f32::max);
        assert!(worst > 0.5, "bilinear's worst relative error {worst}");
    }
}
