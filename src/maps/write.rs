//! Moved to [`crate::io`] (issue 15): image file I/O is its own layer.

// moved: issue 15, the lead removes this at merge
pub use crate::io::{encode_exr, encode_png16, read_exr, write_exr, write_png, write_png16};
