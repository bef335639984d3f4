//! Decoding captured images into linear `f32` planes: black-level subtraction, normalisation
//! by the white level, and a per-pixel saturation mask. This module knows nothing about
//! lights. Today it reads the 16-bit RGB PNG/TIFF frames psscan's synthetic sets use; camera
//! RAW files (rawler) are the RAW issue's work and are refused with a clear error until then.

mod linear;

pub use linear::{decode_dn_image, encode_png16, read_dn_image, DnImage, Levels};
