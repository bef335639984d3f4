//! SIGINT and SIGTERM for every command. A handler passes the signal's number through a pipe
//! to one watcher thread, which does the work (a handler may do almost nothing safely). Commands that stop on their own
//! between steps (capture, the calibration wizard, the firmware demo) get the first signal as
//! their `Interrupt` (LEDs off, frames kept, `--resume` named); everything else, and a second
//! signal, stops at once: progress bar cleared, cursor shown, everything staged removed, what
//! is kept said on stderr, exit 130 (SIGINT) or 143 (SIGTERM).

use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::sync::atomic::{AtomicI32, Ordering};
use std::sync::{Mutex, OnceLock};

use psscan::capture::Interrupt;
use psscan::fsutil::CommittedOutput;

use super::progress::BarSlot;

/// The signal that stopped the run (0: none yet).
static RECEIVED: AtomicI32 = AtomicI32::new(0);

/// The token of a command that stops on its own, once it has asked for one.
static COOPERATIVE: OnceLock<Interrupt> = OnceLock::new();

/// What the run is doing, for the message when it is stopped.
static DOING: Mutex<String> = Mutex::new(String::new());

/// The write end of the pipe the signal handler reports on.
static PIPE_WRITE: AtomicI32 = AtomicI32::new(-1);

/// The handler: only async-signal-safe work, one byte (the signal number) into the pipe.
extern "C" fn on_signal(signal: libc::c_int) {
    let byte = signal as u8;
    // SAFETY: write(2) is async-signal-safe; the pipe outlives the process.
    unsafe {
        libc::write(
            PIPE_WRITE.load(Ordering::Relaxed),
            (&byte as *const u8).cast(),
            1,
        );
    }
}

/// Installs handlers for SIGINT and SIGTERM that hand the signal to a watcher thread (through
/// a pipe), and starts the watcher.
pub fn install(command: &str, bars: BarSlot) {
    *DOING.lock().unwrap() = command.to_string();
    let mut fds = [0; 2];
    // SAFETY: pipe fills the two descriptors; sigaction gets an initialised struct whose
    // handler only writes to the pipe.
    unsafe {
        if libc::pipe(fds.as_mut_ptr()) != 0 {
            return;
        }
        PIPE_WRITE.store(fds[1], Ordering::Relaxed);
        let mut action = std::mem::zeroed::<libc::sigaction>();
        action.sa_sigaction = on_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
        action.sa_flags = libc::SA_RESTART;
        libc::sigemptyset(&mut action.sa_mask);
        for signal in [libc::SIGINT, libc::SIGTERM] {
            libc::sigaction(signal, &action, std::ptr::null_mut());
        }
    }
    let read_end = fds[0];
    std::thread::Builder::new()
        .name("signals".into())
        .spawn(move || watch(read_end, bars))
        .expect("the signal thread starts");
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

fn watch(read_end: libc::c_int, bars: BarSlot) {
    loop {
        let mut byte = 0u8;
        // SAFETY: reads one byte into a live local.
        let n = unsafe { libc::read(read_end, (&mut byte as *mut u8).cast(), 1) };
        if n != 1 {
            continue;
        }
        let signal = i32::from(byte);
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
    // Taken after the removal, which waits for an output being renamed into place.
    let removed = psscan::fsutil::remove_staging();
    let committed = psscan::fsutil::committed_outputs();
    let doing = DOING.lock().map(|d| d.clone()).unwrap_or_default();
    let message = stop_message(
        name(signal),
        &doing,
        &removed,
        &committed,
        COOPERATIVE.get().is_some(),
    );
    let _ = write!(err, "{message}");
    let _ = err.flush();
    drop(err);
    // SAFETY: _exit ends the process at once: no destructor or other thread may write into a
    // folder just removed.
    unsafe { libc::_exit(128 + signal) }
}

/// What a stopped run says: what it removed, and what it had already finished (an output put
/// in place before the signal is the new output: the earlier one under its name is gone).
fn stop_message(
    signal: &str,
    doing: &str,
    removed: &[PathBuf],
    committed: &[CommittedOutput],
    cooperative: bool,
) -> String {
    let mut out = format!("psscan: {signal}: stopped {doing} before it finished\n");
    for c in committed {
        let replaced = if c.replaced.is_some() {
            " (it replaced the earlier output there)"
        } else {
            ""
        };
        out += &format!(
            "  finished before the stop and in place: {}{replaced}\n",
            c.path.display()
        );
    }
    for path in removed {
        match committed.iter().find(|c| c.replaced.as_ref() == Some(path)) {
            Some(c) => {
                out += &format!(
                    "  removed the earlier output that {} replaced (set aside as {})\n",
                    c.path.display(),
                    path.display()
                )
            }
            None => out += &format!("  removed unfinished {}\n", path.display()),
        }
    }
    let (others, unless_named) = if committed.is_empty() {
        ("", "")
    } else {
        ("else ", " unless named above")
    };
    out += &format!(
        "  kept: everything {others}that was there before the run (an earlier output under the \
         same name is untouched{unless_named}){}\n",
        if cooperative {
            "; every frame or step already saved"
        } else {
            ""
        }
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stop_before_any_commit_says_every_earlier_output_is_untouched() {
        let removed = [PathBuf::from("/o.partial-1-0")];
        let text = stop_message("SIGINT (Ctrl-C)", "`psscan solve`", &removed, &[], false);
        assert!(text.contains("removed unfinished /o.partial-1-0"), "{text}");
        assert!(text.contains("kept: everything that was there before the run (an earlier output under the same name is untouched)"), "{text}");
        assert!(!text.contains("finished before the stop"), "{text}");
    }

    #[test]
    fn a_stop_after_a_commit_names_the_new_output_and_the_replaced_one() {
        let committed = [CommittedOutput {
            path: PathBuf::from("/o"),
            replaced: Some(PathBuf::from("/o.old-1-3")),
        }];
        let removed = [PathBuf::from("/o.old-1-3")];
        let text = stop_message(
            "SIGINT (Ctrl-C)",
            "`psscan solve`",
            &removed,
            &committed,
            false,
        );
        assert!(
            text.contains(
                "finished before the stop and in place: /o (it replaced the earlier output there)"
            ),
            "{text}"
        );
        assert!(
            text.contains("removed the earlier output that /o replaced (set aside as /o.old-1-3)"),
            "{text}"
        );
        assert!(!text.contains("removed unfinished"), "{text}");
        assert!(text.contains("kept: everything else"), "{text}");
        assert!(text.contains("untouched unless named above"), "{text}");
    }
}
