//! The LED firmware without the board: the real firmware image running in its simavr harness
//! (`firmware/build/psscan-avr-sim`, see firmware/PROTOCOL.md part 2), its UART on a
//! pseudo-terminal that psscan opens with its ordinary serial code, and the harness's pin log,
//! which says which LED pins were high and when. The simulated camera reads the pin log when
//! it fires, so it photographs what the firmware actually lit.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::error::{Error, Result};

const HARNESS: &str = "psscan-avr-sim";
const FIRMWARE_ELF: &str = "psscan_led.elf";
const BUILD_HINT: &str = "build it with `make -C firmware all sim` (Debian packages: gcc-avr \
                          avr-libc simavr libsimavr-dev libelf-dev pkg-config)";

/// Where the harness and the firmware image are.
#[derive(Clone, Debug)]
pub struct EmulatorFiles {
    /// The simavr harness executable, `psscan-avr-sim`.
    pub harness: PathBuf,
    /// The firmware image the harness runs, `psscan_led.elf`.
    pub firmware: PathBuf,
}

impl EmulatorFiles {
    /// Finds `psscan-avr-sim` and `psscan_led.elf` in `$PSSCAN_FIRMWARE_BUILD`, else in
    /// `firmware/build/` under the current folder, else in the source tree psscan was built
    /// from. When the firmware sources are there but not built, builds them with make (once
    /// per process); fails saying how to build them otherwise.
    pub fn locate() -> Result<EmulatorFiles> {
        let mut candidates = Vec::new();
        if let Some(dir) = std::env::var_os("PSSCAN_FIRMWARE_BUILD") {
            candidates.push(PathBuf::from(dir));
        }
        candidates.push(PathBuf::from("firmware/build"));
        candidates.push(Path::new(env!("CARGO_MANIFEST_DIR")).join("firmware/build"));
        let found = |dir: &Path| {
            let files = EmulatorFiles {
                harness: dir.join(HARNESS),
                firmware: dir.join(FIRMWARE_ELF),
            };
            (files.harness.is_file() && files.firmware.is_file()).then_some(files)
        };
        if let Some(files) = candidates.iter().find_map(|d| found(d)) {
            return Ok(files);
        }
        // Sources present: build them (serialised, so parallel tests do not race make).
        static BUILD: std::sync::Mutex<()> = std::sync::Mutex::new(());
        let _guard = BUILD.lock().unwrap_or_else(|p| p.into_inner());
        for dir in &candidates {
            let Some(source) = dir.parent().filter(|s| s.join("Makefile").is_file()) else {
                continue;
            };
            if let Some(files) = found(dir) {
                return Ok(files);
            }
            let output = Command::new("make")
                .arg("-C")
                .arg(source)
                .args(["all", "sim"])
                .output();
            match output {
                Ok(out) if out.status.success() => {
                    if let Some(files) = found(dir) {
                        return Ok(files);
                    }
                }
                Ok(out) => {
                    let stderr = String::from_utf8_lossy(&out.stderr);
                    let tail: Vec<&str> = stderr.lines().rev().take(3).collect();
                    return Err(Error::device(
                        "firmware emulator",
                        format!(
                            "not built, and `make -C {} all sim` failed ({}); {BUILD_HINT}",
                            source.display(),
                            tail.into_iter().rev().collect::<Vec<_>>().join(" / ")
                        ),
                    ));
                }
                Err(e) => {
                    return Err(Error::device(
                        "firmware emulator",
                        format!("not built, and make could not run ({e}); {BUILD_HINT}"),
                    ))
                }
            }
        }
        Err(Error::device(
            "firmware emulator",
            format!(
                "{HARNESS} and {FIRMWARE_ELF} not found in firmware/build (or \
                 $PSSCAN_FIRMWARE_BUILD); {BUILD_HINT}"
            ),
        ))
    }
}

/// A running harness: the firmware on a pty. Stopped (and waited for) when dropped.
pub struct Emulator {
    child: Option<Child>,
    pty: String,
    pin_log: PathBuf,
}

