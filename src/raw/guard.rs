//! A structural check of a RAW file's container before rawler parses it.
//!
//! rawler turns decoder panics into errors, but two failures cannot be caught: an allocation
//! sized from a corrupt header (rawler allocates a TIFF entry's `count` values before reading
//! them; 4 G entries abort the process) and unbounded recursion through IFDs that point at
//! each other (a stack overflow). Both were found by psscan's fuzz test. This walk visits the
//! same structures rawler does (TIFF IFD chains, SubIFDs, the EXIF, GPS and interoperability
//! IFDs, Nikon/Canon/Olympus/Sony/Panasonic maker notes, and the ISO-BMFF boxes of CR3 with the
//! TIFF structures inside them) and refuses any entry, IFD or box that claims more bytes than
//! the file holds, any IFD reached twice, and any image size beyond `MAX_SAMPLES`.

use std::collections::HashSet;

/// The largest image psscan will decode (samples); a header claiming more is corrupt.
pub const MAX_SAMPLES: usize = 400_000_000;

/// TIFF tags whose values point at further IFDs.
const SUB_IFD_TAGS: [u16; 4] = [330, 34665, 34853, 40965];
const MAKER_NOTE: u16 = 37500;
const IMAGE_WIDTH: u16 = 256;
const IMAGE_LENGTH: u16 = 257;
/// Bounds on how much structure a sane file has.
const MAX_IFDS: usize = 512;
const MAX_DEPTH: usize = 8;

/// Checks the container structure of a RAW file; the error says what is wrong.
pub fn check_structure(data: &[u8]) -> Result<(), String> {
    if data.len() >= 12 && &data[4..8] == b"ftyp" {
        check_bmff(data, 0, data.len(), 0)?;
    } else if let Some(tiff) = Tiff::at(data, 0) {
        tiff.walk_from_header(&mut Visited::default())?;
    }
    check_embedded_tiffs(data)
}

/// TIFF structures embedded anywhere (CR3 timed metadata, maker notes, EXIF blocks of
/// previews, RAF's TIFF): rawler parses them with the same eager allocation. Each TIFF header
/// in the file whose first IFD looks like one (a sane entry count, entries of known types) is
/// walked; random bytes that happen to read "II*\0" almost never pass that test.
fn check_embedded_tiffs(data: &[u8]) -> Result<(), String> {
    for at in tiff_headers(data) {
        let Some(tiff) = Tiff::at(data, at) else {
            continue;
        };
        if tiff.looks_like_an_ifd_at_header() {
            // rawler reads embedded TIFFs' first IFD (and what it points at), not their chains.
            let first = tiff.u32_at(at + 4).unwrap_or(0) as usize;
            tiff.walk_ifd(first, 0, &mut Visited::default())
                .map_err(|e| format!("TIFF structure at byte {at}: {e}"))?;
        }
    }
    Ok(())
}

/// Every position after the first byte where a TIFF header ("II*\0" or "MM\0*") starts and
/// 8 bytes fit, in order. A SIMD substring search: a byte-by-byte scan of a frame's tens of
/// megabytes cost more than the rest of the structure check.
fn tiff_headers(data: &[u8]) -> Vec<usize> {
    let end = data.len().saturating_sub(8);
    let mut at: Vec<usize> = [&b"II*\0"[..], &b"MM\0*"[..]]
        .iter()
        .flat_map(|needle| memchr::memmem::find_iter(data, needle))
        .filter(|&at| at >= 1 && at < end)
        .collect();
    at.sort_unstable();
    at
}

#[derive(Default)]
struct Visited {
    ifds: HashSet<usize>,
}

#[derive(Clone, Copy)]
struct Tiff<'a> {
    data: &'a [u8],
    /// Offsets in the file are relative to this position.
    base: usize,
    little: bool,
}

