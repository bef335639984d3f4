//! The LED controller on a serial port (the Arduino over USB, or the firmware emulator's
//! pseudo-terminal): open, handshake and version check, one command at a time with a
//! per-command timeout and one retry, and errors that say what happened to the line.

use std::io::{ErrorKind, Read, Write};
use std::time::{Duration, Instant};

use serialport::SerialPort;

use super::protocol::{
    parse_reply, quote, quote_bytes, Answer, Command, FirmwareInfo, LightState, Reply, MAX_ANSWER,
    TIMEOUT_RANGE_MS,
};
use super::LightController;
use crate::error::{Error, LinkError, PortProblem, Result};

/// How to talk to the controller.
#[derive(Clone, Debug)]
pub struct SerialOptions {
    /// Line speed in baud (the firmware's is 115200).
    pub baud: u32,
    /// How long to wait for the `READY` banner after opening (an Uno resets when the port
    /// opens and runs its bootloader for 0.5-2 s). `None`: 2.5 s on a serial device, none on a
    /// pseudo-terminal (the emulator has no bootloader; its banner is already queued).
    pub ready_wait: Option<Duration>,
    /// How long one command may wait for its answer (the protocol suggests ~1 s).
    pub command_timeout: Duration,
}

impl Default for SerialOptions {
    fn default() -> Self {
        SerialOptions {
            baud: 115_200,
            ready_wait: None,
            command_timeout: Duration::from_millis(1000),
        }
    }
}

/// Deliberate damage to one outgoing command, the next `times` times it is sent: `garbage`
/// goes on the line right before it, as noise on the wire would. For fault tests and for
/// checking a rig's link on the bench; never set in a normal capture.
#[derive(Clone, Debug)]
pub struct LineNoise {
    /// The command line to damage, e.g. `ON 3`.
    pub command: String,
    /// How many more times the command is damaged; at zero the noise stops.
    pub times: usize,
    /// The bytes written to the line right before the command.
    pub garbage: Vec<u8>,
}

/// Why one request failed, before it is named ([`LinkError`] says which request).
#[derive(Debug)]
enum Failure {
    /// No complete answer line in time.
    Timeout,
    /// The port is gone (EOF, hang-up, I/O error).
    Vanished(std::io::Error),
    /// A line that is not an answer to what was sent.
    Malformed(String),
    /// `ERR <code> <reason>`.
    Refused { code: u32, reason: String },
}

/// The psscan LED controller on a serial port.
pub struct SerialLights {
    port: Box<dyn SerialPort>,
    path: String,
    options: SerialOptions,
    rx: Vec<u8>,
    info: Option<FirmwareInfo>,
    /// The timeout this host set, sent again if the board resets mid-session.
    timeout_ms: Option<u32>,
    noise: Option<LineNoise>,
    /// `READY` banners seen after the handshake (board resets).
    resets: u32,
    in_session: bool,
    vanished: bool,
}

impl SerialLights {
    /// Opens `path`, waits for the board to come up, identifies it and checks its protocol.
    pub fn open(path: &str, options: SerialOptions) -> Result<SerialLights> {
        let port = serialport::new(path, options.baud)
            .timeout(Duration::from_millis(20))
            .dtr_on_open(true)
            .open()
            .map_err(|e| open_error(path, e))?;
        let mut lights = SerialLights {
            port,
            path: path.to_string(),
            options,
            rx: Vec::new(),
            info: None,
            timeout_ms: None,
            noise: None,
            resets: 0,
            in_session: false,
            vanished: false,
        };
        lights.wait_ready()?;
        lights.identify()?;
        lights.in_session = true;
        Ok(lights)
    }

    /// The serial port's path, as opened.
    pub fn path(&self) -> &str {
        &self.path
    }

    /// The identity read at the handshake.
    pub fn info(&self) -> Option<&FirmwareInfo> {
        self.info.as_ref()
    }

    /// How often the board announced a reset (`READY`) after the handshake.
    pub fn resets(&self) -> u32 {
        self.resets
    }

    /// Damages a command the next times it is sent ([`LineNoise`]); `None` stops any damage.
    pub fn set_line_noise(&mut self, noise: Option<LineNoise>) {
        self.noise = noise;
    }

