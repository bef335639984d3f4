//! The LED controller's line protocol (firmware/PROTOCOL.md, proto=1) as pure functions: the
//! command lines the host sends and the parsing of the answers it gets back. No I/O here, so
//! every rule of the contract is unit-tested without a device.

use serde::Serialize;

/// The protocol version this host speaks (`proto=` in `ID` and `READY`).
pub const PROTOCOL_VERSION: u32 = 1;
/// The firmware name in `ID` and `READY`.
pub const FIRMWARE_NAME: &str = "psscan-led";
/// Longest line the firmware accepts, not counting CR and LF.
pub const MAX_LINE: usize = 32;
/// Longest answer the firmware sends is 42 bytes; anything much longer is line noise.
pub const MAX_ANSWER: usize = 96;
/// Host-silence timeout range the firmware accepts (ms).
pub const TIMEOUT_RANGE_MS: std::ops::RangeInclusive<u32> = 100..=60000;

/// One command line.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Command {
    /// `ID`: asks the firmware who it is (answered `OK ID <identity>`).
    Id,
    /// `ON <n>`: LED `n` on, every other LED off.
    On(usize),
    /// `OFF`: every LED off.
    Off,
    /// `STATE`: asks which LED is on, the silence timeout, and whether it tripped.
    State,
    /// `TIMEOUT <ms>`: sets the host-silence timeout, in milliseconds (within
    /// [`TIMEOUT_RANGE_MS`]).
    Timeout(u32),
    /// `PING`: a keepalive that only restarts the host-silence clock (answered `OK PONG`).
    Ping,
}

impl Command {
    /// The line as sent, without the LF.
    pub fn line(&self) -> String {
        match self {
            Command::Id => "ID".into(),
            Command::On(n) => format!("ON {n}"),
            Command::Off => "OFF".into(),
            Command::State => "STATE".into(),
            Command::Timeout(ms) => format!("TIMEOUT {ms}"),
            Command::Ping => "PING".into(),
        }
    }

    /// Checks that `rest` (the text after `OK `) answers this command, and returns what it
    /// carries.
    pub fn check_answer(&self, rest: &str) -> Result<Answer, String> {
        let mismatch = || {
            Err(format!(
                "answer \"OK {rest}\" does not belong to the command \"{}\"",
                self.line()
            ))
        };
        match self {
            Command::Id => match rest.strip_prefix("ID ") {
                Some(ident) => Ok(Answer::Identity(parse_identity(ident)?)),
                None => mismatch(),
            },
            Command::State => match rest.strip_prefix("STATE ") {
                Some(state) => Ok(Answer::State(parse_state(state)?)),
                None => mismatch(),
            },
            Command::Ping if rest == "PONG" => Ok(Answer::Done),
            Command::Off if rest == "OFF" => Ok(Answer::Done),
            Command::On(n) if rest == format!("ON {n}") => Ok(Answer::Done),
            Command::Timeout(ms) if rest == format!("TIMEOUT {ms}") => Ok(Answer::Done),
            _ => mismatch(),
        }
    }
}

/// What an `OK` answer carried.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Answer {
    /// The command was carried out and carries nothing back (`ON`, `OFF`, `TIMEOUT`, `PING`).
    Done,
    /// The firmware's identity, answering `ID`.
    Identity(FirmwareInfo),
    /// The LEDs' state, answering `STATE`.
    State(LightState),
}

/// One line from the controller, classified.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Reply {
    /// `OK <rest>`.
    Ok(String),
    /// `ERR <code> <reason>`.
    Err {
        /// The error's number (PROTOCOL.md: 1 unknown command, 2 bad argument, 3 line too
        /// long, 4 out of range, 5 bad character).
        code: u32,
        /// The fixed reason text that follows the code (possibly empty).
        reason: String,
    },
    /// The banner after a reset: `READY <identity>`.
    Ready(String),
}