impl<'a> Tiff<'a> {
    /// A TIFF header (II or MM, then any 16-bit magic: 42, or ORF's and RW2's variants) at
    /// `base`.
    fn at(data: &'a [u8], base: usize) -> Option<Tiff<'a>> {
        let little = match data.get(base..base + 2)? {
            b"II" => true,
            b"MM" => false,
            _ => return None,
        };
        data.get(base + 4..base + 8)?;
        Some(Tiff { data, base, little })
    }

    fn u16_at(&self, pos: usize) -> Option<u16> {
        let b = self.data.get(pos..pos + 2)?;
        Some(if self.little {
            u16::from_le_bytes([b[0], b[1]])
        } else {
            u16::from_be_bytes([b[0], b[1]])
        })
    }

    fn u32_at(&self, pos: usize) -> Option<u32> {
        let b = self.data.get(pos..pos + 4)?;
        let b = [b[0], b[1], b[2], b[3]];
        Some(if self.little {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    }

    /// Whether the header's first IFD is plausible: inside the file, 1 to 1000 entries, at
    /// least three quarters of them of a known TIFF type.
    fn looks_like_an_ifd_at_header(&self) -> bool {
        let Some(first) = self.u32_at(self.base + 4) else {
            return false;
        };
        let pos = self.base.saturating_add(first as usize);
        let Some(count) = self.u16_at(pos).map(usize::from) else {
            return false;
        };
        if count == 0 || count > 1000 || pos + 2 + 12 * count > self.data.len() {
            return false;
        }
        let known = (0..count)
            .filter(|e| {
                self.u16_at(pos + 2 + 12 * e + 2)
                    .is_some_and(|t| (1..=13).contains(&t))
            })
            .count();
        4 * known >= 3 * count
    }

    fn walk_from_header(&self, visited: &mut Visited) -> Result<(), String> {
        let first = self
            .u32_at(self.base + 4)
            .ok_or("TIFF header is cut short")?;
        self.walk_chain(first as usize, 0, visited)
    }

    /// An IFD and the IFDs chained after it.
    fn walk_chain(
        &self,
        mut offset: usize,
        depth: usize,
        visited: &mut Visited,
    ) -> Result<(), String> {
        for _ in 0..64 {
            if offset == 0 {
                return Ok(());
            }
            offset = self.walk_ifd(offset, depth, visited)?;
        }
        Err("more than 64 chained IFDs".into())
    }

    /// One IFD; returns the offset of the next one in its chain (0 for none).
    fn walk_ifd(
        &self,
        offset: usize,
        depth: usize,
        visited: &mut Visited,
    ) -> Result<usize, String> {
        let len = self.data.len();
        let pos = self
            .base
            .checked_add(offset)
            .filter(|&p| p + 2 <= len)
            .ok_or_else(|| format!("an IFD offset ({offset}) points past the end of the file"))?;
        if !visited.ifds.insert(pos) {
            return Err(format!("the IFD at byte {pos} is reached twice (a loop)"));
        }
        if visited.ifds.len() > MAX_IFDS || depth > MAX_DEPTH {
            return Err("implausibly many or deeply nested IFDs".into());
        }
        let count = self.u16_at(pos).ok_or("IFD cut short")? as usize;
        let end = pos + 2 + 12 * count;
        if end + 4 > len {
            return Err(format!(
                "the IFD at byte {pos} claims {count} entries, more than the file holds"
            ));
        }
        let mut dims = [None::<usize>; 2];
        let mut layout = Layout::default();
        for e in 0..count {
            let entry = pos + 2 + 12 * e;
            let tag = self.u16_at(entry).ok_or("IFD entry cut short")?;
            let typ = self.u16_at(entry + 2).ok_or("IFD entry cut short")?;
            let n = self.u32_at(entry + 4).ok_or("IFD entry cut short")? as usize;
            let size = n.saturating_mul(type_size(typ));
            if size > len {
                return Err(format!(
                    "tag {tag} at byte {entry} claims {n} values ({size} bytes) in a {len}-byte file"
                ));
            }
            let value_at = if size <= 4 {
                entry + 8
            } else {
                let off = self.u32_at(entry + 8).ok_or("IFD entry cut short")? as usize;
                self.base.saturating_add(off)
            };
            if (tag == IMAGE_WIDTH || tag == IMAGE_LENGTH) && n == 1 {
                let v = match typ {
                    3 => self.u16_at(entry + 8).map(usize::from),
                    4 => self.u32_at(entry + 8).map(|v| v as usize),
                    _ => None,
                };
                dims[(tag == IMAGE_LENGTH) as usize] = v;
            }
            layout.note(self, tag, typ, n, value_at);
            if SUB_IFD_TAGS.contains(&tag) && (typ == 4 || typ == 13) {
                for k in 0..n.min(64) {
                    let Some(sub) = self.u32_at(value_at + 4 * k) else {
                        break;
                    };
                    if sub != 0 {
                        self.walk_chain(sub as usize, depth + 1, visited)?;
                    }
                }
            }
            if tag == MAKER_NOTE && size > 12 && value_at + size <= len {
                self.walk_maker_note(value_at, size, depth + 1, visited)?;
            }
        }
        if let [Some(w), Some(h)] = dims {
            if w.saturating_mul(h) > MAX_SAMPLES {
                return Err(format!(
                    "the IFD at byte {pos} announces a {w}x{h} image, larger than any camera's"
                ));
            }
            self.check_ljpeg_segments(&layout, (w, h))
                .map_err(|m| format!("the image of the IFD at byte {pos}: {m}"))?;
        }
        Ok(self.u32_at(end).unwrap_or(0) as usize)
    }

    /// Values of a SHORT or LONG entry (at most `MAX_SEGMENTS`).
    fn values(&self, typ: u16, n: usize, at: usize) -> Vec<usize> {
        (0..n.min(MAX_SEGMENTS))
            .map_while(|k| match typ {
                3 => self.u16_at(at + 2 * k).map(usize::from),
                4 => self.u32_at(at + 4 * k).map(|v| v as usize),
                _ => None,
            })
            .collect()
    }

    /// Lossless-JPEG images (compression 7, as DNG stores them): each tile's or strip's
    /// stream must lie inside the file and its SOF3 header must describe exactly as many
    /// samples as the tile or strip holds. The decoder sizes its work from the SOF, so a
    /// damaged one would otherwise cost time and memory the container never declared.
    fn check_ljpeg_segments(&self, l: &Layout, (w, h): (usize, usize)) -> Result<(), String> {
        if l.compression != Some(7) {
            return Ok(());
        }
        let spp = l.samples_per_pixel.unwrap_or(1).max(1);
        let (offsets, counts, sizes): (&[usize], &[usize], Vec<(usize, usize)>) =
            match (l.tile_w, l.tile_h) {
                (Some(tw), Some(th)) if tw > 0 && th > 0 => {
                    let n = w.div_ceil(tw) * h.div_ceil(th);
                    (&l.tile_offsets, &l.tile_counts, vec![(tw, th); n])
                }
                _ => {
                    let rows = l.rows_per_strip.unwrap_or(h).clamp(1, h.max(1));
                    let sizes = (0..h.div_ceil(rows))
                        .map(|k| (w, rows.min(h - k * rows)))
                        .collect();
                    (&l.strip_offsets, &l.strip_counts, sizes)
                }
            };
        if offsets.len() != sizes.len() || counts.len() != sizes.len() {
            return Err(format!(
                "{} compressed segments listed ({} byte counts) where a {w}x{h} image holds {}",
                offsets.len(),
                counts.len(),
                sizes.len()
            ));
        }
        for (k, ((&at, &count), (sw, sh))) in offsets.iter().zip(counts).zip(sizes).enumerate() {
            let at = self.base.saturating_add(at);
            let Some(stream) = self.data.get(at..at.saturating_add(count)) else {
                return Err(format!(
                    "compressed segment {k} lies past the end of the file"
                ));
            };
            let (lines, width, components) = ljpeg_frame(stream)
                .map_err(|m| format!("compressed segment {k} at byte {at}: {m}"))?;
            let samples = lines * width * components;
            if samples != sw * sh * spp {
                return Err(format!(
                    "compressed segment {k} at byte {at} declares {lines} lines of {width} x \
                     {components} samples, the container a {sw}x{sh} segment of {spp} sample(s) \
                     per pixel: the compressed stream is damaged"
                ));
            }
        }
        Ok(())
    }

    /// The maker notes rawler parses as IFDs.
    fn walk_maker_note(
        &self,
        at: usize,
        size: usize,
        depth: usize,
        visited: &mut Visited,
    ) -> Result<(), String> {
        let note = &self.data[at..at + size];
        if note.starts_with(b"Nikon\0") {
            // Its own TIFF header ten bytes in, offsets relative to it.
            if let Some(inner) = Tiff::at(self.data, at + 10) {
                return inner.walk_from_header(visited);
            }
            return Ok(());
        }
        let prefixed = [
            (&b"OLYMPUS\0"[..], 12usize, true),
            (&b"OLYMP\0"[..], 8, false),
            (&b"SONY DSC \0\0\0"[..], 12, false),
            (&b"Panasonic\0\0\0"[..], 12, false),
        ];
        for (prefix, skip, relative) in prefixed {
            if note.starts_with(prefix) {
                let tiff = Tiff {
                    base: if relative { at } else { self.base },
                    ..*self
                };
                let offset = if relative {
                    skip
                } else {
                    at + skip - self.base
                };
                return tiff.walk_ifd(offset, depth, visited).map(|_| ());
            }
        }
        // Canon and others: a bare IFD at the note, offsets like the file's. Only walk it
        // when it looks like one (a plausible entry count).
        let plausible = self
            .u16_at(at)
            .is_some_and(|n| n > 0 && 2 + 12 * n as usize <= size);
        if plausible {
            self.walk_ifd(at - self.base, depth, visited)?;
        }
        Ok(())
    }
}

/// More tiles or strips than this in one image is not a camera's file.
const MAX_SEGMENTS: usize = 1 << 16;

/// How an IFD's image is stored, as far as the lossless-JPEG check needs.
#[derive(Default)]
struct Layout {
    compression: Option<usize>,
    samples_per_pixel: Option<usize>,
    tile_w: Option<usize>,
    tile_h: Option<usize>,
    rows_per_strip: Option<usize>,
    tile_offsets: Vec<usize>,
    tile_counts: Vec<usize>,
    strip_offsets: Vec<usize>,
    strip_counts: Vec<usize>,
}

impl Layout {
    fn note(&mut self, tiff: &Tiff, tag: u16, typ: u16, n: usize, at: usize) {
        let first = || tiff.values(typ, 1, at).first().copied();
        match tag {
            259 => self.compression = first(),
            277 => self.samples_per_pixel = first(),
            278 => self.rows_per_strip = first(),
            322 => self.tile_w = first(),
            323 => self.tile_h = first(),
            273 => self.strip_offsets = tiff.values(typ, n, at),
            279 => self.strip_counts = tiff.values(typ, n, at),
            324 => self.tile_offsets = tiff.values(typ, n, at),
            325 => self.tile_counts = tiff.values(typ, n, at),
            _ => {}
        }
    }
}

/// Lines, samples per line and components of a lossless-JPEG stream's SOF3 header: the
/// markers from SOI up to the frame header, each inside the stream.
fn ljpeg_frame(stream: &[u8]) -> Result<(usize, usize, usize), String> {
    if !stream.starts_with(&[0xFF, 0xD8]) {
        return Err("does not start with a JPEG SOI marker".into());
    }
    let mut pos = 2;
    loop {
        let marker = stream.get(pos..pos + 4).ok_or("no SOF3 frame header")?;
        if marker[0] != 0xFF {
            return Err(format!("byte {pos} is not a JPEG marker"));
        }
        let len = u16::from_be_bytes([marker[2], marker[3]]) as usize;
        match marker[1] {
            0xC3 => {
                let f = stream
                    .get(pos + 4..pos + 10)
                    .ok_or("SOF3 header cut short")?;
                let lines = u16::from_be_bytes([f[1], f[2]]) as usize;
                let width = u16::from_be_bytes([f[3], f[4]]) as usize;
                return Ok((lines, width, f[5] as usize));
            }
            0xC4 | 0xDD | 0xFE | 0xE0..=0xEF if len >= 2 => pos += 2 + len,
            other => {
                return Err(format!(
                    "marker 0xFF{other:02X} before the SOF3 frame header"
                ))
            }
        }
    }
}

fn type_size(typ: u16) -> usize {
    match typ {
        3 | 8 => 2,
        4 | 9 | 11 | 13 => 4,
        5 | 10 | 12 => 8,
        _ => 1,
    }
}

/// The UUID of the box in which CR3 files keep their TIFF metadata (CMT1..CMT4).
const CANON_UUID: [u8; 16] = [
    0x85, 0xc0, 0xb6, 0x87, 0x82, 0x0f, 0x11, 0xe0, 0x81, 0x11, 0xf4, 0xce, 0x46, 0x2b, 0x6a, 0x48,
];

/// ISO-BMFF boxes (CR3), as rawler reads them: every box holds at least its own header and
/// fits its parent (rawler loops forever on a box of size 0, since it steps to
/// `offset + size`), containers are walked after their fixed fields, and Canon's CMT boxes hold
/// TIFF structures.
fn check_bmff(data: &[u8], start: usize, end: usize, depth: usize) -> Result<(), String> {
    if depth > 8 {
        return Err("implausibly deep box nesting".into());
    }
    let mut pos = start;
    while pos + 8 <= end {
        let size32 = u32::from_be_bytes([data[pos], data[pos + 1], data[pos + 2], data[pos + 3]]);
        let kind: [u8; 4] = data[pos + 4..pos + 8].try_into().expect("four bytes");
        let (mut header, size) = if size32 == 1 {
            let b = data.get(pos + 8..pos + 16).ok_or("box header cut short")?;
            let big = u64::from_be_bytes(b.try_into().expect("eight bytes"));
            (16, usize::try_from(big).unwrap_or(usize::MAX))
        } else {
            (8, size32 as usize)
        };
        let uuid = if &kind == b"uuid" {
            let id = data
                .get(pos + header..pos + header + 16)
                .ok_or("uuid box cut short")?;
            header += 16;
            Some(id)
        } else {
            None
        };
        if size < header || pos.saturating_add(size) > end {
            return Err(format!(
                "box \"{}\" at byte {pos} claims {size} bytes, which is not between its header \
                 ({header}) and what its container holds",
                kind.escape_ascii()
            ));
        }
        let body = pos + header;
        // Fixed fields before a container's child boxes.
        let children = match &kind {
            b"moov" | b"trak" | b"mdia" | b"minf" | b"stbl" | b"dinf" => Some(0),
            b"stsd" => Some(8),
            b"CRAW" => Some(82),
            b"CCTP" => Some(12),
            b"CDI1" => Some(4),
            b"uuid" if uuid == Some(&CANON_UUID[..]) => Some(0),
            _ => None,
        };
        if let Some(skip) = children {
            if body + skip <= pos + size {
                check_bmff(data, body + skip, pos + size, depth + 1)?;
            }
        }
        // Tables rawler sizes from a count before reading them: the entries must fit the box.
        let table = match &kind {
            b"stts" => Some((4, 8)),
            b"stco" => Some((4, 4)),
            b"co64" => Some((4, 8)),
            b"stsc" => Some((4, 12)),
            b"stsz" => Some((8, 4)),
            b"CTMD" => Some((8, 6)),
            _ => None,
        };
        if let Some((at, entry)) = table {
            let count = data
                .get(body + at..body + at + 4)
                .map(|b| u32::from_be_bytes(b.try_into().expect("four bytes")) as usize)
                .ok_or("box cut short")?;
            if count.saturating_mul(entry) > size {
                return Err(format!(
                    "box \"{}\" at byte {pos} claims {count} entries, more than its {size} bytes hold",
                    kind.escape_ascii()
                ));
            }
        }
        if matches!(&kind, b"CMT1" | b"CMT2" | b"CMT3" | b"CMT4") {
            if let Some(tiff) = Tiff::at(&data[body..pos + size], 0) {
                tiff.walk_from_header(&mut Visited::default())?;
            }
        }
        pos += size;
    }
    // rawler reads a box header wherever a container still has bytes left, even fewer than a
    // header's; what it finds there steers it.
    if depth > 0 && pos != end {
        return Err(format!(
            "{} stray bytes at the end of a box container at byte {pos}",
            end - pos
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiff_headers_are_found_where_a_byte_by_byte_scan_finds_them() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let mut data: Vec<u8> = (0..100_000).map(|_| rng.gen_range(0..4u8) * 0x15).collect();
        // Headers at the start (not embedded), back to back, mixed, and too near the end.
        for (at, head) in [
            (0, b"II*\0"),
            (500, b"MM\0*"),
            (504, b"II*\0"),
            (70_000, b"II*\0"),
        ] {
            data[at..at + 4].copy_from_slice(head);
        }
        let n = data.len();
        data[n - 8..n - 4].copy_from_slice(b"MM\0*");
        data[n - 9..n - 5].copy_from_slice(b"II*\0");
        let by_byte: Vec<usize> = (1..n - 8)
            .filter(|&at| &data[at..at + 4] == b"II*\0" || &data[at..at + 4] == b"MM\0*")
            .collect();
        assert_eq!(tiff_headers(&data), by_byte);
        assert_eq!(by_byte, [500, 504, 70_000, n - 9]);
    }

    fn tiff_with_entry(tag: u16, typ: u16, count: u32, value: u32) -> Vec<u8> {
        let mut d = b"II*\0".to_vec();
        d.extend_from_slice(&8u32.to_le_bytes());
        d.extend_from_slice(&1u16.to_le_bytes());
        d.extend_from_slice(&tag.to_le_bytes());
        d.extend_from_slice(&typ.to_le_bytes());
        d.extend_from_slice(&count.to_le_bytes());
        d.extend_from_slice(&value.to_le_bytes());
        d.extend_from_slice(&0u32.to_le_bytes());
        d.resize(64, 0);
        d
    }

    #[test]
    fn entries_claiming_more_than_the_file_are_refused() {
        assert!(check_structure(&tiff_with_entry(256, 3, 1, 64)).is_ok());
        let err = check_structure(&tiff_with_entry(271, 4, 0x4000_0000, 8)).unwrap_err();
        assert!(err.contains("tag 271") && err.contains("claims"), "{err}");
    }

    #[test]
    fn ifd_loops_are_refused() {
        // SubIFDs (330) pointing back at the IFD itself.
        let err = check_structure(&tiff_with_entry(330, 4, 1, 8)).unwrap_err();
        assert!(err.contains("loop"), "{err}");
    }

    /// Three corruptions of a real CR3's boxes the fuzz test found, each of which made rawler
    /// loop allocating or allocate 30 GB and abort the process.
    #[test]
    fn cr3_boxes_that_would_abort_the_decoder_are_refused() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/raw");
        let good = std::fs::read(dir.join("stripped-CanonRaw.cr3")).unwrap();
        assert_eq!(check_bmff(&good, 0, good.len(), 0), Ok(()));
        let corrupt = |at: usize, bytes: &[u8]| {
            let mut d = good.clone();
            d[at..at + bytes.len()].copy_from_slice(bytes);
            check_structure(&d).unwrap_err()
        };
        // The first track's co64 (at 9356) claiming 0xFF000001 chunk offsets.
        assert!(corrupt(9356 + 12, &[0xFF, 0, 0, 1]).contains("entries"));
        // A box of size 0 inside the third track's sample table (stsc at 10477).
        assert!(corrupt(10477, &[0, 0, 0, 0]).contains("claims 0 bytes"));
        // The same box 7 bytes too long for the rest of its container: stray bytes.
        assert!(corrupt(10477, &[0, 0, 0, 28 + 7]).contains("box"));
    }

    #[test]
    fn a_real_file_passes_and_stripped_ones_are_judged_without_trouble() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/raw");
        let real = std::fs::read(dir.join("real-canon550d-colorchart.dng")).unwrap();
        assert_eq!(check_structure(&real), Ok(()));
        // The stripped files' headers are genuine but their data is gone: whichever way the
        // walk judges them, it returns.
        for name in [
            "stripped-Nikon.nef",
            "stripped-CanonRaw.cr2",
            "stripped-CanonRaw.cr3",
            "stripped-DNG.dng",
        ] {
            let data = std::fs::read(dir.join(name)).unwrap();
            let _ = check_structure(&data);
        }
    }
}
