//! Decoding captured images into linear `f32` planes: black-level subtraction, normalisation
//! by the white level, a per-pixel saturation mask, 2x2 CFA binning or a shading-preserving
//! demosaic of the whole stack of frames, and dark-frame subtraction. This module knows
//! nothing about lights beyond their colour.
//!
//! Two kinds of frames: camera RAW files (rawler: NEF, CR2, CR3, ARW, RAF, ORF, DNG, ...)
//! decoded to their CFA samples ([`Mosaic`]), and the 16-bit RGB PNG/TIFF frames of raw
//! digital numbers of psscan's `dn16` sets ([`DnImage`]). psscan writes DNG too ([`encode_dng`]),
//! so synthetic capture sets take the path real RAW files take.

mod chroma;
mod colour;
mod decode;
mod develop;
mod dng;
mod five_rows;
mod guard;
mod hue;
mod linear;
mod mosaic;
mod pass;
mod shading;
mod stack;

pub use colour::camera_to_srgb;
pub use decode::{
    decode_raw, probe_raw, quiet_decoder_panics, read_raw, DecodedRaw, RawMeta, MAX_SAMPLES,
};
pub use develop::{
    below_black_floor, check_consistent, check_plausible, decode_codec, decode_frame,
    develop_frames, develop_frames_timed, finish_decode, Coded, DecodeInfo, DecodedFrame,
    DevelopOptions, Encoding, FrameData, RawPrep, BINNING_PASS_STAGE, DARK_STAGE, DECODE_STAGES,
    DN16_DECODE_STAGE,
};
pub use dng::{encode_dng, DngStorage};
pub use hue::Backing;
pub use linear::{
    decode_dn_frame, decode_dn_image, encode_png16, png_rows_from, read_dn_image, DnImage, Levels,
    SizedFrame,
};
pub use mosaic::{
    bilinear, subtract_dark, DarkFrame, LinearMosaic, Mosaic, Resolution, BLUE, GREEN, RED,
    SATURATION_MARGIN,
};
pub use pass::{LinearPass, SampleCounts};
pub use shading::ShadingField;
pub use stack::{develop_stack, Developed};
