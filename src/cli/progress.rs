//! indicatif progress bars behind the library's `Progress` trait. Bars draw on stderr and hide
//! themselves when stderr is not a terminal, so `--json` output on stdout stays clean.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use indicatif::{ProgressBar, ProgressStyle};
use psscan::progress::Progress;

pub struct Bars {
    current: BarSlot,
    quiet: bool,
}

/// The bar on screen, shared with the signal watcher so a stopped run leaves a clean line.
#[derive(Clone, Default)]
pub struct BarSlot(Arc<Mutex<Option<ProgressBar>>>);

impl BarSlot {
    fn lock(&self) -> std::sync::MutexGuard<'_, Option<ProgressBar>> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Clears the bar from the terminal (waiting a moment for a thread drawing it).
    pub fn clear(&self) {
        for _ in 0..50 {
            if let Ok(mut slot) = self.0.try_lock() {
                if let Some(bar) = slot.take() {
                    bar.finish_and_clear();
                }
                return;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}

impl Bars {
    pub fn new(quiet: bool) -> Self {
        Bars {
            current: BarSlot::default(),
            quiet,
        }
    }

    /// The bar's slot, for the signal watcher.
    pub fn slot(&self) -> BarSlot {
        self.current.clone()
    }
}

impl Progress for Bars {
    fn begin(&self, stage: &str, total: u64) {
        if self.quiet {
            return;
        }
        let bar = ProgressBar::new(total);
        bar.set_style(
            ProgressStyle::with_template("{prefix:>8} [{bar:40}] {pos}/{len} {elapsed_precise}")
                .expect("valid template")
                .progress_chars("=> "),
        );
        bar.set_prefix(stage.to_string());
        if let Some(old) = self.current.lock().replace(bar) {
            old.finish_and_clear();
        }
    }

    fn advance(&self, steps: u64) {
        if let Some(bar) = self.current.lock().as_ref() {
            bar.inc(steps);
        }
    }

    fn end(&self) {
        if let Some(bar) = self.current.lock().take() {
            bar.finish_and_clear();
        }
    }
}
