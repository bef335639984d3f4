//! A camera driven by an external command, e.g.
//! `gphoto2 --capture-image-and-download --filename {out}`: the template is split like a
//! shell would (no shell runs it), `{out}` is replaced by the file to write, and the command
//! must exit 0 having written that file.

use std::io::Read;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use super::unix_now_us;
use super::{extension_of, raw_image_info, Camera, Shot};
use crate::capture::interrupt::Interrupt;
use crate::capture::manifest::{CameraSettings, ImageInfo};
use crate::error::{Error, Result};
use crate::rig::Rig;

const OUT: &str = "{out}";

/// A camera that runs an external command for every shot: the command template, split into
/// arguments, with `{out}` replaced by the file the frame must be written to.
pub struct CommandCamera {
    template: String,
    argv: Vec<String>,
    extension: Option<String>,
    timeout: Duration,
}

impl CommandCamera {
    /// `template` must contain `{out}`. `extension`: what to name the frames (default: `png`
    /// for PNG output, else `raw`). `timeout`: the longest one shot may take.
    pub fn new(template: &str, extension: Option<&str>, timeout: Duration) -> Result<Self> {
        let argv = shlex::split(template).ok_or_else(|| {
            Error::Invalid(format!(
                "camera command {template:?}: unbalanced quotes or a trailing backslash"
            ))
        })?;
        if argv.is_empty() {
            return Err(Error::Invalid("the camera command is empty".into()));
        }
        if !argv.iter().any(|a| a.contains(OUT)) {
            return Err(Error::Invalid(format!(
                "camera command {template:?} has no {OUT}: psscan needs to tell it where to \
                 write the photograph"
            )));
        }
        if let Some(ext) = extension {
            if extension_of(&format!("x.{ext}")).is_none() {
                return Err(Error::Invalid(format!(
                    "frame extension {ext:?}: letters and digits only"
                )));
            }
        }
        Ok(CommandCamera {
            template: template.to_string(),
            argv,
            extension: extension.map(|e| e.to_ascii_lowercase()),
            timeout,
        })
    }

    fn device(&self) -> String {
        format!("camera command `{}`", self.template)
    }
}

impl Camera for CommandCamera {
    fn name(&self) -> String {
        self.device()
    }

    fn settings(&mut self) -> Result<CameraSettings> {
        Ok(CameraSettings {
            model: format!("external command: {}", self.template),
            ..Default::default()
        })
    }

    fn image_info(&self, rig: &Rig) -> ImageInfo {
        raw_image_info(rig)
    }

    fn max_shot_time(&self) -> Duration {
        self.timeout
    }

    fn capture(&mut self, dest: &Path, interrupt: &Interrupt) -> Result<Shot> {
        let out = dest.to_string_lossy();
        let argv: Vec<String> = self.argv.iter().map(|a| a.replace(OUT, &out)).collect();
        let _ = std::fs::remove_file(dest);
        let fired_unix_us = unix_now_us();
        let mut child = Command::new(&argv[0])
            .args(&argv[1..])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| Error::device(self.device(), format!("cannot run {:?}: {e}", argv[0])))?;
        // Collect stderr on the side so a chatty command cannot block on a full pipe.
        let mut stderr = child.stderr.take().expect("piped");
        let reader = std::thread::spawn(move || {
            let mut text = String::new();
            let _ = stderr.read_to_string(&mut text);
            text
        });
        let start = Instant::now();
        let status = loop {
            match child.try_wait() {
                Ok(Some(status)) => break status,
                Ok(None) => {}
                Err(e) => return Err(Error::device(self.device(), format!("wait failed: {e}"))),
            }
            let stop = if interrupt.is_set() {
                Some("interrupted")
            } else if start.elapsed() > self.timeout {
                Some("timed out")
            } else {
                None
            };
            if let Some(why) = stop {
                let _ = child.kill();
                let _ = child.wait();
                let message = format!(
                    "{why} after {:.1} s; the command was stopped",
                    start.elapsed().as_secs_f64()
                );
                return Err(if interrupt.is_set() {
                    Error::Interrupted(format!("{}: {message}", self.device()))
                } else {
                    Error::device(self.device(), message)
                });
            }
            std::thread::sleep(Duration::from_millis(10));
        };
        let stderr = reader.join().unwrap_or_default();
        if !status.success() {
            let tail: Vec<&str> = stderr.lines().rev().take(3).collect();
            let tail = tail.into_iter().rev().collect::<Vec<_>>().join(" / ");
            return Err(Error::device(
                self.device(),
                format!(
                    "failed ({status}){}",
                    if tail.is_empty() {
                        String::new()
                    } else {
                        format!(": {tail}")
                    }
                ),
            ));
        }
        let len = std::fs::metadata(dest).map(|m| m.len()).unwrap_or(0);
        if len == 0 {
            return Err(Error::device(
                self.device(),
                format!("exited 0 but wrote nothing to {}", dest.display()),
            ));
        }
        let extension = match &self.extension {
            Some(ext) => ext.clone(),
            None => sniff_extension(dest),
        };
        Ok(Shot {
            extension,
            lit: None,
            fired_unix_us,
        })
    }
}

