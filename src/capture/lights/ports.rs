//! Finding the LED controller's serial port. The serialport crate is built without libudev
//! (so the default build needs no system packages); on Linux it then reads sysfs
//! (`/sys/class/tty/*/device`), which still gives USB vendor and product IDs, so Arduino
//! boards and the USB-serial bridges of their clones are recognised.

use serde::Serialize;

use crate::error::{Error, PortSearch, Result};

/// One serial port and what is known about it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct PortInfo {
    /// The port's device path, e.g. `/dev/ttyACM0` or `COM3`.
    pub path: String,
    /// `usb`, `pci`, `bluetooth` or `other`.
    pub kind: String,
    /// USB vendor ID; `None` for a port that is not USB.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vid: Option<u16>,
    /// USB product ID; `None` for a port that is not USB.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pid: Option<u16>,
    /// The USB manufacturer string, when the device reports one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub manufacturer: Option<String>,
    /// The USB product string, when the device reports one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub product: Option<String>,
    /// The USB serial number, when the device reports one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub serial_number: Option<String>,
    /// The board or bridge these IDs belong to, when psscan knows them.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub board: Option<String>,
    /// An Arduino (1) or a bridge used on Arduino clones (2); `None` for anything else.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub arduino_rank: Option<u8>,
}

/// What psscan knows about USB IDs: (vendor, product or None for any, name, rank).
const KNOWN: &[(u16, Option<u16>, &str, u8)] = &[
    (0x2341, Some(0x0043), "Arduino Uno R3", 1),
    (0x2341, Some(0x0001), "Arduino Uno", 1),
    (0x2341, Some(0x0243), "Arduino Uno R3", 1),
    (0x2341, Some(0x0010), "Arduino Mega 2560", 1),
    (0x2341, Some(0x0042), "Arduino Mega 2560 R3", 1),
    (0x2341, None, "Arduino board", 1),
    (0x2a03, Some(0x0043), "Arduino Uno R3 (arduino.org)", 1),
    (0x2a03, None, "Arduino board (arduino.org)", 1),
    (
        0x1a86,
        Some(0x7523),
        "CH340 USB-serial (Nano/Uno clones)",
        2,
    ),
    (
        0x0403,
        Some(0x6001),
        "FTDI FT232R USB-serial (Nano, Duemilanove)",
        2,
    ),
    (0x10c4, Some(0xea60), "CP210x USB-serial (clones)", 2),
];

/// The board name and rank for a USB vendor/product pair.
pub fn classify_usb(vid: u16, pid: u16) -> Option<(&'static str, u8)> {
    KNOWN
        .iter()
        .find(|(v, p, _, _)| *v == vid && p.map_or(true, |p| p == pid))
        .map(|(_, _, name, rank)| (*name, *rank))
}

/// Serial ports on this machine.
pub fn list_ports() -> Result<Vec<PortInfo>> {
    // serialport's sysfs scan panics when /sys/class/tty is missing (a container without
    // sysfs); say so instead.
    #[cfg(target_os = "linux")]
    if !std::path::Path::new("/sys/class/tty").is_dir() {
        return Err(Error::NoPort(PortSearch::NoSysfs));
    }
    let ports = serialport::available_ports()
        .map_err(|e| Error::Unsupported(format!("cannot list serial ports: {e}")))?;
    let mut out: Vec<PortInfo> = ports.into_iter().map(port_info).collect();
    out.sort_by(|a, b| a.path.cmp(&b.path));
    Ok(out)
}

fn port_info(port: serialport::SerialPortInfo) -> PortInfo {
    let mut info = PortInfo {
        path: port.port_name,
        kind: "other".into(),
        vid: None,
        pid: None,
        manufacturer: None,
        product: None,
        serial_number: None,
        board: None,
        arduino_rank: None,
    };
    match port.port_type {
        serialport::SerialPortType::UsbPort(usb) => {
            info.kind = "usb".into();
            info.vid = Some(usb.vid);
            info.pid = Some(usb.pid);
            info.manufacturer = usb.manufacturer;
            info.product = usb.product;
            info.serial_number = usb.serial_number;
            if let Some((name, rank)) = classify_usb(usb.vid, usb.pid) {
                info.board = Some(name.into());
                info.arduino_rank = Some(rank);
            }
        }
        serialport::SerialPortType::PciPort => info.kind = "pci".into(),
        serialport::SerialPortType::BluetoothPort => info.kind = "bluetooth".into(),
        serialport::SerialPortType::Unknown => {}
    }
    info
}