    /// Sends `bytes` as one line, exactly as given (plus LF), and returns the text of its
    /// `OK` answer; an `ERR` answer becomes an error quoting the line and the reason. For
    /// bench work and tests of the firmware's handling of bad input.
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<String> {
        let deadline = Instant::now() + self.options.command_timeout;
        let mut line = bytes.to_vec();
        line.push(b'\n');
        self.write(&line)
            .map_err(|e| self.error(e, &quote_bytes(bytes)))?;
        loop {
            let received = self
                .read_line(deadline)
                .map_err(|e| self.error(e, &quote_bytes(bytes)))?;
            match parse_reply(&received) {
                Ok(Reply::Ok(rest)) => return Ok(rest),
                Ok(Reply::Err { code, reason }) => {
                    return Err(self.error(Failure::Refused { code, reason }, &quote_bytes(bytes)))
                }
                Ok(Reply::Ready(_)) => self.note_reset(),
                Err(m) => return Err(self.error(Failure::Malformed(m), &quote_bytes(bytes))),
            }
        }
    }

    fn device(&self) -> String {
        format!("LED controller on {}", self.path)
    }

    /// Waits for the `READY` banner (or for the wait to run out: a board without auto-reset
    /// printed it long ago). Other lines before it are leftovers and are dropped.
    fn wait_ready(&mut self) -> Result<()> {
        let wait = self.options.ready_wait.unwrap_or_else(|| {
            if self.path.starts_with("/dev/pts/") {
                Duration::ZERO
            } else {
                Duration::from_millis(2500)
            }
        });
        // Even with no wait, read what is already queued, so a banner is not mistaken for
        // the answer to the first command.
        let deadline = Instant::now() + wait.max(Duration::from_millis(30));
        loop {
            match self.read_line(deadline) {
                Ok(line) if line.starts_with("READY ") => return Ok(()),
                Ok(_) => continue,
                Err(Failure::Timeout) => return Ok(()),
                Err(Failure::Malformed(_)) => continue,
                Err(e) => return Err(self.error(e, "the handshake")),
            }
        }
    }

    /// One command with one retry after a resynchronisation. The host only sends
    /// well-formed lines, so a missing answer, a garbled one, or a refusal (`ERR 3` for a
    /// short line, `ERR 5`, `ERR 1` for a known command) means the line was damaged on the
    /// way; a second refusal is reported as the firmware's answer.
    fn command(&mut self, command: Command) -> Result<Answer> {
        let what = quote(&command.line());
        match self.exchange(command) {
            Ok(answer) => Ok(answer),
            Err(e @ Failure::Vanished(_)) => Err(self.error(e, &what)),
            Err(_first) => {
                self.resync().map_err(|e| self.error(e, &what))?;
                self.exchange(command)
                    .map_err(|e| self.error(e, &format!("{what} (after one retry)")))
            }
        }
    }

    /// Sends one line and reads until its answer.
    fn exchange(&mut self, command: Command) -> std::result::Result<Answer, Failure> {
        let line = command.line();
        let mut bytes = Vec::with_capacity(line.len() + 8);
        if let Some(noise) = self
            .noise
            .as_mut()
            .filter(|n| n.command == line && n.times > 0)
        {
            noise.times -= 1;
            bytes.extend_from_slice(&noise.garbage);
        }
        bytes.extend_from_slice(line.as_bytes());
        bytes.push(b'\n');
        self.write(&bytes)?;
        let deadline = Instant::now() + self.options.command_timeout;
        loop {
            let received = self.read_line(deadline)?;
            match parse_reply(&received).map_err(Failure::Malformed)? {
                Reply::Ok(rest) => return command.check_answer(&rest).map_err(Failure::Malformed),
                Reply::Err { code, reason } => return Err(Failure::Refused { code, reason }),
                // A reset during the session: the command may have been lost with it; keep
                // reading until the deadline, the retry sends it again.
                Reply::Ready(_) => self.note_reset(),
            }
        }
    }

    fn note_reset(&mut self) {
        if self.in_session {
            self.resets += 1;
        }
    }

    /// After a lost or damaged answer: a bare LF (always answered with exactly one `ERR 1`),
    /// then everything read until the line has been quiet for a moment is dropped. If the
    /// board reset meanwhile, the timeout this host had set is sent again.
    fn resync(&mut self) -> std::result::Result<(), Failure> {
        let resets_before = self.resets;
        self.write(b"\n")?;
        let quiet = Duration::from_millis(150);
        let mut deadline = Instant::now() + quiet;
        loop {
            match self.read_line(deadline) {
                Ok(line) => {
                    if line.starts_with("READY ") {
                        self.note_reset();
                    }
                    deadline = Instant::now() + quiet;
                }
                Err(Failure::Timeout) => break,
                Err(Failure::Malformed(_)) => deadline = Instant::now() + quiet,
                Err(e) => return Err(e),
            }
        }
        self.rx.clear();
        if self.resets != resets_before {
            if let Some(ms) = self.timeout_ms {
                self.exchange(Command::Timeout(ms))?;
            }
        }
        Ok(())
    }

