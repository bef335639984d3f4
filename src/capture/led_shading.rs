//! The LEDs' shading vectors over a capture set's sensor window, for the full-resolution RAW
//! demosaic (`raw::ShadingField`): `raw` develops frames without knowing about lights, so the
//! set that knows its rig hands them over as plain vectors.

use crate::plane::SensorWindow;
use crate::raw::ShadingField;
use crate::rig::Rig;
use crate::solve::{Illumination, LightModel, LightSource};

/// Grid step (in mosaic samples) of the sampled field. The LEDs stand hundreds of millimetres
/// from a sample seen at a fraction of a millimetre per pixel, so their direction and
/// irradiance are smooth on this scale and the bilinear interpolation between nodes is far
/// below the sensor noise.
const STEP: usize = 16;

/// Each LED's direction times its irradiance (the near-light model with the beam falloff) at
/// every mosaic sample of a `width x height` mosaic at `window`, in LED order; `None` when the
/// rig has fewer than three LEDs (a fit needs three) or its camera misses the sample plane.
pub fn led_shading_field(
    rig: &Rig,
    width: usize,
    height: usize,
    window: SensorWindow,
) -> Option<ShadingField> {
    if rig.leds.len() < 3 {
        return None;
    }
    let lights = Illumination::new(
        &LightSource::Rig(rig),
        LightModel::Near,
        width,
        height,
        window,
    )
    .ok()?;
    ShadingField::sample(width, height, STEP, |x, y| {
        let point = lights.point_at(x, y).ok_or_else(|| {
            crate::error::Error::Invalid(format!("pixel ({x}, {y}) misses the sample plane"))
        })?;
        Ok((0..lights.len())
            .map(|k| {
                let s = lights.sample(k, &point);
                (s.direction * s.falloff).into()
            })
            .collect())
    })
    .ok()
}
