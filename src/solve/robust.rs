//! The robust fit: least squares that rejects the lights that do not fit the rest (a thread's
//! cast shadow reads far below the Lambertian prediction, a highlight far above), then, where
//! the kept lights still disagree with a Lambertian surface more than the sensor noise allows,
//! the sheen model of seed 004 (see `sheen`).
//!
//! Rejection is backward elimination by the studentised residual: with `L` the kept lights'
//! matrix, `h_k = l_k^T (L^T L)^-1 l_k` is light `k`'s leverage, and `r_k / (s_k sqrt(1 - h_k))`
//! is its residual in units of its own standard deviation under the noise model. The light
//! furthest out is dropped and the rest refitted, until no light is an outlier at
//! `outlier_sigma` or only `max(4, (1 - max_rejected_fraction) m)` lights are left. A second
//! pass drops only lights darker than the fit (cast shadows), down to 4 lights whatever the
//! fraction: in a crevice most lights can be shadowed. Lights that agree are all kept, so on
//! clean data the robust fit is least squares.
//!
//! Why this scheme (measured, see README "Estimators"): thresholding the darkest and brightest
//! readings drops good lights wherever the normal tilts toward one side of the rig, and
//! iteratively reweighted least squares spreads a shadow's weight over every light; removing
//! one light at a time by its own noise-normalised residual keeps the noise-optimal fit
//! wherever the data allow it.

use nalgebra::Vector3;

use super::chi_square::{weighted_fit, ChiSquare, WeightedFit};
use super::departures;
use super::measure::{condition_of, fit_luminance, Fit, LuminanceFit, Measurement};
use super::options::RobustOptions;
use super::sheen::{self, SheenModel};

/// What the robust fit needs from the pixel besides its measurements.
pub(super) struct Context<'a> {
    /// The robust fit's tuning.
    pub options: &'a RobustOptions,
    /// Refits whose light matrix is worse conditioned than this are not taken.
    pub max_condition: f64,
    /// The test every decision is made with.
    pub chi: &'a ChiSquare,
    /// Unit vector from the pixel's point toward the camera.
    pub view: Vector3<f64>,
    /// Fit the sheen model (when configured) even where the Lambertian fit passes the test.
    pub force_sheen: bool,
}

/// Per-thread buffers for the robust fit, reused across pixels.
#[derive(Default)]
pub(super) struct Buffers {
    /// The usable lights before rejection.
    original: Vec<Measurement>,
    /// The lights the darker-only pass keeps.
    darker: Vec<Measurement>,
    /// The original readings while the sheen-corrected ones are tested.
    sheen: Vec<Measurement>,
    /// All usable lights while the sheen rejection alternates with the sheen fit.
    usable: Vec<Measurement>,
    /// The data-scaled fit's buffers.
    departures: departures::Buffers,
    /// All usable lights while the noise-model rejection and the data-scaled fit are compared.
    noise_usable: Vec<Measurement>,
}

/// True when `n_lum` predicts a positive reading for every light.
fn predicts_light(measurements: &[Measurement], n_lum: &Vector3<f64>) -> bool {
    measurements.iter().all(|m| n_lum.dot(&m.l) > 0.0)
}

/// Which lights a rejection pass may drop.
#[derive(Clone, Copy, PartialEq)]
enum Rule {
    /// Any light, the one furthest out first.
    Any,
    /// Only lights darker than the fit: a cast shadow only ever darkens, so this pass finds
    /// the lit lights where the shadowed ones are consistent among themselves (the fill light
    /// in a crevice is a fraction of the direct light).
    DarkerOnly,
}

