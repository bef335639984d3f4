//! Which calibration bundle a solve of a capture set uses: the one the set cites, another one
//! named by the user, or none, checked against the set's citation.

use std::path::PathBuf;

use super::bundle::{self, Bundle};
use crate::capture::CaptureSet;
use crate::error::{BundleProblem, Error, Result};

/// Where a solve's rig comes from when no rig is given explicitly.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum CalibrationChoice {
    /// The bundle the set's manifest cites, read from the path recorded there; sets that cite
    /// none use their rig copy.
    #[default]
    Cited,
    /// This bundle folder; a set that cites another bundle (or this one before its files
    /// changed) is an error unless the mismatch is allowed.
    Bundle(PathBuf),
    /// No bundle: the set's rig copy.
    Ignore,
}

/// The bundle a solve of `set` uses as `choice` says, checked against the one the set cites
/// (a different one is refused unless `allow_mismatch`); `None`: solve with the set's rig
/// copy.
pub fn resolve(
    set: &CaptureSet,
    choice: &CalibrationChoice,
    allow_mismatch: bool,
) -> Result<Option<Bundle>> {
    let cited = set.manifest.calibration.as_ref();
    let bundle = match (choice, cited) {
        (CalibrationChoice::Ignore, _) | (CalibrationChoice::Cited, None) => return Ok(None),
        (CalibrationChoice::Bundle(dir), _) => bundle::read(dir)?,
        (CalibrationChoice::Cited, Some(c)) => {
            if !c.path.join(bundle::INDEX_FILE).is_file() {
                return Err(Error::Bundle {
                    dir: set.dir.clone(),
                    problem: Box::new(BundleProblem::Missing {
                        id: c.id.clone(),
                        path: c.path.clone(),
                    }),
                });
            }
            bundle::read(&c.path).map_err(|e| {
                Error::capture_set(
                    &set.dir,
                    format!("its calibration bundle {} cannot be used: {e}", c.id),
                )
            })?
        }
    };
    if let Some(c) = cited {
        let (id, sha) = (&bundle.index.id, &bundle.index.sha256);
        if (&c.id != id || &c.sha256 != sha) && !allow_mismatch {
            return Err(Error::Bundle {
                dir: set.dir.clone(),
                problem: Box::new(BundleProblem::Mismatch {
                    cited_id: c.id.clone(),
                    cited_sha256: c.sha256.clone(),
                    path: bundle.dir.clone(),
                    id: id.clone(),
                    sha256: sha.clone(),
                }),
            });
        }
    }
    if bundle.rig.leds.len() != set.rig.leds.len() {
        return Err(Error::capture_set(
            &set.dir,
            format!(
                "has frames for {} LEDs, but calibration bundle {} describes {}",
                set.rig.leds.len(),
                bundle.index.id,
                bundle.rig.leds.len()
            ),
        ));
    }
    Ok(Some(bundle))
}