    fn write(&mut self, bytes: &[u8]) -> std::result::Result<(), Failure> {
        if self.vanished {
            return Err(Failure::Vanished(std::io::Error::new(
                ErrorKind::BrokenPipe,
                "the port went away earlier",
            )));
        }
        self.port.write_all(bytes).map_err(|e| self.classify(e))
    }

    /// The next complete line (LF removed), waiting until `deadline`.
    fn read_line(&mut self, deadline: Instant) -> std::result::Result<String, Failure> {
        let mut buf = [0u8; 256];
        loop {
            if let Some(end) = self.rx.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = self.rx.drain(..=end).take(end).collect();
                return match String::from_utf8(line) {
                    Ok(text) => Ok(text),
                    Err(e) => Err(Failure::Malformed(format!(
                        "an answer that is not text: {}",
                        quote_bytes(e.as_bytes())
                    ))),
                };
            }
            if self.rx.len() > MAX_ANSWER {
                let head = quote_bytes(&self.rx);
                self.rx.clear();
                return Err(Failure::Malformed(format!(
                    "more than {MAX_ANSWER} bytes without a line end ({head}): line noise, a \
                     wrong baud rate, or not a psscan LED controller"
                )));
            }
            if self.vanished {
                return Err(Failure::Vanished(std::io::Error::new(
                    ErrorKind::BrokenPipe,
                    "the port went away earlier",
                )));
            }
            if Instant::now() >= deadline {
                return Err(Failure::Timeout);
            }
            match self.port.read(&mut buf) {
                Ok(0) => {
                    return Err(
                        self.classify(std::io::Error::new(ErrorKind::UnexpectedEof, "end of file"))
                    )
                }
                Ok(n) => self.rx.extend_from_slice(&buf[..n]),
                Err(e) if e.kind() == ErrorKind::TimedOut || e.kind() == ErrorKind::Interrupted => {
                }
                Err(e) => return Err(self.classify(e)),
            }
        }
    }

    fn classify(&mut self, e: std::io::Error) -> Failure {
        if e.kind() == ErrorKind::TimedOut {
            return Failure::Timeout;
        }
        self.vanished = true;
        Failure::Vanished(e)
    }

    fn error(&self, e: Failure, what: &str) -> Error {
        let what = what.to_string();
        let source = match e {
            Failure::Timeout => LinkError::Timeout {
                what,
                timeout_ms: self.options.command_timeout.as_millis(),
                baud: self.options.baud,
            },
            Failure::Vanished(source) => LinkError::Vanished { what, source },
            Failure::Malformed(message) => LinkError::Malformed { what, message },
            Failure::Refused { code, reason } => LinkError::Refused { what, code, reason },
        };
        Error::Link {
            device: self.device(),
            source,
        }
    }
}

fn open_error(path: &str, e: serialport::Error) -> Error {
    let problem = match &e.kind {
        _ if e.description.contains("lock") => PortProblem::InUse,
        serialport::ErrorKind::NoDevice => PortProblem::NoDevice,
        serialport::ErrorKind::Io(ErrorKind::NotFound) => PortProblem::NotFound,
        serialport::ErrorKind::Io(ErrorKind::PermissionDenied) => PortProblem::PermissionDenied,
        _ => PortProblem::Other,
    };
    Error::Link {
        device: format!("LED controller on {path}"),
        source: LinkError::Unopened {
            problem,
            source: e.into(),
        },
    }
}

impl LightController for SerialLights {
    fn name(&self) -> String {
        self.device()
    }

    fn identify(&mut self) -> Result<FirmwareInfo> {
        let info = match self.command(Command::Id)? {
            Answer::Identity(info) => info,
            other => unreachable!("ID answered {other:?}"),
        };
        info.check_compatible()
            .map_err(|m| Error::device(self.device(), m))?;
        self.info = Some(info.clone());
        Ok(info)
    }

    fn on(&mut self, led: usize) -> Result<()> {
        if let Some(info) = &self.info {
            if led >= info.leds {
                return Err(Error::device(
                    self.device(),
                    format!(
                        "LED {led} does not exist: the controller has {} (0..{})",
                        info.leds,
                        info.leds - 1
                    ),
                ));
            }
        }
        self.command(Command::On(led)).map(|_| ())
    }

    fn off(&mut self) -> Result<()> {
        self.command(Command::Off).map(|_| ())
    }

    fn state(&mut self) -> Result<LightState> {
        match self.command(Command::State)? {
            Answer::State(state) => Ok(state),
            other => unreachable!("STATE answered {other:?}"),
        }
    }

