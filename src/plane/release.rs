//! Giving the memory of frame rows a solve has finished back to the kernel while the solve
//! goes on, for a caller that drops the frames afterwards.
//!
//! Why: a 16 MP solve's outputs are over half a gigabyte of fresh pages, written while the
//! frames (another half gigabyte) are still held. On a virtual machine that hands free memory
//! back to its host (free page reporting), a fresh page costs a fault on the host as well as
//! the kernel's zeroing: perf showed `clear_page_erms` in more than half of the solve's samples.
//! The frame rows a solve has finished are never read again; given back with
//! `madvise(MADV_DONTNEED)`, their pages are what the next output rows fault in, and the peak
//! is lower by what was given back.
//!
//! The buffers each frame owns are given back (its colour planes, DN samples and saturation
//! flags), then the planes the frames share through an `Arc` (a stack's CFA colour ratios, a
//! dark frame) where every holder of them is one of the frames, in whole 2 MiB pages. On the
//! 16 MP DNG set the shared planes are 257 MB (three `f32` ratio planes and the dark frame's
//! `f32` samples), which stayed whole until the frames were dropped after the solve, its peak.

use std::sync::Arc;

use super::dn::Dark;
use super::{Frames, LightFrame};

/// Granularity of what is given back: what a transparent huge page spans (a large buffer may
/// have them, and giving back part of one splits it), and few calls.
const PAGE: usize = 2 << 20;

/// Consent, taken from the frames' owner, to give their rows back to the kernel as they go;
/// see [`FrameRelease::release_rows_before`].
pub struct FrameRelease {
    buffers: Vec<RowBuffer>,
}

/// One row-major buffer of a frame.
struct RowBuffer {
    /// The buffer's first byte: taken from the `Vec` through `&mut` for a buffer a frame owns;
    /// for a shared one, through the `Arc` whose every holder is one of the frames, which their
    /// owner lent with `&mut` (the kernel, not Rust code, writes the zeros, into rows no one
    /// reads again).
    start: *mut u8,
    /// Bytes per row.
    row_bytes: usize,
    /// Bytes in all.
    len: usize,
    /// Bytes from `start` done with: given back, or before the first page boundary.
    done: usize,
    /// Bytes given back.
    given: usize,
}

// SAFETY: the pointers are only used by `release_rows_before`, whose caller guarantees that no
// thread reads the rows it gives back; moving the handle between threads changes nothing.
unsafe impl Send for FrameRelease {}

impl FrameRelease {
    /// Records every buffer the frames own, row by row (`&mut`: only their owner may consent),
    /// then every buffer they share that nothing else holds.
    pub fn new(frames: &mut Frames) -> FrameRelease {
        let (width, height) = (frames.width, frames.height);
        let mut buffers = Vec::new();
        let mut record = |start: *mut u8, elem: usize, len: usize| {
            if len == width * height && len > 0 {
                buffers.push(RowBuffer {
                    start,
                    row_bytes: width * elem,
                    len: len * elem,
                    done: 0,
                    given: 0,
                });
            }
        };
        for frame in &mut frames.lights {
            owned_buffers_mut(frame, &mut record);
        }
        shared_buffers(frames, &mut |start, elem, len| {
            record(start as *mut u8, elem, len)
        });
        FrameRelease { buffers }
    }

    /// Gives back at most `bytes` in all: keeps the first recorded buffers that fit within
    /// them, and leaves the others whole.
    pub fn limit(&mut self, bytes: usize) {
        let mut total = 0;
        self.buffers.retain(|b| {
            total += b.len;
            total <= bytes
        });
    }

    /// Whether there is nothing (left) to give back: no buffer of the frame's size.
    pub fn is_empty(&self) -> bool {
        self.buffers.is_empty()
    }

    /// Bytes given back so far (on Linux; elsewhere nothing is given back, and this counts
    /// what would have been).
    pub fn released_bytes(&self) -> usize {
        self.buffers.iter().map(|b| b.given).sum()
    }

