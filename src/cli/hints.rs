//! Flag hints: the library's typed errors say what went wrong; this adds which of psscan's
//! flags (or which command) fixes it, so only the CLI knows the flags' names.

use psscan::error::{BundleProblem, Conflict, Needed, Occupied, PortSearch};
use psscan::Error;

/// How a stopped capture is completed from the command that ran it.
#[derive(Clone, Copy)]
pub(super) enum Resume {
    /// `psscan capture`: the same command with `--resume`.
    WithFlag,
    /// The calibration wizard: the same command resumes by itself.
    SameCommand,
}

/// The advice for the first error in `err`'s chain that has one, to append to its text.
pub(super) fn for_chain(err: &anyhow::Error, resume: Resume) -> Option<&'static str> {
    err.chain()
        .filter_map(|cause| cause.downcast_ref::<Error>())
        .find_map(|e| hint(e, resume))
}

/// `text` with the advice for `err`, if it has one, after a semicolon.
pub(super) fn with_hint(text: String, err: &Error, resume: Resume) -> String {
    match hint(err, resume) {
        Some(h) => format!("{text}; {h}"),
        None => text,
    }
}

/// What the user can pass to get past `err`, in the CLI's words.
fn hint(err: &Error, resume: Resume) -> Option<&'static str> {
    Some(match err {
        Error::Exists { .. } => "pass --force to overwrite it",
        Error::SetOccupied { state, .. } => match state {
            Occupied::Complete => {
                "--resume has nothing left to shoot: pass --force to shoot it again (its frames \
                 are replaced), or choose another --out"
            }
            Occupied::Unfinished { .. } => "pass --resume to complete it, or --force to start over",
            Occupied::OtherRig { .. } => "resume with the set's rig, or pass --force to start over",
            Occupied::OtherFrames { .. } => {
                "resume with the same camera settings, or pass --force to start over"
            }
        },
        Error::Resumable { .. } => match resume {
            Resume::WithFlag => "run the same command with --resume to complete the set",
            Resume::SameCommand => "run the same psscan calibrate command to resume",
        },
        Error::NoPort(search) => match search {
            PortSearch::NoSysfs => "give the port with --port PATH",
            PortSearch::Several { .. } => "--port auto needs one: choose it with --port PATH",
            PortSearch::NoArduino { .. } => {
                "plug the LED controller in, or give its port with --port PATH"
            }
        },
        Error::Bundle { problem, .. } => match **problem {
            BundleProblem::Missing { .. } => {
                "pass --calibration DIR where the bundle is now, or --no-calibration to solve \
                 with the rig copy in the set"
            }
            BundleProblem::Mismatch { .. } => {
                "solve with the bundle the set cites, or pass --allow-calibration-mismatch to \
                 use this one anyway (the report records both)"
            }
        },
        Error::Incompatible(conflict) => match conflict {
            Conflict::RobustStreaming => {
                "drop --precision f32 and --tile-tolerance, or use --estimator adaptive (the \
                 streaming least squares, the robust fit only where the residual asks for it)"
            }
            Conflict::SvdStreaming => "drop --precision f32 and --tile-tolerance",
            Conflict::CameraWithoutTable => "give --table with --camera",
            Conflict::TableWithoutCamera => "give --camera with --table",
            Conflict::RegionOnDiligent { .. } => {
                "--roi, --bin and --background apply to psscan capture sets only"
            }
        },
        Error::NeedsValue(needed) => match needed {
            Needed::ChartRect { .. } => "give the chart's place with --rect X,Y,W,H",
            Needed::SensorStep { .. } => {
                "give --step (sensor pixels per image pixel; the photographs are taken as \
                 centred on the sensor)"
            }
        },
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    #[test]
    fn every_kind_that_a_flag_fixes_names_the_flag() {
        let dir = PathBuf::from("set");
        let cases: Vec<(Error, &str)> = vec![
            (Error::Exists { path: dir.clone() }, "--force"),
            (
                Error::SetOccupied {
                    dir: dir.clone(),
                    state: Occupied::Complete,
                },
                "--out",
            ),
            (
                Error::SetOccupied {
                    dir: dir.clone(),
                    state: Occupied::Unfinished { kept: 2, total: 11 },
                },
                "--resume",
            ),
            (
                Error::Resumable {
                    dir: dir.clone(),
                    source: Box::new(Error::Interrupted("Ctrl-C".into())),
                },
                "--resume",
            ),
            (
                Error::Incompatible(Conflict::RobustStreaming),
                "--estimator adaptive",
            ),
            (Error::Incompatible(Conflict::CameraWithoutTable), "--table"),
            (
                Error::NoPort(PortSearch::NoArduino {
                    seen: "no serial ports at all".into(),
                }),
                "--port PATH",
            ),
            (
                Error::Bundle {
                    dir: dir.clone(),
                    problem: Box::new(BundleProblem::Missing {
                        id: "b1".into(),
                        path: dir.clone(),
                    }),
                },
                "--no-calibration",
            ),
            (
                Error::NeedsValue(Needed::ChartRect {
                    reason: "the gray chart was not found in the photographs".into(),
                }),
                "--rect X,Y,W,H",
            ),
            (
                Error::NeedsValue(Needed::SensorStep {
                    reason: "the photographs are 1024x512".into(),
                }),
                "--step",
            ),
        ];
        for (err, flag) in cases {
            let text = with_hint(err.to_string(), &err, Resume::WithFlag);
            assert!(text.contains(flag), "{text}");
            // The library's own text names no flag.
            assert!(!err.to_string().contains("--"), "{err}");
        }
    }

    #[test]
    fn the_wizard_resumes_without_a_flag() {
        let err = anyhow::Error::new(Error::Resumable {
            dir: PathBuf::from("set"),
            source: Box::new(Error::Interrupted("Ctrl-C".into())),
        });
        let hint = for_chain(&err, Resume::SameCommand).unwrap();
        assert!(
            hint.contains("psscan calibrate") && !hint.contains("--resume"),
            "{hint}"
        );
    }
}