/// Classifies one received line (without its LF; a CR is tolerated and dropped).
pub fn parse_reply(line: &str) -> Result<Reply, String> {
    let line = line.strip_suffix('\r').unwrap_or(line);
    if let Some(rest) = line.strip_prefix("OK ") {
        return Ok(Reply::Ok(rest.to_string()));
    }
    if let Some(rest) = line.strip_prefix("READY ") {
        return Ok(Reply::Ready(rest.to_string()));
    }
    if let Some(rest) = line.strip_prefix("ERR ") {
        let (code, reason) = rest.split_once(' ').unwrap_or((rest, ""));
        return match code.parse::<u32>() {
            Ok(code) => Ok(Reply::Err {
                code,
                reason: reason.to_string(),
            }),
            Err(_) => Err(format!("malformed error answer {}", quote(line))),
        };
    }
    Err(format!(
        "malformed answer {}: expected \"OK ...\" or \"ERR <code> <reason>\"",
        quote(line)
    ))
}

/// The firmware's identity: `psscan-led fw=1.0.0 proto=1 leds=10`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct FirmwareInfo {
    /// The firmware's name; [`FIRMWARE_NAME`] for firmware this host can drive.
    pub name: String,
    /// The firmware's version string (`fw=`).
    pub firmware_version: String,
    /// The protocol version the firmware speaks (`proto=`).
    pub protocol: u32,
    /// LED channels the controller drives (`leds=`).
    pub leds: usize,
}

/// Parses the identity text of `OK ID ...` and `READY ...` (fields by key, so a later
/// firmware may append fields).
pub fn parse_identity(text: &str) -> Result<FirmwareInfo, String> {
    let mut words = text.split(' ');
    let name = words.next().unwrap_or_default().to_string();
    let (mut fw, mut proto, mut leds) = (None, None, None);
    for word in words {
        match word.split_once('=') {
            Some(("fw", v)) => fw = Some(v.to_string()),
            Some(("proto", v)) => proto = v.parse::<u32>().ok(),
            Some(("leds", v)) => leds = v.parse::<usize>().ok(),
            _ => {}
        }
    }
    match (fw, proto, leds) {
        (Some(firmware_version), Some(protocol), Some(leds)) if !name.is_empty() => {
            Ok(FirmwareInfo {
                name,
                firmware_version,
                protocol,
                leds,
            })
        }
        _ => Err(format!(
            "malformed identity {}: expected \"<name> fw=<version> proto=<n> leds=<n>\"",
            quote(text)
        )),
    }
}

impl FirmwareInfo {
    /// Refuses firmware this host cannot drive, saying what to do.
    pub fn check_compatible(&self) -> Result<(), String> {
        if self.name != FIRMWARE_NAME {
            return Err(format!(
                "the device identifies as \"{}\", not {FIRMWARE_NAME}: wrong port, or the board \
                 runs other firmware (flash firmware/ with `make -C firmware flash`)",
                self.name
            ));
        }
        if self.protocol != PROTOCOL_VERSION {
            return Err(format!(
                "{} fw={} speaks protocol {}, this psscan speaks protocol {PROTOCOL_VERSION}: \
                 flash the firmware from this psscan's firmware/ folder (or upgrade psscan)",
                self.name, self.firmware_version, self.protocol
            ));
        }
        if self.leds == 0 {
            return Err("the controller reports no LED channels".into());
        }
        Ok(())
    }
}

/// What `STATE` reports.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct LightState {
    /// The LED that is on, if any.
    pub on: Option<usize>,
    /// Host-silence timeout (ms).
    pub timeout_ms: u32,
    /// The silence timeout switched an LED off since the last `ON`.
    pub tripped: bool,
}

/// Parses the text after `OK STATE `: `<n|OFF> timeout=<ms> tripped=<0|1>`.
pub fn parse_state(text: &str) -> Result<LightState, String> {
    let bad = || {
        format!(
            "malformed state {}: expected \"<n|OFF> timeout=<ms> tripped=<0|1>\"",
            quote(text)
        )
    };
    let mut words = text.split(' ');
    let on = match words.next() {
        Some("OFF") => None,
        Some(n) => Some(n.parse::<usize>().map_err(|_| bad())?),
        None => return Err(bad()),
    };
    let (mut timeout_ms, mut tripped) = (None, None);
    for word in words {
        match word.split_once('=') {
            Some(("timeout", v)) => timeout_ms = v.parse::<u32>().ok(),
            Some(("tripped", "0")) => tripped = Some(false),
            Some(("tripped", "1")) => tripped = Some(true),
            _ => {}
        }
    }
    match (timeout_ms, tripped) {
        (Some(timeout_ms), Some(tripped)) => Ok(LightState {
            on,
            timeout_ms,
            tripped,
        }),
        _ => Err(bad()),
    }
}