/// Refits `measurements`, starting from their least-squares `fit`, leaving in `measurements`
/// the lights the returned fit used. `weighted` is the weighted fit of all of them where the
/// caller's test already computed it.
///
/// Two rejection passes run from the weighted fit of all lights, one dropping any outlier and
/// one dropping only lights darker than the fit. The result is the pass whose lights pass the
/// chi-square test, then the one that kept more lights, then (shadows only darken) the one
/// with the higher albedo.
pub(super) fn refine(
    context: &Context,
    measurements: &mut Vec<Measurement>,
    buffers: &mut Buffers,
    least_squares: Fit,
    weighted: Option<WeightedFit>,
) -> Fit {
    let options = context.options;
    let chi = context.chi;
    // A configured sheen model is the user's account of the model error: it decides there.
    let Some(start) = weighted.or_else(|| weighted_fit(chi, measurements)) else {
        return least_squares;
    };
    let lambertian = chi.accepts_statistic(start.chi2, measurements.len());
    if lambertian && !predicts_light(measurements, &start.n_lum) {
        // Every light was read above the dark threshold, so a normal that turns away from one
        // of them is a numerical failure of the weighted fit: keep least squares.
        return least_squares;
    }
    let condition = least_squares.condition;
    let all_lights = start.clone().into_fit(chi, measurements, condition, false);
    let Some(model) = &options.sheen else {
        if lambertian {
            return all_lights;
        }
        return noise_or_data_scaled(context, measurements, buffers, start, least_squares);
    };
    // The sheen lobe brightens many lights smoothly: fit it to all lights before treating any
    // as an outlier.
    let mut sheen_normal = None;
    if context.force_sheen || !lambertian {
        if let Some((fit, statistic)) =
            sheen::fit(model, chi, &context.view, measurements, &all_lights)
        {
            if chi.accepts_statistic(statistic, measurements.len()) {
                return fit;
            }
            sheen_normal = fit.n_lum.try_normalize(1e-12);
        }
    }
    if lambertian {
        return all_lights;
    }
    // Outliers under the sheen model: the Lambertian tests on the readings with the lobe taken
    // out, then the sheen fit on the lights kept.
    let Some(normal) = sheen_normal else {
        return lambertian_rejection(context, measurements, buffers, start, condition)
            .unwrap_or(least_squares);
    };
    match sheen_alternation(context, model, normal, measurements, buffers) {
        Some(fit) => fit,
        None => lambertian_rejection(context, measurements, buffers, start, condition)
            .unwrap_or(least_squares),
    }
}

/// The Lambertian pixel the noise model does not explain with all lights.
///
/// The data-scaled fit ([`departures::fit`]) looks first: where even the pixel's trimmed
/// residuals are several noise deviations wide, the sensor model does not explain the pixel
/// (soft shadows, inter-reflection, a diffuse lobe that is not Lambertian) and the scale of a
/// departure must come from the data. There a rejection judged in sensor-noise units ends on
/// whatever small subset happens to agree to the noise: measured on the DiLiGenT bunny with
/// cast shadows it gave 3.77 deg against 3.29 for the data-scaled fit, and on the real bear
/// (96 lights) 5.97 against 5.41.
///
/// Where the data-scaled fit finds the residuals within the noise (it returns `None`: clean
/// Lambertian data with a few cast shadows), the noise-model rejection decides: it judges
/// each light in units of sensor noise, more finely than any scale taken from the pixel's own
/// residuals. A passing rejection whose normal turns away from a light the pixel reads lit is
/// not a solution ([`lit_behind_surface`]): the pixel keeps least squares. A configured sheen
/// model never comes here: it is the user's account of the model error.
fn noise_or_data_scaled(
    context: &Context,
    measurements: &mut Vec<Measurement>,
    buffers: &mut Buffers,
    start: WeightedFit,
    least_squares: Fit,
) -> Fit {
    let chi = context.chi;
    let condition = least_squares.condition;
    let data_scaled = departures::fit(
        &departures::Departures::default(),
        measurements,
        &mut buffers.departures,
        &least_squares.n_lum,
    );
    if let Some(fit) = data_scaled {
        return fit;
    }
    // The data-scaled fit declined and left every usable light in `measurements`: keep a copy
    // while the rejection drops lights.
    let mut usable = std::mem::take(&mut buffers.noise_usable);
    usable.clear();
    usable.extend_from_slice(measurements);
    let usable_count = usable.len();
    let fit = match reject_outliers(context, measurements, buffers, start) {
        Some(weighted)
            if !chi.accepts_statistic(weighted.chi2, measurements.len())
                || !lit_behind_surface(&usable, &weighted.n_lum, context.options.outlier_sigma) =>
        {
            let rejected = measurements.len() < usable_count;
            Some(weighted.into_fit(chi, measurements, condition, rejected))
        }
        // No rejection, or one whose normal the data contradict: least squares over all
        // lights is the fit that does not rest on it.
        _ => None,
    };
    let fit = fit.unwrap_or_else(|| {
        measurements.clear();
        measurements.extend_from_slice(&usable);
        least_squares
    });
    buffers.noise_usable = usable;
    fit
}

