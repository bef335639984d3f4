//! How a run ends: exit codes, the error text (on stderr, and as JSON with `--json`), clap's
//! usage errors, and the quiet unwinding of a closed stdout pipe.

use std::sync::atomic::Ordering;

use super::{hints, print_json, signals, Cli, JSON_PRINTED};

/// Reports a command's outcome (the error on stderr, and as JSON with `--json`); its exit code.
pub(super) fn exit_code(cli: &Cli, outcome: anyhow::Result<()>) -> i32 {
    match outcome {
        Ok(()) => 0,
        Err(err) => {
            let mut message = error_text(&err);
            if let Some(hint) = hints::for_chain(&err, cli.command.resume()) {
                message = format!("{message}; {hint}");
            }
            // 130 / 143: stopped by SIGINT / SIGTERM, as shells report them.
            let interrupted = err
                .downcast_ref::<psscan::Error>()
                .is_some_and(psscan::Error::is_interrupted);
            let code = if interrupted {
                signals::interrupted_exit_code()
            } else {
                1
            };
            eprintln!("psscan: error: {message}");
            // A script reading --json gets the failure on stdout too, unless the command
            // already printed its own object (a batch's summary names each failed set).
            if cli.json && !JSON_PRINTED.load(Ordering::Relaxed) {
                print_json(&serde_json::json!({ "error": message, "exit_code": code }));
            }
            code
        }
    }
}

/// Rust ignores SIGPIPE, so a print to a closed pipe (`psscan lights ports | head -0`) fails
/// with EPIPE and `println!` panics. The process must not die by the signal instead: a command
/// holding the LEDs or a staging folder has to unwind so its guards switch the LEDs off and
/// remove what it staged. So the panic's message is silenced here, the command unwinds, and
/// `run` turns it into the shell's exit code for SIGPIPE (141).
pub(super) fn quiet_closed_pipe_panics() {
    let previous = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        if !is_closed_pipe_message(panic_text(info.payload())) {
            previous(info);
        }
    }));
}

/// The text of a panic payload (`panic!` with a literal or a formatted message).
pub(super) fn panic_text(payload: &(dyn std::any::Any + Send)) -> &str {
    payload
        .downcast_ref::<String>()
        .map(String::as_str)
        .or_else(|| payload.downcast_ref::<&str>().copied())
        .unwrap_or("")
}

/// Whether a panic is std's "failed printing to stdout/stderr: Broken pipe".
pub(super) fn is_closed_pipe_message(text: &str) -> bool {
    text.starts_with("failed printing to std") && text.contains("Broken pipe")
}

/// A usage error (exit 2, clap's message and usage line on stderr; with `--json` also as a
/// JSON object on stdout). `--help` and `--version` print and exit 0 as clap does.
pub(super) fn usage_error(err: clap::Error) -> i32 {
    use clap::error::ErrorKind;
    if matches!(
        err.kind(),
        ErrorKind::DisplayHelp | ErrorKind::DisplayVersion
    ) {
        err.exit();
    }
    let code = err.exit_code();
    let rendered = err.render().to_string();
    // clap leaves the usage line out of some errors (a value its parser rejected): add it.
    let text = if rendered.contains("Usage:") {
        rendered
    } else {
        let hint = "For more information, try '--help'.";
        format!(
            "{}\n\n{}\n\n{hint}\n",
            rendered.replace(hint, "").trim_end(),
            usage_of_invoked_command()
        )
    };
    if json_requested() {
        let message = text
            .lines()
            .next()
            .unwrap_or_default()
            .trim_start_matches("error: ");
        print_json(&serde_json::json!({
            "error": message,
            "exit_code": code,
            "usage": text.trim_end(),
        }));
    }
    eprint!("{text}");
    code
}

/// The usage line of the (sub)command the arguments name, e.g. `Usage: psscan solve ...`.
fn usage_of_invoked_command() -> String {
    use clap::CommandFactory;
    let mut command = Cli::command();
    command.build();
    let mut current = &command;
    for arg in std::env::args().skip(1) {
        if let Some(sub) = current.find_subcommand(&arg) {
            current = sub;
        }
    }
    current.clone().render_usage().to_string()
}

/// `--json` among the arguments (before any `--`), for errors found before parsing completes.
pub(super) fn json_requested() -> bool {
    std::env::args_os()
        .skip(1)
        .take_while(|a| a != "--")
        .any(|a| a == "--json")
}

/// The error and its causes, each cause only where the text so far does not already say it
/// (an I/O error's message is both in psscan's own text and its source).
fn error_text(err: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in err.chain() {
        let part = cause.to_string();
        if text.is_empty() {
            text = part;
        } else if !text.contains(&part) {
            text.push_str(": ");
            text.push_str(&part);
        }
    }
    text
}
