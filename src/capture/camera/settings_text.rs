//! The exposure settings as a tethered camera's driver shows them (libgphoto2's widget text:
//! `ISO 400`, `1/125`, `f/5.6`), parsed into numbers. Outside the `gphoto2` feature so that
//! these pure functions are tested by the main suite, which does not build that feature.

/// ISO from a camera's text (`100`, `ISO 100`); `Auto` and the like give `None`.
pub fn parse_iso(text: &str) -> Option<u32> {
    text.trim().trim_start_matches("ISO").trim().parse().ok()
}

/// Shutter time in seconds from `1/125`, `0.5`, `2`, `2s`, `1/125s`; `bulb` gives `None`.
pub fn parse_shutter(text: &str) -> Option<f64> {
    let t = text.trim().trim_end_matches('s').trim();
    let value = match t.split_once('/') {
        Some((n, d)) => n.trim().parse::<f64>().ok()? / d.trim().parse::<f64>().ok()?,
        None => t.parse::<f64>().ok()?,
    };
    (value.is_finite() && value > 0.0).then_some(value)
}

/// Aperture f-number from `f/8`, `f/5.6`, `8`, `5.6`.
pub fn parse_aperture(text: &str) -> Option<f64> {
    let t = text.trim().trim_start_matches("f/").trim_start_matches('f');
    t.parse::<f64>().ok().filter(|v| v.is_finite() && *v > 0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_text_parses() {
        assert_eq!(parse_iso("100"), Some(100));
        assert_eq!(parse_iso("ISO 400"), Some(400));
        assert_eq!(parse_iso("Auto"), None);
        assert_eq!(parse_shutter("1/125"), Some(1.0 / 125.0));
        assert_eq!(parse_shutter("2s"), Some(2.0));
        assert_eq!(parse_shutter("0.5"), Some(0.5));
        assert_eq!(parse_shutter("bulb"), None);
        assert_eq!(parse_aperture("f/5.6"), Some(5.6));
        assert_eq!(parse_aperture("8"), Some(8.0));
        assert_eq!(parse_aperture("implicit auto"), None);
    }
}
