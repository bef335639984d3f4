//! The operator's stop request (Ctrl-C), as a token the library polls. The CLI sets it from
//! its signal handler; the LED keepalive thread switches the LEDs off as soon as it is set,
//! and the sequencer stops between steps, keeping every frame already committed.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Shared "stop now" flag.
#[derive(Clone, Debug, Default)]
pub struct Interrupt(Arc<AtomicBool>);

impl Interrupt {
    /// A flag not yet set; clones share it.
    pub fn new() -> Self {
        Self::default()
    }

    /// Asks everything holding a clone to stop (the CLI's Ctrl-C handler calls this).
    pub fn set(&self) {
        self.0.store(true, Ordering::SeqCst);
    }

    /// Whether a stop has been asked for.
    pub fn is_set(&self) -> bool {
        self.0.load(Ordering::SeqCst)
    }

    /// `Err(Interrupted)` once the flag is set: the check between a capture's steps.
    pub fn check(&self) -> crate::error::Result<()> {
        if self.is_set() {
            Err(crate::error::Error::Interrupted("Ctrl-C".into()))
        } else {
            Ok(())
        }
    }

    /// Sleeps for `duration` in short steps; returns false as soon as the flag is set.
    /// `Duration::MAX` sleeps until the flag is set.
    pub fn sleep(&self, duration: Duration) -> bool {
        let end = Instant::now().checked_add(duration);
        loop {
            if self.is_set() {
                return false;
            }
            let now = Instant::now();
            let left = match end {
                Some(end) if now >= end => return true,
                Some(end) => end - now,
                None => Duration::MAX,
            };
            std::thread::sleep(left.min(Duration::from_millis(10)));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sleep_ends_early_when_set() {
        let stop = Interrupt::new();
        assert!(stop.sleep(Duration::from_millis(5)));
        let other = stop.clone();
        let t = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(20));
            other.set();
        });
        let start = Instant::now();
        assert!(!stop.sleep(Duration::from_secs(10)));
        assert!(start.elapsed() < Duration::from_secs(5));
        t.join().unwrap();
    }
}
