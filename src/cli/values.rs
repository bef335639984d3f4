//! Value parsers for options with a range: clap runs them while parsing, so a value out of
//! range is a usage error (clap's message naming the option, the usage line, exit 2) before
//! any work starts.

use psscan::region::Roi;

/// A whole number, 1 or more (counts: repeats, sets at once, pixels).
pub fn positive_count(text: &str) -> Result<usize, String> {
    match text.trim().parse::<usize>() {
        Ok(0) => Err("must be 1 or more".into()),
        Ok(n) => Ok(n),
        Err(e) => Err(format!("{e} (expected a whole number, 1 or more)")),
    }
}

fn finite(text: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(_) => Err("must be a finite number".into()),
        Err(e) => Err(format!("{e} (expected a number)")),
    }
}

/// A finite number, 0 or more (fractions that may be zero).
pub fn non_negative(text: &str) -> Result<f64, String> {
    let v = finite(text)?;
    if v < 0.0 {
        return Err("must be 0 or more".into());
    }
    Ok(v)
}

/// A finite number above 0 (tolerances, steps).
pub fn positive(text: &str) -> Result<f64, String> {
    let v = finite(text)?;
    if v <= 0.0 {
        return Err("must be more than 0".into());
    }
    Ok(v)
}

/// A bench scene size in megapixels: more than 0, at most 64.
pub fn megapixels(text: &str) -> Result<f64, String> {
    let v = positive(text)?;
    if v > 64.0 {
        return Err("must be at most 64 megapixels".into());
    }
    Ok(v)
}

/// A pixel rectangle `x,y,w,h` with a positive width and height.
pub fn roi(text: &str) -> Result<Roi, String> {
    Roi::parse(text).map_err(|_| "expected x,y,w,h: whole numbers, w and h 1 or more".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_are_enforced() {
        assert_eq!(positive_count("3"), Ok(3));
        assert!(positive_count("0").is_err() && positive_count("-1").is_err());
        assert_eq!(non_negative("0"), Ok(0.0));
        assert!(non_negative("-0.1").is_err() && non_negative("nan").is_err());
        assert!(positive("0").is_err() && positive("inf").is_err());
        assert!(megapixels("0").is_err() && megapixels("65").is_err());
        assert_eq!(megapixels("0.12"), Ok(0.12));
        assert!(roi("10,10,0,50").is_err() && roi("10,10,5,5").is_ok());
    }
}