/// A received line for an error message: quoted, with control and non-ASCII bytes escaped,
/// and cut short when long.
pub fn quote(text: &str) -> String {
    let mut out: String = text
        .chars()
        .take(60)
        .flat_map(char::escape_default)
        .collect();
    if text.chars().count() > 60 {
        out.push_str("...");
    }
    format!("\"{out}\"")
}

/// Escapes raw bytes the same way (for lines that are not even UTF-8).
pub fn quote_bytes(bytes: &[u8]) -> String {
    let text: String = bytes
        .iter()
        .take(60)
        .flat_map(|&b| std::ascii::escape_default(b))
        .map(char::from)
        .collect();
    let more = if bytes.len() > 60 { "..." } else { "" };
    format!("\"{text}{more}\"")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn command_lines_fit_the_firmware_limit() {
        for cmd in [
            Command::Id,
            Command::On(9),
            Command::Off,
            Command::State,
            Command::Timeout(60000),
            Command::Ping,
        ] {
            assert!(cmd.line().len() <= MAX_LINE);
            assert!(cmd.line().bytes().all(|b| (0x20..0x7f).contains(&b)));
        }
        assert_eq!(Command::On(3).line(), "ON 3");
        assert_eq!(Command::Timeout(500).line(), "TIMEOUT 500");
    }

    #[test]
    fn answers_are_matched_to_their_command() {
        assert_eq!(Command::On(3).check_answer("ON 3"), Ok(Answer::Done));
        assert!(Command::On(3)
            .check_answer("ON 4")
            .unwrap_err()
            .contains("does not belong"));
        assert_eq!(Command::Ping.check_answer("PONG"), Ok(Answer::Done));
        assert!(Command::Off.check_answer("PONG").is_err());
        assert_eq!(
            Command::State.check_answer("STATE 3 timeout=3000 tripped=0"),
            Ok(Answer::State(LightState {
                on: Some(3),
                timeout_ms: 3000,
                tripped: false
            }))
        );
        assert_eq!(
            Command::State.check_answer("STATE OFF timeout=500 tripped=1"),
            Ok(Answer::State(LightState {
                on: None,
                timeout_ms: 500,
                tripped: true
            }))
        );
        assert!(Command::State.check_answer("STATE x timeout=1").is_err());
        match Command::Id.check_answer("ID psscan-led fw=1.0.0 proto=1 leds=10") {
            Ok(Answer::Identity(info)) => {
                assert_eq!(info.leds, 10);
                assert_eq!(info.firmware_version, "1.0.0");
                assert!(info.check_compatible().is_ok());
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn replies_are_classified_and_garbage_is_named() {
        assert_eq!(parse_reply("OK PONG"), Ok(Reply::Ok("PONG".into())));
        assert_eq!(parse_reply("OK PONG\r"), Ok(Reply::Ok("PONG".into())));
        assert_eq!(
            parse_reply("ERR 3 line too long"),
            Ok(Reply::Err {
                code: 3,
                reason: "line too long".into()
            })
        );
        assert!(matches!(
            parse_reply("READY psscan-led fw=1.0.0 proto=1 leds=10"),
            Ok(Reply::Ready(_))
        ));
        let err = parse_reply("HELLO\u{1}").unwrap_err();
        assert!(err.contains("malformed") && err.contains("\\u{1}"), "{err}");
        assert!(parse_reply("ERR x y").is_err());
        assert!(parse_reply("").is_err());
    }

    #[test]
    fn other_firmware_and_protocols_are_refused_with_advice() {
        let other = parse_identity("blinky fw=2 proto=1 leds=10").unwrap();
        assert!(other
            .check_compatible()
            .unwrap_err()
            .contains("not psscan-led"));
        let newer = parse_identity("psscan-led fw=2.0.0 proto=2 leds=10 extra=1").unwrap();
        let err = newer.check_compatible().unwrap_err();
        assert!(err.contains("protocol 2") && err.contains("flash"), "{err}");
        assert!(parse_identity("psscan-led fw=1.0.0").is_err());
    }
}