/// `auto` or a path: the port to open.
pub fn resolve_port(requested: &str) -> Result<String> {
    if requested != "auto" {
        return Ok(requested.to_string());
    }
    choose_port(&list_ports()?)
}

/// The one Arduino-like port among `ports` (genuine Arduinos before clone bridges).
pub fn choose_port(ports: &[PortInfo]) -> Result<String> {
    for rank in [1u8, 2] {
        let found: Vec<&PortInfo> = ports
            .iter()
            .filter(|p| p.arduino_rank == Some(rank))
            .collect();
        match found.as_slice() {
            [] => continue,
            [one] => return Ok(one.path.clone()),
            many => {
                return Err(Error::NoPort(PortSearch::Several {
                    candidates: many
                        .iter()
                        .map(|p| format!("{} {}", p.path, p.board.as_deref().unwrap_or("")))
                        .collect::<Vec<_>>()
                        .join(", "),
                }))
            }
        }
    }
    let seen = if ports.is_empty() {
        "no serial ports at all".to_string()
    } else {
        format!(
            "ports seen: {}",
            ports
                .iter()
                .map(|p| p.path.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        )
    };
    Err(Error::NoPort(PortSearch::NoArduino { seen }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn port(path: &str, vid: u16, pid: u16) -> PortInfo {
        let (board, rank) = match classify_usb(vid, pid) {
            Some((b, r)) => (Some(b.to_string()), Some(r)),
            None => (None, None),
        };
        PortInfo {
            path: path.into(),
            kind: "usb".into(),
            vid: Some(vid),
            pid: Some(pid),
            manufacturer: None,
            product: None,
            serial_number: None,
            board,
            arduino_rank: rank,
        }
    }

    #[test]
    fn arduino_ids_are_recognised() {
        assert_eq!(classify_usb(0x2341, 0x0043).unwrap().0, "Arduino Uno R3");
        assert_eq!(classify_usb(0x2341, 0x1234).unwrap().0, "Arduino board");
        assert_eq!(classify_usb(0x1a86, 0x7523).unwrap().1, 2);
        assert!(classify_usb(0x046d, 0xc52b).is_none());
    }

    #[test]
    fn auto_picks_the_one_arduino_and_explains_otherwise() {
        let modem = port("/dev/ttyACM1", 0x1bc7, 0x1201);
        let uno = port("/dev/ttyACM0", 0x2341, 0x0043);
        let clone = port("/dev/ttyUSB0", 0x1a86, 0x7523);
        assert_eq!(
            choose_port(&[modem.clone(), uno.clone(), clone.clone()]).unwrap(),
            "/dev/ttyACM0"
        );
        assert_eq!(
            choose_port(&[modem.clone(), clone.clone()]).unwrap(),
            "/dev/ttyUSB0"
        );
        let err = choose_port(std::slice::from_ref(&modem))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("no Arduino") && err.contains("/dev/ttyACM1"),
            "{err}"
        );
        let mut uno2 = uno.clone();
        uno2.path = "/dev/ttyACM2".into();
        let err = choose_port(&[uno, uno2]).unwrap_err();
        assert!(
            matches!(&err, Error::NoPort(PortSearch::Several { candidates })
                if candidates.contains("/dev/ttyACM2")),
            "{err}"
        );
        assert!(choose_port(&[])
            .unwrap_err()
            .to_string()
            .contains("no serial ports"));
    }

    #[test]
    fn listing_works_without_libudev() {
        // Whatever this machine has (often nothing): the sysfs scan must not fail.
        let ports = list_ports().unwrap();
        for p in &ports {
            assert!(p.path.starts_with("/dev/"), "{p:?}");
        }
    }
}