/// True when `n_lum` turns away from a light (`n . l <= 0`) that `all` reads lit by more than
/// `sigma` of its noise deviation. Direct light cannot reach a surface from behind it: cast
/// shadows only darken and highlights need `n . l > 0`, so under a noise model that explains
/// the lights a rejection kept, such a reading contradicts the kept lights' normal rather than
/// being an outlier against it. (Where the rejected lights are instead the grazing readings a
/// pixel's footprint blends across the terminator, dropping the brighter-than-predicted ones
/// leaves a subset that fits exactly a normal tilted away from the lit side.)
fn lit_behind_surface(all: &[Measurement], n_lum: &Vector3<f64>, sigma: f64) -> bool {
    all.iter()
        .any(|m| n_lum.dot(&m.l) <= 0.0 && m.lum > sigma * m.test_var.sqrt())
}

/// At most this many rounds of lobe removal, rejection and sheen refit. Each round's normal
/// comes from lights the previous round kept, so the kept set settles in one or two rounds.
const SHEEN_ROUNDS: usize = 3;

/// Alternates rejection under the sheen model with the sheen fit. The first lobe is removed at
/// `normal`, the sheen fit of all lights, which cast-shadowed lights bias: the removed lobe is
/// then wrong for the lights whose half vector is near that normal, and the rejection keeps or
/// drops lights by a wrong residual. Each next round removes the lobe at the normal fitted to
/// the kept lights (the maximum-likelihood normal for the lights the model holds on), until the
/// kept set stops changing. A second alternation starts from the Lambertian rejection's normal
/// (cast shadows screened before any lobe is fitted); of the two, the one whose lights pass the
/// chi-square test wins, then the one with more lights (the ranking of `reject_outliers`).
/// Leaves the returned fit's lights in `measurements`; `None`, with all lights restored, when
/// neither alternation finds a solution.
fn sheen_alternation(
    context: &Context,
    model: &SheenModel,
    normal: Vector3<f64>,
    measurements: &mut Vec<Measurement>,
    buffers: &mut Buffers,
) -> Option<Fit> {
    // The alternation tracks lights as bits of a u64 (the sheen fit takes at most 64 lights);
    // a light numbered past that leaves the pixel to the Lambertian rejection.
    if measurements.iter().any(|m| u32::from(m.light) >= u64::BITS) {
        return None;
    }
    let chi = context.chi;
    let mut all = std::mem::take(&mut buffers.usable);
    all.clear();
    all.extend_from_slice(measurements);
    let from_all = alternate(context, model, normal, &all, measurements, buffers);
    // Second start: the normal of the Lambertian rejection, which screens the cast shadows
    // (darker than the fit) before any lobe is fitted.
    measurements.clear();
    measurements.extend_from_slice(&all);
    let screened = weighted_fit(chi, measurements)
        .and_then(|start| lambertian_rejection(context, measurements, buffers, start, 1.0))
        .and_then(|fit| fit.n_lum.try_normalize(1e-12))
        .and_then(|n| alternate(context, model, n, &all, measurements, buffers));
    let rank = |c: &Candidate| {
        let lights = c.mask.count_ones() as usize;
        let passes = chi.accepts_statistic(c.statistic, lights);
        let score = if passes {
            lights as f64
        } else {
            -c.statistic / lights.saturating_sub(3).max(1) as f64
        };
        (passes, score)
    };
    let result = match (from_all, screened) {
        (Some(a), Some(b)) => Some(if rank(&b) > rank(&a) { b } else { a }),
        (a, b) => a.or(b),
    };
    // Leave the returned fit's lights (or, without one, all lights) in `measurements`.
    measurements.clear();
    match &result {
        Some(c) => measurements.extend(all.iter().filter(|m| c.mask & (1u64 << m.light) != 0)),
        None => measurements.extend_from_slice(&all),
    }
    buffers.usable = all;
    result.map(|c| c.fit)
}