impl Emulator {
    /// Starts the harness with `pin_log` as its pin log and waits for its `PTY` line. The
    /// harness gets `--exit-with-parent`: it stops when the thread that started it ends, so a
    /// killed test run leaves no emulator behind (start it from a thread that outlives it).
    pub fn start(files: &EmulatorFiles, pin_log: &Path) -> Result<Emulator> {
        use std::os::unix::process::CommandExt;
        let mut child = Command::new(&files.harness)
            .arg("--firmware")
            .arg(&files.firmware)
            .arg("--pin-log")
            .arg(pin_log)
            .arg("--exit-with-parent")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            // Its own process group: Ctrl-C in the terminal reaches psscan, which switches
            // the LEDs off through the emulator before stopping it, not the emulator first.
            .process_group(0)
            .spawn()
            .map_err(|e| {
                Error::device(
                    "firmware emulator",
                    format!("cannot start {}: {e}", files.harness.display()),
                )
            })?;
        let stdout = child.stdout.take().expect("piped");
        let mut line = String::new();
        // The harness prints its one line at once or exits (closing stdout) on failure.
        let read = BufReader::new(stdout).read_line(&mut line);
        let pty = match (read, line.strip_prefix("PTY ")) {
            (Ok(_), Some(path)) if path.ends_with('\n') => path.trim_end().to_string(),
            _ => {
                let _ = child.kill();
                let mut stderr = String::new();
                if let Some(mut err) = child.stderr.take() {
                    use std::io::Read;
                    let _ = err.read_to_string(&mut stderr);
                }
                let _ = child.wait();
                return Err(Error::device(
                    "firmware emulator",
                    format!(
                        "{} did not print its PTY line (got {:?}): {}",
                        files.harness.display(),
                        line,
                        stderr.trim()
                    ),
                ));
            }
        };
        // simavr chatters on stderr; drain it so the pipe never fills.
        if let Some(mut err) = child.stderr.take() {
            std::thread::spawn(move || {
                let _ = std::io::copy(&mut err, &mut std::io::sink());
            });
        }
        Ok(Emulator {
            child: Some(child),
            pty,
            pin_log: pin_log.to_path_buf(),
        })
    }

    /// The pseudo-terminal to open as the controller's serial port.
    pub fn pty(&self) -> &str {
        &self.pty
    }

    /// A reader of the pin log this emulator writes.
    pub fn pin_log(&self) -> PinLog {
        PinLog::new(&self.pin_log)
    }

    /// The harness's process id; `None` once it has been stopped or killed.
    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(|c| c.id())
    }

    /// Kills the emulator abruptly (SIGKILL), as a pulled cable and a dead board would look
    /// to the host: the port vanishes.
    pub fn kill(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    /// Stops the emulator cleanly (SIGTERM: the pin log gets its `# exit` line).
    pub fn stop(&mut self) {
        if let Some(mut child) = self.child.take() {
            // SAFETY: kill(2) on our own child's pid, which we have not yet waited for.
            unsafe {
                libc::kill(child.id() as libc::pid_t, libc::SIGTERM);
            }
            let end = Instant::now() + Duration::from_secs(3);
            loop {
                match child.try_wait() {
                    Ok(Some(_)) => return,
                    Ok(None) if Instant::now() < end => {
                        std::thread::sleep(Duration::from_millis(5))
                    }
                    _ => {
                        let _ = child.kill();
                        let _ = child.wait();
                        return;
                    }
                }
            }
        }
    }
}

impl Drop for Emulator {
    fn drop(&mut self) {
        self.stop();
    }
}

/// One LED pin change in the pin log.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct PinEvent {
    /// Simulated time of the change, microseconds since the simulation started.
    pub sim_us: u64,
    /// Microseconds since the harness started (monotonic clock).
    pub wall_us: u64,
    /// The LED whose pin changed, by its controller index.
    pub led: usize,
    /// Whether the pin went high (LED on) or low.
    pub on: bool,
}

/// A pin log read at one moment.
#[derive(Clone, Debug, Default)]
pub struct PinHistory {
    /// Unix time (µs) of the harness's start: `start_unix_us + wall_us` is an event's time.
    pub start_unix_us: u64,
    /// LED channels the harness logs (from the log's header).
    pub leds: usize,
    /// Every LED pin change, in the order logged.
    pub events: Vec<PinEvent>,
    /// `# reset`, `# exit`, ... markers, with their simulated time.
    pub markers: Vec<(String, u64)>,
}

impl PinHistory {
    /// The LEDs whose last level is high after the events for which `until(event)` holds
    /// (all events: the state now).
    fn lit_after(&self, until: impl Fn(&PinEvent) -> bool) -> Vec<usize> {
        let mut level = vec![false; self.leds.max(1)];
        for e in self.events.iter().filter(|e| until(e)) {
            if e.led >= level.len() {
                level.resize(e.led + 1, false);
            }
            level[e.led] = e.on;
        }
        (0..level.len()).filter(|&k| level[k]).collect()
    }

    /// The LEDs on at the end of the log.
    pub fn lit_now(&self) -> Vec<usize> {
        self.lit_after(|_| true)
    }

    /// The LEDs on at Unix time `unix_us`.
    pub fn lit_at_unix_us(&self, unix_us: u64) -> Vec<usize> {
        self.lit_after(|e| self.start_unix_us + e.wall_us <= unix_us)
    }

