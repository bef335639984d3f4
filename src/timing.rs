//! Where a command's wall time goes: a table of stages that adds up to the total.
//!
//! Stages that run one after another are timed directly ([`StageClock::time`]). Stages that
//! run interleaved on several threads (reading, hashing and decoding frames; encoding and
//! writing maps) record their busy time per thread in a [`Busy`]; the phase's wall time is
//! then split among them in proportion to their busy time ([`StageClock::time_shared`]), so
//! the table still adds up to the wall time while showing which work filled it. Whatever no
//! stage covers is the `other` row: `sum(stages) + other == total`.

use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use serde::Serialize;

/// The row of the table for time no stage covers.
pub const OTHER: &str = "other";

/// One row of the stage table.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StageTime {
    /// The stage's name (`decode`, `solve`, ...; [`OTHER`] for the rest).
    pub stage: String,
    /// Wall seconds attributed to the stage.
    pub seconds: f64,
    /// Thread seconds the stage kept busy, for stages that run on several threads at once.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub busy_s: Option<f64>,
}

/// Busy time of named stages that run on several threads at once.
pub struct Busy {
    names: Vec<&'static str>,
    nanos: Vec<AtomicU64>,
}

impl Busy {
    /// A counter per stage name, in the order the table will list them.
    pub fn new(names: &[&'static str]) -> Busy {
        Busy {
            names: names.to_vec(),
            nanos: names.iter().map(|_| AtomicU64::new(0)).collect(),
        }
    }

    /// Runs `f`, adding its duration to `stage` (which must be one of the names given).
    pub fn time<T>(&self, stage: &str, f: impl FnOnce() -> T) -> T {
        let start = Instant::now();
        let value = f();
        self.add(stage, start.elapsed());
        value
    }

    /// Adds `elapsed` to `stage`.
    pub fn add(&self, stage: &str, elapsed: Duration) {
        let i = self
            .names
            .iter()
            .position(|n| *n == stage)
            .unwrap_or_else(|| panic!("stage {stage} was not declared"));
        self.nanos[i].fetch_add(elapsed.as_nanos() as u64, Ordering::Relaxed);
    }

    /// Busy seconds per stage, in declaration order.
    pub fn seconds(&self) -> Vec<(&'static str, f64)> {
        self.names
            .iter()
            .zip(&self.nanos)
            .map(|(n, v)| (*n, v.load(Ordering::Relaxed) as f64 * 1e-9))
            .collect()
    }
}

/// The clock of one command: stages in the order they ran, and the total since it started.
pub struct StageClock {
    start: Instant,
    stages: Vec<StageTime>,
}

impl Default for StageClock {
    fn default() -> Self {
        StageClock::start()
    }
}

impl StageClock {
    /// Starts the total now.
    pub fn start() -> StageClock {
        StageClock {
            start: Instant::now(),
            stages: Vec::new(),
        }
    }

    /// Runs `f` as the stage `stage` (a stage timed twice adds up).
    pub fn time<T>(&mut self, stage: &str, f: impl FnOnce() -> T) -> T {
        let start = Instant::now();
        let value = f();
        self.record(stage, start.elapsed().as_secs_f64(), None);
        value
    }

    /// Runs `f`, a phase whose stages run interleaved on several threads and record their busy
    /// time in the `Busy` it is given; the phase's wall time is split among those stages in
    /// proportion to their busy time (all to `fallback` when none was recorded).
    pub fn time_shared<T>(
        &mut self,
        names: &[&'static str],
        fallback: &str,
        f: impl FnOnce(&Busy) -> T,
    ) -> T {
        let busy = Busy::new(names);
        let start = Instant::now();
        let value = f(&busy);
        let wall = start.elapsed().as_secs_f64();
        let shares = busy.seconds();
        let sum: f64 = shares.iter().map(|(_, s)| s).sum();
        if sum <= 0.0 {
            self.record(fallback, wall, None);
        } else {
            // A stage that did not run here (a path this command did not take) gets no row.
            for (name, s) in shares.into_iter().filter(|(_, s)| *s > 0.0) {
                self.record(name, wall * s / sum, Some(s));
            }
        }
        value
    }

    fn record(&mut self, stage: &str, seconds: f64, busy_s: Option<f64>) {
        match self.stages.iter_mut().find(|s| s.stage == stage) {
            Some(row) => {
                row.seconds += seconds;
                row.busy_s = match (row.busy_s, busy_s) {
                    (None, None) => None,
                    (a, b) => Some(a.unwrap_or(0.0) + b.unwrap_or(0.0)),
                };
            }
            None => self.stages.push(StageTime {
                stage: stage.to_string(),
                seconds,
                busy_s,
            }),
        }
    }

    /// Seconds recorded so far for `stage` (0 when it did not run).
    pub fn seconds(&self, stage: &str) -> f64 {
        self.stages
            .iter()
            .find(|s| s.stage == stage)
            .map_or(0.0, |s| s.seconds)
    }

    /// Seconds since the clock started.
    pub fn elapsed(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    /// The table now: the stages, then `other` (the total less the stages), and the total.
    pub fn table(&self) -> (Vec<StageTime>, f64) {
        let total = self.elapsed();
        let covered: f64 = self.stages.iter().map(|s| s.seconds).sum();
        let mut rows = self.stages.clone();
        rows.push(StageTime {
            stage: OTHER.into(),
            seconds: (total - covered).max(0.0),
            busy_s: None,
        });
        (rows, total)
    }
}

/// The table as text, one stage a line with its share of the total.
pub fn format_table(rows: &[StageTime], total: f64) -> String {
    let mut out = String::new();
    for row in rows {
        let share = if total > 0.0 {
            100.0 * row.seconds / total
        } else {
            0.0
        };
        let busy = row
            .busy_s
            .map(|b| format!("  ({b:.3} s busy on all threads)"))
            .unwrap_or_default();
        out.push_str(&format!(
            "  {:<24} {:>8.3} s {:>5.1} %{busy}\n",
            row.stage, row.seconds, share
        ));
    }
    out.push_str(&format!("  {:<24} {:>8.3} s\n", "total", total));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stages_and_other_add_up_to_the_total() {
        let mut clock = StageClock::start();
        clock.time("a", || std::thread::sleep(Duration::from_millis(5)));
        std::thread::sleep(Duration::from_millis(3));
        clock.time_shared(&["x", "y"], "xy", |busy| {
            busy.add("x", Duration::from_millis(30));
            busy.add("y", Duration::from_millis(10));
            std::thread::sleep(Duration::from_millis(8));
        });
        let (rows, total) = clock.table();
        let sum: f64 = rows.iter().map(|r| r.seconds).sum();
        assert!((sum - total).abs() < 1e-9, "{rows:?} vs {total}");
        let other = rows.iter().find(|r| r.stage == OTHER).unwrap().seconds;
        assert!(other >= 0.003, "the untimed sleep is other: {other}");
        // The shared phase is split 3:1 by busy time.
        let (x, y) = (clock.seconds("x"), clock.seconds("y"));
        assert!((x / y - 3.0).abs() < 1e-9, "{x} {y}");
        assert!(x + y >= 0.008);
    }
}
