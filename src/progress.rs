//! How long-running library calls report progress without drawing anything themselves: the
//! library calls this small trait, the CLI implements it with indicatif bars (as espflash
//! does). Implementations must be `Sync` because rows are processed in parallel.

/// Receives progress of one stage at a time.
pub trait Progress: Sync {
    /// A stage named `stage` starts with `total` steps.
    fn begin(&self, _stage: &str, _total: u64) {}
    /// `steps` more steps of the current stage are done.
    fn advance(&self, _steps: u64) {}
    /// The current stage is finished.
    fn end(&self) {}
}

/// Reports nothing (tests, library users who do not care).
pub struct Silent;

impl Progress for Silent {}