    /// The largest number of LEDs that were ever on together.
    pub fn max_lit_together(&self) -> usize {
        let mut level = vec![false; self.leds.max(10)];
        let mut most = 0;
        for e in &self.events {
            if e.led < level.len() {
                level[e.led] = e.on;
            }
            most = most.max(level.iter().filter(|&&l| l).count());
        }
        most
    }
}

/// The harness's pin log file (format in firmware/PROTOCOL.md, "Pin log").
#[derive(Clone, Debug)]
pub struct PinLog {
    path: PathBuf,
}

impl PinLog {
    /// A reader of the pin log at `path` (the file need not exist yet).
    pub fn new(path: &Path) -> PinLog {
        PinLog {
            path: path.to_path_buf(),
        }
    }

    /// The pin log's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Reads the whole log. A last line without LF is being written and is ignored; data
    /// lines are parsed by key, so later fields do not break the reader.
    pub fn read(&self) -> Result<PinHistory> {
        let text = std::fs::read_to_string(&self.path).map_err(|e| Error::io(&self.path, e))?;
        parse_pin_log(&text).map_err(|m| Error::config(&self.path, "pin log", m))
    }

    /// The LEDs on now, by the log.
    pub fn lit(&self) -> Result<Vec<usize>> {
        Ok(self.read()?.lit_now())
    }
}

fn parse_pin_log(text: &str) -> std::result::Result<PinHistory, String> {
    let mut history = PinHistory::default();
    let complete = match text.rfind('\n') {
        Some(end) => &text[..end],
        None => "",
    };
    for (i, line) in complete.lines().enumerate() {
        let fields = |s: &str| -> Vec<(String, String)> {
            s.split(' ')
                .filter_map(|w| w.split_once('='))
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect()
        };
        if let Some(comment) = line.strip_prefix("# ") {
            let kv = fields(comment);
            let get = |key: &str| kv.iter().find(|(k, _)| k == key).map(|(_, v)| v.as_str());
            if comment.starts_with("psscan-avr-sim pinlog v1") {
                history.start_unix_us = get("start_unix_us")
                    .and_then(|v| v.parse().ok())
                    .ok_or(format!("line {}: header without start_unix_us", i + 1))?;
                history.leds = get("leds").map_or(0, |v| v.split(',').count());
            } else {
                let name = comment.split(' ').next().unwrap_or_default().to_string();
                let sim_us = get("sim_us").and_then(|v| v.parse().ok()).unwrap_or(0);
                history.markers.push((name, sim_us));
            }
            continue;
        }
        let kv = fields(line);
        let get = |key: &str| -> std::result::Result<u64, String> {
            kv.iter()
                .find(|(k, _)| k == key)
                .and_then(|(_, v)| v.parse().ok())
                .ok_or(format!("line {}: no {key} in {line:?}", i + 1))
        };
        history.events.push(PinEvent {
            sim_us: get("sim_us")?,
            wall_us: get("wall_us")?,
            led: get("led")? as usize,
            on: get("level")? == 1,
        });
    }
    Ok(history)
}

#[cfg(test)]
mod tests {
    use super::*;

    const LOG: &str = "# psscan-avr-sim pinlog v1 mcu=atmega328p f_cpu=16000000 start_unix_us=1000000 leds=0:PD2,1:PD3,2:PD4\n\
# power-on sim_us=0 wall_us=25\n\
sim_us=0 wall_us=26 led=0 level=0\n\
sim_us=0 wall_us=26 led=1 level=0\n\
sim_us=5822 wall_us=5837 led=1 level=1\n\
sim_us=7822 wall_us=7840 led=1 level=0\n\
sim_us=7823 wall_us=7850 led=2 level=1 extra=7\n\
sim_us=9000 wall_us=9000 led=0 lev";

    #[test]
    fn the_pin_log_reads_as_documented() {
        let h = parse_pin_log(LOG).unwrap();
        assert_eq!(h.start_unix_us, 1_000_000);
        assert_eq!(h.leds, 3);
        assert_eq!(h.events.len(), 5, "the unfinished last line is ignored");
        assert_eq!(h.lit_now(), vec![2]);
        assert_eq!(h.lit_at_unix_us(1_000_000 + 6000), vec![1]);
        assert_eq!(h.lit_at_unix_us(1_000_000 + 7845), Vec::<usize>::new());
        assert_eq!(h.max_lit_together(), 1);
        assert_eq!(h.markers[0].0, "power-on");
        assert!(parse_pin_log("sim_us=1 led=0 level=1\n").is_err());
    }
}