/// One alternation's outcome: the fit, its chi-square statistic and its lights.
struct Candidate {
    fit: Fit,
    statistic: f64,
    mask: u64,
}

/// The alternation from `normal` over the lights `all`; `measurements` is scratch.
fn alternate(
    context: &Context,
    model: &SheenModel,
    mut normal: Vector3<f64>,
    all: &[Measurement],
    measurements: &mut Vec<Measurement>,
    buffers: &mut Buffers,
) -> Option<Candidate> {
    let chi = context.chi;
    let mut result: Option<Candidate> = None;
    for _ in 0..SHEEN_ROUNDS {
        measurements.clear();
        measurements.extend_from_slice(all);
        let Some(kept) = sheen_rejection(context, model, &normal, measurements, buffers) else {
            break;
        };
        let mask = light_mask(measurements);
        let lambert_statistic = chi.statistic(measurements, &kept.n_lum);
        let (fit, statistic) = match sheen::fit(model, chi, &context.view, measurements, &kept) {
            Some((fit, statistic)) if context.force_sheen || statistic < lambert_statistic => {
                (fit, statistic)
            }
            _ => (kept, lambert_statistic),
        };
        let settled = result.as_ref().is_some_and(|c| c.mask == mask);
        let next = fit.n_lum.try_normalize(1e-12);
        result = Some(Candidate {
            fit,
            statistic,
            mask,
        });
        match next {
            Some(n) if !settled => normal = n,
            _ => break,
        }
    }
    result
}

/// The lights of `measurements` as a mask of their indices (all below 64).
fn light_mask(measurements: &[Measurement]) -> u64 {
    measurements
        .iter()
        .fold(0, |mask, m| mask | 1u64 << m.light)
}

/// Rejection under the Lambertian model; leaves the kept lights in `measurements`.
fn lambertian_rejection(
    context: &Context,
    measurements: &mut Vec<Measurement>,
    buffers: &mut Buffers,
    start: WeightedFit,
    condition: f64,
) -> Option<Fit> {
    let chi = context.chi;
    let usable = measurements.len();
    let weighted = reject_outliers(context, measurements, buffers, start)?;
    let rejected = measurements.len() < usable;
    Some(weighted.into_fit(chi, measurements, condition, rejected))
}

/// Rejection on the readings with the sheen lobe at normal `n` taken out; leaves the kept
/// lights' original readings in `measurements` and returns their Lambertian weighted fit.
fn sheen_rejection(
    context: &Context,
    model: &sheen::SheenModel,
    n: &Vector3<f64>,
    measurements: &mut Vec<Measurement>,
    buffers: &mut Buffers,
) -> Option<Fit> {
    let chi = context.chi;
    if measurements.iter().any(|m| m.light >= 64) {
        // The kept set is tracked as a 64-bit mask of light indices.
        return None;
    }
    let mut originals = std::mem::take(&mut buffers.sheen);
    originals.clear();
    originals.extend_from_slice(measurements);
    for m in measurements.iter_mut() {
        *m = sheen::lambertian_equivalent(model, &context.view, n, m);
    }
    let outcome = weighted_fit(chi, measurements)
        .and_then(|start| reject_outliers(context, measurements, buffers, start));
    let kept = outcome.map(|_| {
        let rejected = measurements.len() < originals.len();
        let kept_lights = light_mask(measurements);
        measurements.clear();
        measurements.extend(
            originals
                .iter()
                .filter(|m| kept_lights & (1u64 << m.light) != 0),
        );
        rejected
    });
    let result = match kept {
        Some(rejected) => weighted_fit(chi, measurements).map(|w| {
            let condition = condition_of(measurements);
            w.into_fit(chi, measurements, condition, rejected)
        }),
        None => {
            measurements.clear();
            measurements.extend_from_slice(&originals);
            None
        }
    };
    buffers.sheen = originals;
    result
}

