//! SIGINT and SIGTERM for every command. Both are blocked in every thread and taken by one
//! watcher thread (`sigwait`), which knows which signal came. Commands that stop on their own
//! between steps (capture, the calibration wizard, the firmware demo) get the first signal as
//! their `Interrupt` (LEDs off, frames kept, `--resume` named); everything else, and a second
//! signal, stops at once: progress bar cleared, cursor shown, everything staged removed, what
//! is kept said on stderr, exit 130 (SIGINT) or 143 (SIGTERM).

use std::io::{IsTerminal, Write};
use std::sync::atomic::{AtomicI32, Ordering};
use std::sync::{Mutex, OnceLock};

use psscan::capture::Interrupt;

use super::progress::BarSlot;

/// The signal that stopped the run (0: none yet).
static RECEIVED: AtomicI32 = AtomicI32::new(0);

/// The token of a command that stops on its own, once it has asked for one.
static COOPERATIVE: OnceLock<Interrupt> = OnceLock::new();

/// What the run is doing, for the message when it is stopped.
static DOING: Mutex<String> = Mutex::new(String::new());

/// Blocks SIGINT and SIGTERM in this thread (and so in every thread started after it) and
/// starts the watcher. Call first, before any other thread exists. Child processes start with
/// an empty signal mask (the standard library resets it), so they still get the signals.
pub fn install(command: &str, bars: BarSlot) {
    *DOING.lock().unwrap() = command.to_string();
    let set = signal_set();
    // SAFETY: a valid, initialised signal set; only the calling thread's mask changes.
    unsafe {
        libc::pthread_sigmask(libc::SIG_BLOCK, &set, std::ptr::null_mut());
    }
    std::thread::Builder::new()
        .name("signals".into())
        .spawn(move || watch(set, bars))
        .expect("the signal thread starts");
}

fn signal_set() -> libc::sigset_t {
    // SAFETY: sigemptyset initialises the set before sigaddset uses it.
    unsafe {
        let mut set = std::mem::zeroed::<libc::sigset_t>();
        libc::sigemptyset(&mut set);
        libc::sigaddset(&mut set, libc::SIGINT);
        libc::sigaddset(&mut set, libc::SIGTERM);
        set
    }
}

/// The token the library polls; the first signal sets it instead of stopping the process.
pub fn cooperative() -> Interrupt {
    COOPERATIVE.get_or_init(Interrupt::new).clone()
}

/// The exit code for a run the operator stopped: 128 + the signal (130 for SIGINT, also when
/// the library stopped for a reason of its own).
pub fn interrupted_exit_code() -> i32 {
    match RECEIVED.load(Ordering::SeqCst) {
        0 => 128 + libc::SIGINT,
        s => 128 + s,
    }
}

fn name(signal: i32) -> &'static str {
    if signal == libc::SIGTERM {
        "SIGTERM"
    } else {
        "SIGINT (Ctrl-C)"
    }
}

fn watch(set: libc::sigset_t, bars: BarSlot) {
    loop {
        let mut signal = 0;
        // SAFETY: `set` is initialised; sigwait writes the signal taken into `signal`.
        if unsafe { libc::sigwait(&set, &mut signal) } != 0 {
            continue;
        }
        let first = RECEIVED.swap(signal, Ordering::SeqCst) == 0;
        if let (true, Some(stop)) = (first, COOPERATIVE.get()) {
            stop.set();
            bars.clear();
            eprintln!(
                "psscan: {}: switching the LEDs off and stopping after this step; what is \
                 captured is kept (send it again to quit now)",
                name(signal)
            );
            continue;
        }
        stop_now(signal, &bars);
    }
}

/// Clears the terminal line, removes everything staged, says so, exits.
fn stop_now(signal: i32, bars: &BarSlot) -> ! {
    bars.clear();
    let mut err = std::io::stderr().lock();
    if std::io::stderr().is_terminal() {
        // Back to column 0 on a clean line, cursor shown.
        let _ = write!(err, "\r\x1b[2K\x1b[?25h");
    }
    let removed = psscan::fsutil::remove_staging();
    let doing = DOING.lock().map(|d| d.clone()).unwrap_or_default();
    let _ = writeln!(err, "psscan: {}: stopped {doing} before it finished", name(signal));
    for path in &removed {
        let _ = writeln!(err, "  removed unfinished {}", path.display());
    }
    let _ = writeln!(
        err,
        "  kept: everything that was there before the run (an earlier output under the same \
         name is untouched){}",
        if COOPERATIVE.get().is_some() {
            "; every frame or step already saved"
        } else {
            ""
        }
    );
    let _ = err.flush();
    drop(err);
    // SAFETY: _exit ends the process at once: no destructor or other thread may write into a
    // folder just removed.
    unsafe { libc::_exit(128 + signal) }
}