    fn set_timeout(&mut self, ms: u32) -> Result<()> {
        if !TIMEOUT_RANGE_MS.contains(&ms) {
            return Err(Error::device(
                self.device(),
                format!(
                    "a host-silence timeout of {ms} ms is outside what the firmware accepts \
                     ({}..{} ms)",
                    TIMEOUT_RANGE_MS.start(),
                    TIMEOUT_RANGE_MS.end()
                ),
            ));
        }
        self.command(Command::Timeout(ms))?;
        self.timeout_ms = Some(ms);
        Ok(())
    }

    fn keepalive(&mut self) -> Result<()> {
        self.command(Command::Ping).map(|_| ())
    }
}

impl Drop for SerialLights {
    /// LEDs off when the controller goes out of scope, whatever the reason; one try, no
    /// retry (the firmware's silence timeout is the backstop).
    fn drop(&mut self) {
        if !self.vanished {
            let _ = self.exchange(Command::Off);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{BufRead, BufReader};
    use std::os::fd::FromRawFd;

    /// A misbehaving device on a real pseudo-terminal: `answer` maps each received line to
    /// the bytes sent back.
    fn fake_device(answer: impl Fn(&str) -> Vec<u8> + Send + 'static) -> String {
        // SAFETY: plain libc pty calls; the master fd is owned by the File below.
        let (master, name) = unsafe {
            let fd = libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY);
            assert!(fd >= 0);
            assert_eq!(libc::grantpt(fd), 0);
            assert_eq!(libc::unlockpt(fd), 0);
            let mut buf = [0 as libc::c_char; 64];
            assert_eq!(libc::ptsname_r(fd, buf.as_mut_ptr(), buf.len()), 0);
            let name = std::ffi::CStr::from_ptr(buf.as_ptr())
                .to_string_lossy()
                .into_owned();
            (std::fs::File::from_raw_fd(fd), name)
        };
        std::thread::spawn(move || {
            let mut writer = master.try_clone().unwrap();
            for line in BufReader::new(master).split(b'\n') {
                let Ok(line) = line else { return };
                let text = String::from_utf8_lossy(&line).into_owned();
                if writer.write_all(&answer(&text)).is_err() {
                    return;
                }
            }
        });
        name
    }

    const ID: &[u8] = b"OK ID psscan-led fw=1.0.0 proto=1 leds=10\n";

    fn open(path: &str) -> Result<SerialLights> {
        SerialLights::open(
            path,
            SerialOptions {
                command_timeout: Duration::from_millis(200),
                ..SerialOptions::default()
            },
        )
    }

    #[test]
    fn malformed_mismatched_and_missing_answers_are_retried_once_then_named() {
        for (reply, needle) in [
            (b"HELLO\n".to_vec(), "malformed answer \"HELLO\""),
            (b"OK ON 4\n".to_vec(), "does not belong"),
            (vec![b'Z'; 200], "without a line end"),
            (b"OK \xff\xfe\n".to_vec(), "not text"),
            (Vec::new(), "no answer"),
        ] {
            let path = fake_device(move |line| match line {
                "ID" => ID.to_vec(),
                "" => b"ERR 1 unknown command\n".to_vec(),
                _ => reply.clone(),
            });
            let mut lights = open(&path).unwrap();
            let err = lights.on(3).unwrap_err().to_string();
            assert!(err.contains(needle), "{needle}: {err}");
            assert!(
                err.contains("after one retry") && err.contains(&path),
                "{err}"
            );
        }
    }

    #[test]
    fn a_retry_recovers_a_lost_answer_and_other_firmware_is_refused() {
        let count = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let seen = count.clone();
        let path = fake_device(move |line| match line {
            "ID" => ID.to_vec(),
            // The first ON is lost; the retry is answered.
            "ON 3" if seen.fetch_add(1, std::sync::atomic::Ordering::SeqCst) == 0 => Vec::new(),
            "ON 3" => b"OK ON 3\n".to_vec(),
            "" => b"ERR 1 unknown command\n".to_vec(),
            _ => b"ERR 1 unknown command\n".to_vec(),
        });
        let mut lights = open(&path).unwrap();
        lights.on(3).unwrap();
        assert_eq!(count.load(std::sync::atomic::Ordering::SeqCst), 2);

        let path = fake_device(|line| match line {
            "ID" => b"OK ID psscan-led fw=9.0.0 proto=9 leds=10\n".to_vec(),
            _ => b"OK OFF\n".to_vec(),
        });
        let err = open(&path).err().unwrap().to_string();
        assert!(err.contains("protocol 9") && err.contains("flash"), "{err}");

        let err = open("/dev/pts/999999").err().unwrap().to_string();
        assert!(
            err.contains("cannot open") && err.contains("/dev/pts/999999"),
            "{err}"
        );
    }
}