/// `png` for a PNG, else `raw` (a RAW's own format is found from its content when decoded).
fn sniff_extension(path: &Path) -> String {
    let mut head = [0u8; 8];
    let is_png = std::fs::File::open(path)
        .and_then(|mut f| f.read_exact(&mut head))
        .is_ok()
        && head == *b"\x89PNG\r\n\x1a\n";
    if is_png { "png" } else { "raw" }.into()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn templates_are_checked() {
        assert!(
            CommandCamera::new("gphoto2 --filename {out}", None, Duration::from_secs(1)).is_ok()
        );
        let err = CommandCamera::new("gphoto2 --capture", None, Duration::from_secs(1))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("{out}"), "{err}");
        assert!(CommandCamera::new("sh -c 'x {out}", None, Duration::from_secs(1)).is_err());
        assert!(CommandCamera::new("cp a {out}", Some("n/ef"), Duration::from_secs(1)).is_err());
    }

    #[test]
    fn a_command_writes_the_frame_and_failures_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let dest = dir.path().join("shot");
        let stop = Interrupt::new();
        let mut ok = CommandCamera::new(
            "sh -c 'printf abc > \"$1\"' sh {out}",
            Some("NEF"),
            Duration::from_secs(10),
        )
        .unwrap();
        let shot = ok.capture(&dest, &stop).unwrap();
        assert_eq!(std::fs::read(&dest).unwrap(), b"abc");
        assert_eq!(shot.extension, "nef");

        let mut failing = CommandCamera::new(
            "sh -c 'echo no camera found >&2; exit 3' sh {out}",
            None,
            Duration::from_secs(10),
        )
        .unwrap();
        let err = failing.capture(&dest, &stop).unwrap_err().to_string();
        assert!(
            err.contains("no camera found") && err.contains("3"),
            "{err}"
        );

        let mut silent = CommandCamera::new("true {out}", None, Duration::from_secs(10)).unwrap();
        let err = silent.capture(&dest, &stop).unwrap_err().to_string();
        assert!(err.contains("wrote nothing"), "{err}");

        let mut slow =
            CommandCamera::new("sh -c 'sleep 5' sh {out}", None, Duration::from_millis(100))
                .unwrap();
        let err = slow.capture(&dest, &stop).unwrap_err().to_string();
        assert!(err.contains("timed out"), "{err}");

        stop.set();
        let mut slow =
            CommandCamera::new("sh -c 'sleep 5' sh {out}", None, Duration::from_secs(10)).unwrap();
        let err = slow.capture(&dest, &stop).unwrap_err();
        assert!(matches!(err, Error::Interrupted(_)), "{err}");
    }
}