    /// Gives back the whole 2 MiB pages of every recorded buffer that hold only rows before
    /// `y`: those rows then read as zeros (a valid value of every sample type here), and their
    /// pages go back to the kernel.
    ///
    /// # Panics
    /// If `frames` no longer holds the buffers [`FrameRelease::new`] recorded, in order.
    ///
    /// # Safety
    /// `frames` is the `Frames` this release was made from, and no thread reads its rows
    /// before `y` during or after this call (they are only dropped).
    pub unsafe fn release_rows_before(&mut self, frames: &Frames, y: usize) {
        // The recorded buffers are a subsequence of the frames' buffers, in the same order.
        let mut matched = 0;
        let mut each = |start: usize, bytes: usize| {
            let next = self.buffers.get(matched);
            if next.is_some_and(|b| (b.start as usize, b.len) == (start, bytes)) {
                matched += 1;
            }
        };
        for frame in &frames.lights {
            owned_buffers(frame, &mut each);
        }
        shared_buffers(frames, &mut |start, elem, len| {
            each(start as usize, elem * len)
        });
        assert!(
            matched == self.buffers.len(),
            "the frames no longer hold the buffers their release was made from"
        );
        for buffer in &mut self.buffers {
            // SAFETY: the buffer is alive and unmoved (`frames` holds it, checked above), and
            // the caller guarantees its rows before `y` are not read again.
            unsafe { buffer.release_rows_before(y) };
        }
    }
}

impl RowBuffer {
    /// Gives back the whole [`PAGE`]s of the rows before `y`.
    ///
    /// # Safety
    /// The buffer is alive, and its rows before `y` are not read again.
    unsafe fn release_rows_before(&mut self, y: usize) {
        let addr = self.start as usize;
        let end = (addr + (y * self.row_bytes).min(self.len)) / PAGE * PAGE;
        let from = (addr + self.done).next_multiple_of(PAGE);
        if end <= from {
            return;
        }
        #[cfg(target_os = "linux")]
        // SAFETY: [from, end) lies inside the live buffer (the caller's guarantee), in rows no
        // one reads again; MADV_DONTNEED on private anonymous memory makes it read as zeros.
        unsafe {
            libc::madvise(
                self.start.add(from - addr) as *mut libc::c_void,
                end - from,
                libc::MADV_DONTNEED,
            );
        }
        self.done = end - addr;
        self.given += end - from;
    }
}

/// Calls `each(start, element size, elements)` for every row-major buffer `frame` owns.
fn owned_buffers_mut(frame: &mut LightFrame, each: &mut dyn FnMut(*mut u8, usize, usize)) {
    fn one<T>(data: &mut Vec<T>, each: &mut dyn FnMut(*mut u8, usize, usize)) {
        each(
            data.as_mut_ptr() as *mut u8,
            std::mem::size_of::<T>(),
            data.len(),
        );
    }
    for plane in [&mut frame.rgb.r, &mut frame.rgb.g, &mut frame.rgb.b] {
        one(&mut plane.data, each);
    }
    if let Some(mask) = &mut frame.saturated {
        one(&mut mask.data, each);
    }
    if let Some(dn) = &mut frame.dn {
        dn.dn.iter_mut().for_each(|plane| one(plane, each));
    }
    if let Some(mosaic) = &mut frame.cfa_dn {
        one(&mut mosaic.dn, each);
    }
}

/// A plane the frames share through an `Arc`, and its buffers.
enum Shared<'a> {
    Ratios(&'a Arc<super::RgbPlanes>),
    DarkSamples(&'a Arc<Vec<f32>>),
    Dark(&'a Arc<Dark>),
}

impl Shared<'_> {
    /// The `Arc`'s address, which identifies it among the frames, and its strong count.
    fn identity(&self) -> (usize, usize) {
        fn of<T>(arc: &Arc<T>) -> (usize, usize) {
            (
                Arc::as_ptr(arc) as *const () as usize,
                Arc::strong_count(arc),
            )
        }
        match self {
            Shared::Ratios(a) => of(a),
            Shared::DarkSamples(a) => of(a),
            Shared::Dark(a) => of(a),
        }
    }

    /// Calls `each(start, element size, elements)` for each of its row-major buffers.
    fn buffers(&self, each: &mut dyn FnMut(*const u8, usize, usize)) {
        fn one<T>(data: &[T], each: &mut dyn FnMut(*const u8, usize, usize)) {
            each(
                data.as_ptr() as *const u8,
                std::mem::size_of::<T>(),
                data.len(),
            );
        }
        match self {
            Shared::Ratios(ratios) => {
                for plane in [&ratios.r, &ratios.g, &ratios.b] {
                    one(&plane.data, each);
                }
            }
            Shared::DarkSamples(samples) => one(samples, each),
            Shared::Dark(dark) => match &***dark {
                Dark::Planes(rgb) => {
                    for plane in [&rgb.r, &rgb.g, &rgb.b] {
                        one(&plane.data, each);
                    }
                }
                Dark::Dn(samples) => samples.dn.iter().for_each(|plane| one(plane, each)),
            },
        }
    }
}

/// The planes `frame` shares with others through an `Arc`.
fn shared_planes(frame: &LightFrame) -> Vec<Shared<'_>> {
    let mut shared = Vec::new();
    if let Some(cfa) = &frame.cfa {
        shared.push(Shared::Ratios(&cfa.ratios));
    }
    if let Some(dark) = frame.cfa_dn.as_ref().and_then(|m| m.dark.as_ref()) {
        shared.push(Shared::DarkSamples(dark));
    }
    if let Some(dark) = frame.dn.as_ref().and_then(|d| d.dark.as_ref()) {
        shared.push(Shared::Dark(dark));
    }
    shared
}