/// The two rejection passes from `start`; leaves the chosen pass's lights in `measurements`
/// (`None`, with the original lights restored, when the result is not a solution).
fn reject_outliers(
    context: &Context,
    measurements: &mut Vec<Measurement>,
    buffers: &mut Buffers,
    start: WeightedFit,
) -> Option<WeightedFit> {
    let chi = context.chi;
    buffers.original.clear();
    buffers.original.extend_from_slice(measurements);
    let spare = &mut buffers.darker;
    spare.clear();
    spare.extend_from_slice(measurements);
    let any = reject(context, measurements, start.clone(), Rule::Any, 0);
    // Where the first pass passes, the darker-only pass can only win with at least as many
    // lights (the ranking below): it stops there rather than drop more, which changes no
    // result.
    let floor = if chi.accepts_statistic(any.chi2, measurements.len()) {
        measurements.len()
    } else {
        0
    };
    let darker = reject(context, spare, start, Rule::DarkerOnly, floor);
    // A pass whose lights pass the test beats one whose do not; between two that pass, more
    // lights, then (shadows only darken) the higher albedo; between two that fail, the smaller
    // statistic per degree of freedom.
    let rank = |f: &WeightedFit, lights: usize| {
        let passes = chi.accepts_statistic(f.chi2, lights);
        let score = if passes {
            lights as f64
        } else {
            -f.chi2 / lights.saturating_sub(3).max(1) as f64
        };
        (passes, score, f.n_lum.norm())
    };
    let (a, b) = (rank(&any, measurements.len()), rank(&darker, spare.len()));
    let darker_wins = (b.0, b.1) > (a.0, a.1) || ((b.0, b.1) == (a.0, a.1) && b.2 > a.2);
    let weighted = if darker_wins {
        std::mem::swap(measurements, spare);
        darker
    } else {
        any
    };
    if predicts_light(measurements, &weighted.n_lum) {
        Some(weighted)
    } else {
        // Every kept light was read above the dark threshold, so a normal that turns away
        // from one of them is a numerical failure, not a solution.
        measurements.clear();
        measurements.extend_from_slice(&buffers.original);
        None
    }
}

/// Backward elimination from `fit` under `rule` until the lights pass the chi-square test, no
/// light is an outlier, or only the options' minimum (or `floor`, when more) is left.
fn reject(
    context: &Context,
    measurements: &mut Vec<Measurement>,
    fit: WeightedFit,
    rule: Rule,
    floor: usize,
) -> WeightedFit {
    let options = context.options;
    let chi = context.chi;
    let usable = measurements.len();
    // The darker-only pass may reject past `max_rejected_fraction`: in a crevice most lights
    // are cast-shadowed, and only the lit ones, however few, give the normal.
    let keep = match rule {
        Rule::Any => ((1.0 - options.max_rejected_fraction) * usable as f64).ceil() as usize,
        Rule::DarkerOnly => 0,
    };
    // Four lights at least: three fit any normal exactly, so a rejection that left three
    // could not be checked, and with four every single removal fits exactly and which light
    // was the outlier is undecidable.
    let keep = keep.max(4).max(floor);
    let mut fit = fit;
    // The darker-only pass's unweighted fit of the current lights: the condition check of a
    // removal computes it (the same sums as `condition_of`), and the next removal picks the
    // darkest light against it.
    let mut unweighted = None;
    while measurements.len() > keep && !chi.accepts_statistic(fit.chi2, measurements.len()) {
        let sigma = options.outlier_sigma;
        let worst = match rule {
            Rule::Any => worst_outlier(chi, measurements, &fit, sigma),
            Rule::DarkerOnly => unweighted
                .take()
                .or_else(|| fit_luminance(measurements))
                .and_then(|unweighted| darkest_outlier(chi, measurements, &unweighted, sigma)),
        };
        let Some(worst) = worst else {
            break;
        };
        let removed = measurements.swap_remove(worst);
        let condition = match rule {
            Rule::Any => condition_of(measurements),
            Rule::DarkerOnly => {
                unweighted = fit_luminance(measurements);
                unweighted.as_ref().map_or(f64::INFINITY, |u| u.condition)
            }
        };
        match weighted_fit(chi, measurements) {
            Some(refit) if condition <= context.max_condition => fit = refit,
            _ => {
                // Dropping it leaves the lights degenerate: keep it.
                measurements.push(removed);
                break;
            }
        }
    }
    fit
}

