//! Published reference figures for the real-data sets psscan is evaluated on, from the READMEs
//! of the data folders (the benchmark's own tables and the reference implementations of the
//! robust methods). Kept in code, not parsed from the READMEs: a README is prose for people.

use serde::Serialize;

/// A published mean angular error (degrees) of one method on one set at one light count.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Anchor {
    /// The set's folder name.
    pub set: &'static str,
    /// Lights the figure used (the set's full count).
    pub lights: usize,
    /// The method, as the source names it.
    pub method: &'static str,
    /// The published mean angular error, in degrees.
    pub mean_deg: f64,
}

const fn anchor(set: &'static str, lights: usize, method: &'static str, mean_deg: f64) -> Anchor {
    Anchor {
        set,
        lights,
        method,
        mean_deg,
    }
}

/// Every known anchor. DiLiGenT bear: least squares as the benchmark publishes it (L2); the
/// bunny renders: the four reference implementations of yasumat/RobustPhotometricStereo.
pub const PUBLISHED: [Anchor; 13] = [
    anchor("diligent-bear", 96, "published L2", 8.39),
    anchor("bunny_lambert_noshadow", 50, "L2", 1.006),
    anchor("bunny_lambert_noshadow", 50, "RPCA", 0.705),
    anchor("bunny_lambert_noshadow", 50, "L1", 0.143),
    anchor("bunny_lambert_noshadow", 50, "SBL", 0.138),
    anchor("bunny_lambert", 50, "L2", 4.157),
    anchor("bunny_lambert", 50, "RPCA", 3.239),
    anchor("bunny_lambert", 50, "L1", 3.409),
    anchor("bunny_lambert", 50, "SBL", 3.704),
    anchor("bunny_specular", 50, "L2", 18.47),
    anchor("bunny_specular", 50, "RPCA", 3.384),
    anchor("bunny_specular", 50, "L1", 4.598),
    anchor("bunny_specular", 50, "SBL", 3.973),
];

/// The published anchors of `set` at `lights` lights.
pub fn published(set: &str, lights: usize) -> Vec<Anchor> {
    PUBLISHED
        .iter()
        .filter(|a| a.set == set && a.lights == lights)
        .cloned()
        .collect()
}
