//! The reference to a calibration bundle that capture manifests and solve reports record.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

/// What a capture manifest and a solve report record of the bundle they used.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationRef {
    /// The bundle's id (`<rig>/<name>/<checksum prefix>`).
    pub id: String,
    /// The bundle's checksum (defined in `calibration::bundle`'s docs).
    pub sha256: String,
    /// Where the bundle was when it was cited (absolute when it could be resolved).
    pub path: PathBuf,
}