/// The light whose removal lowers the chi-square statistic most, if its studentised residual
/// `t_k^2 = w_k r_k^2 / (1 - h_k)` (exactly that drop, for weighted least squares) exceeds
/// `sigma^2`.
fn worst_outlier(
    chi: &ChiSquare,
    measurements: &[Measurement],
    fit: &WeightedFit,
    sigma: f64,
) -> Option<usize> {
    let mut worst = None;
    let mut worst_t2 = sigma * sigma;
    for (k, m) in measurements.iter().enumerate() {
        let w = 1.0 / chi.variance(m);
        let leverage = w * m.l.dot(&(fit.cov * m.l));
        let spread = 1.0 - leverage;
        if spread <= 1e-9 {
            // A light no other light can check.
            continue;
        }
        let r = m.lum - fit.n_lum.dot(&m.l);
        let t2 = w * r * r / spread;
        if t2 > worst_t2 {
            worst_t2 = t2;
            worst = Some(k);
        }
    }
    worst
}

/// The light darkest relative to `fit`, the unweighted least-squares fit of `measurements`
/// (reading over prediction), among those significantly darker than it. Unweighted, because
/// inverse-variance weights favour the dark readings, which are the shadowed ones.
fn darkest_outlier(
    chi: &ChiSquare,
    measurements: &[Measurement],
    fit: &LuminanceFit,
    sigma: f64,
) -> Option<usize> {
    let mut darkest = None;
    let mut lowest_ratio = f64::INFINITY;
    for (k, m) in measurements.iter().enumerate() {
        let predicted = fit.n_lum.dot(&m.l);
        let r = m.lum - predicted;
        if r >= 0.0 || predicted <= 0.0 {
            continue;
        }
        let spread = 1.0 - m.l.dot(&(fit.a_inv * m.l));
        if spread <= 1e-9 || r * r <= sigma * sigma * chi.variance(m) * spread {
            continue;
        }
        let ratio = m.lum / predicted;
        if ratio < lowest_ratio {
            lowest_ratio = ratio;
            darkest = Some(k);
        }
    }
    darkest
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One light of unit noise deviation reading `lum` from direction `l`.
    fn reading(l: Vector3<f64>, lum: f64) -> Measurement {
        Measurement {
            l: l.normalize(),
            rgb: [lum; 3],
            lum,
            var: 1.0,
            test_var: 1.0,
            light: 0,
        }
    }

    #[test]
    fn a_light_read_lit_behind_the_normal_contradicts_it() {
        let n = Vector3::new(0.0, 0.0, 100.0);
        let behind = Vector3::new(1.0, 0.0, -0.1);
        let front = Vector3::new(0.3, 0.0, 1.0);
        let sigma = 4.0;
        // Behind the surface, a reading beyond `sigma` noise deviations is light the normal
        // cannot receive; one within them is the noise of an unlit reading.
        assert!(lit_behind_surface(&[reading(behind, 4.5)], &n, sigma));
        assert!(!lit_behind_surface(&[reading(behind, 3.5)], &n, sigma));
        // In front of it any reading is possible (a highlight or a cast shadow).
        assert!(!lit_behind_surface(&[reading(front, 1e3)], &n, sigma));
        assert!(lit_behind_surface(
            &[reading(front, 1e3), reading(behind, 50.0)],
            &n,
            sigma
        ));
    }
}
