//! The check every frame passes as it is captured, before it joins the set: it must be what
//! the manifest records (a camera RAW file for `raw` sets, a 16-bit PNG or TIFF of the
//! recorded size for `dn16` sets), the same size as the set's earlier RAW frames, and not a
//! byte-for-byte copy of an earlier frame (a camera command that hands back a stale file).
//! Only headers are read; no pixel is decoded.

use super::manifest::{FrameEntry, ImageInfo};

const PNG_MAGIC: &[u8] = b"\x89PNG\r\n\x1a\n";

/// What a frame's first bytes and header say it is.
#[derive(Clone, Debug, PartialEq)]
pub enum Seen {
    /// A PNG or TIFF image of this size (`dn16` frames are).
    Image {
        format: &'static str,
        width: usize,
        height: usize,
    },
    /// A JPEG: a camera set to JPEG, or a preview, never a frame psscan can solve.
    Jpeg,
    /// A camera RAW file; its raw image's declared size where the container says.
    Raw(Option<(usize, usize)>),
    /// Anything else, with rawler's reason.
    Unknown(String),
}

impl Seen {
    fn describe(&self) -> String {
        match self {
            Seen::Image {
                format,
                width,
                height,
            } => format!("a {width}x{height} {format} image"),
            Seen::Jpeg => "a JPEG image".into(),
            Seen::Raw(Some((w, h))) => format!("a camera RAW file of {w}x{h}"),
            Seen::Raw(None) => "a camera RAW file".into(),
            Seen::Unknown(why) => format!("not an image psscan reads ({why})"),
        }
    }
}

/// Identifies a frame from its bytes.
pub fn identify(bytes: &[u8]) -> Seen {
    if bytes.starts_with(&[0xFF, 0xD8, 0xFF]) {
        return Seen::Jpeg;
    }
    let format = if bytes.starts_with(PNG_MAGIC) {
        Some(("PNG", image::ImageFormat::Png))
    } else {
        None
    };
    if let Some((name, fmt)) = format {
        let reader = image::ImageReader::with_format(std::io::Cursor::new(bytes), fmt);
        return match reader.into_dimensions() {
            Ok((w, h)) => Seen::Image {
                format: name,
                width: w as usize,
                height: h as usize,
            },
            Err(e) => Seen::Unknown(format!("a damaged PNG: {e}")),
        };
    }
    match crate::raw::probe_raw(bytes) {
        Ok(dims) => Seen::Raw(dims),
        Err(why) => {
            // A plain TIFF is no camera RAW file; it may be a dn16 frame.
            let tiff = image::ImageReader::with_format(
                std::io::Cursor::new(bytes),
                image::ImageFormat::Tiff,
            );
            match tiff.into_dimensions() {
                Ok((w, h)) => Seen::Image {
                    format: "TIFF",
                    width: w as usize,
                    height: h as usize,
                },
                Err(_) => Seen::Unknown(why),
            }
        }
    }
}

/// Checks the frame about to be stored as `file` (content `bytes`, checksum `sha256`)
/// against the manifest's `image` description, the `earlier` frames of the set and the raw
/// size of the set's first RAW frame (`raw_size`, `None` before one). Returns what was seen;
/// the error says what is wrong with the frame.
pub fn check(
    file: &str,
    bytes: &[u8],
    sha256: &str,
    image: &ImageInfo,
    earlier: &[FrameEntry],
    raw_size: Option<(usize, usize)>,
) -> Result<Seen, String> {
    if let Some(twin) = earlier.iter().find(|f| f.sha256 == sha256) {
        return Err(format!(
            "{file} is byte-for-byte the same photograph as {} (sha256 {}): the camera handed \
             back a stale file instead of a new photograph",
            twin.file,
            &sha256[..sha256.len().min(12)]
        ));
    }
    let seen = identify(bytes);
    let recorded = format!(
        "the manifest records {} frames of {}x{}",
        image.encoding, image.width, image.height
    );
    let fits = match (image.encoding.as_str(), &seen) {
        (
            "dn16",
            Seen::Image {
                width: w,
                height: h,
                ..
            },
        ) => (*w, *h) == (image.width, image.height),
        ("raw", Seen::Raw(dims)) => match (dims, raw_size) {
            (Some(d), Some(first)) if *d != first => {
                return Err(format!(
                    "{file} is {}, the set's earlier RAW frames {}x{}: the camera's image size \
                     or mode changed mid-set",
                    seen.describe(),
                    first.0,
                    first.1
                ))
            }
            _ => true,
        },
        _ => false,
    };
    if fits {
        Ok(seen)
    } else {
        Err(format!(
            "{file} is {}, but {recorded}: the camera does not give the frames this set \
             records (for a command camera: make it write the camera's RAW file)",
            seen.describe()
        ))
    }
}