/// Calls `each(start, element size, elements)` for every buffer of every plane the frames
/// share, once each, in the order the frames first hold them: only for a plane whose every
/// holder is one of the frames (its `Arc`'s strong count is the frames' holds of it), which
/// their owner may then give back. A plane held elsewhere too is left whole.
fn shared_buffers(frames: &Frames, each: &mut dyn FnMut(*const u8, usize, usize)) {
    let shared: Vec<Shared> = frames.lights.iter().flat_map(shared_planes).collect();
    let identities: Vec<(usize, usize)> = shared.iter().map(Shared::identity).collect();
    for (k, (plane, &(address, strong_count))) in shared.iter().zip(&identities).enumerate() {
        // Each plane once, at the first of its holds.
        if identities[..k].iter().any(|&(a, _)| a == address) {
            continue;
        }
        let holds = identities.iter().filter(|&&(a, _)| a == address).count();
        if holds == strong_count {
            plane.buffers(each);
        }
    }
}

/// [`owned_buffers_mut`] read-only, as `each(start address, bytes)`, in the same order.
fn owned_buffers(frame: &LightFrame, each: &mut dyn FnMut(usize, usize)) {
    fn one<T>(data: &[T], each: &mut dyn FnMut(usize, usize)) {
        each(data.as_ptr() as usize, std::mem::size_of_val(data));
    }
    for plane in [&frame.rgb.r, &frame.rgb.g, &frame.rgb.b] {
        one(&plane.data, each);
    }
    if let Some(mask) = &frame.saturated {
        one(&mask.data, each);
    }
    if let Some(dn) = &frame.dn {
        dn.dn.iter().for_each(|plane| one(plane, each));
    }
    if let Some(mosaic) = &frame.cfa_dn {
        one(&mosaic.dn, each);
    }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;
    use crate::plane::{Mask, Plane, RgbPlanes, SensorWindow};

    /// One frame of `width x height` planes of ones, with a saturation mask all set.
    fn frames(width: usize, height: usize) -> Frames {
        let plane = || Plane::new(width, height, 1.0);
        let rgb = RgbPlanes {
            r: plane(),
            g: plane(),
            b: plane(),
        };
        let mask = Mask::new(width, height, true);
        Frames {
            width,
            height,
            window: SensorWindow::FULL,
            lights: vec![LightFrame::from_rgb(rgb, Some(mask))],
        }
    }

    #[test]
    fn given_back_rows_read_as_zeros_and_the_rows_after_them_are_kept() {
        // 4 KiB rows of `f32`: 512 rows to a 2 MiB page, 16 MiB planes.
        let (w, h, half) = (1024, 4096, 2048);
        let mut frames = frames(w, h);
        let mut release = FrameRelease::new(&mut frames);
        // SAFETY: made from these frames; the test reads back only to check the zeros.
        unsafe { release.release_rows_before(&frames, half) };
        let plane = &frames.lights[0].rgb.g.data;
        let zero_rows = (0..h)
            .filter(|&y| plane[y * w..(y + 1) * w].iter().all(|&v| v == 0.0))
            .count();
        // Whole pages only: the rows before the first page boundary are kept, and so is the
        // row across the last one given back.
        assert!(
            (half - 513..=half).contains(&zero_rows),
            "{zero_rows} rows zero"
        );
        assert!(plane[half * w..].iter().all(|&v| v == 1.0));
        let flags = &frames.lights[0].saturated.as_ref().unwrap().data;
        assert!(flags[half * w..].iter().all(|&f| f));
        // Giving the same rows back again gives nothing more; the rest goes at the end.
        let given = release.released_bytes();
        unsafe { release.release_rows_before(&frames, half) };
        assert_eq!(release.released_bytes(), given);
        unsafe { release.release_rows_before(&frames, h) };
        let all = 3 * w * h * 4 + w * h;
        assert!(release.released_bytes() + 4 * 2 * PAGE >= all);
    }

    #[test]
    fn a_limited_release_gives_back_only_the_buffers_within_the_limit() {
        let (w, h) = (1024, 2048);
        let mut frames = frames(w, h);
        let mut release = FrameRelease::new(&mut frames);
        release.limit(w * h * 4 * 3 / 2);
        // SAFETY: made from these frames; the test reads back only to check the zeros.
        unsafe { release.release_rows_before(&frames, h) };
        let rgb = &frames.lights[0].rgb;
        assert!(rgb.r.data.iter().filter(|&&v| v == 0.0).count() >= w * (h - 1024));
        assert!(rgb.g.data.iter().chain(&rgb.b.data).all(|&v| v == 1.0));
        assert!(release.released_bytes() <= w * h * 4);
        release.limit(0);
        assert!(release.is_empty());
    }

    /// Two frames sharing one `Arc` of colour ratios: the ratios' rows go back too, after
    /// the frames' own buffers; ratios held outside the frames as well stay whole.
    #[test]
    fn planes_the_frames_alone_share_are_given_back_too() {
        use crate::plane::CfaColour;
        let (w, h) = (1024, 1024);
        let shared_frames = |outside: bool| {
            let ratios = Arc::new(RgbPlanes {
                r: Plane::new(w, h, 1.0),
                g: Plane::new(w, h, 1.0),
                b: Plane::new(w, h, 1.0),
            });
            let light = || {
                let mut frame = frames(w, h).lights.remove(0);
                frame.cfa = Some(CfaColour {
                    pattern: [[0, 1], [1, 2]],
                    ratios: Arc::clone(&ratios),
                    colour: [1.0; 3],
                });
                frame
            };
            let lights = vec![light(), light()];
            let kept = outside.then(|| Arc::clone(&ratios));
            let frames = Frames {
                width: w,
                height: h,
                window: SensorWindow::FULL,
                lights,
            };
            (frames, kept)
        };
        let zeros = |frames: &Frames| {
            let ratios = &frames.lights[0].cfa.as_ref().unwrap().ratios;
            ratios.r.data.iter().filter(|&&v| v == 0.0).count()
        };
        let release_all = |outside: bool| {
            let (mut frames, kept) = shared_frames(outside);
            let mut release = FrameRelease::new(&mut frames);
            // SAFETY: made from these frames; the test reads back only to check the zeros.
            unsafe { release.release_rows_before(&frames, h) };
            drop(kept);
            (zeros(&frames), release.released_bytes())
        };
        let (shared_zeros, shared_given) = release_all(false);
        let (kept_zeros, kept_given) = release_all(true);
        // Whole 2 MiB pages only: all but the first and last part-pages of each 4 MiB plane.
        assert!(shared_zeros >= w * (h - 512), "{shared_zeros} zeros");
        assert_eq!(kept_zeros, 0, "held outside the frames: kept whole");
        assert!(shared_given >= kept_given + 3 * PAGE);
        // A limit of the frames' own bytes leaves the shared planes whole.
        let (mut frames, _) = shared_frames(false);
        let mut release = FrameRelease::new(&mut frames);
        release.limit(2 * (3 * w * h * 4 + w * h));
        // SAFETY: as above.
        unsafe { release.release_rows_before(&frames, h) };
        assert_eq!(zeros(&frames), 0);
    }

    #[test]
    #[should_panic(expected = "no longer hold the buffers")]
    fn a_release_refuses_frames_that_no_longer_hold_its_buffers() {
        let mut frames = frames(1024, 1024);
        let mut release = FrameRelease::new(&mut frames);
        frames.lights[0].rgb.g = Plane::new(1024, 1024, 1.0);
        // SAFETY: the check fails before anything is given back.
        unsafe { release.release_rows_before(&frames, 512) };
    }
}
