//! markhold's loop and what every runner shares.
//!
//! The loop ([`pipeline`]) is built in one place from a site file ([`params`]); runners
//! differ only in their camera, their link and the observers they attach ([`observe`],
//! [`record`], [`web`]). The glue both the real-vehicle runner (`markhold-field`) and the
//! simulator (`markhold-sim`) use lives here too: engagement on a vehicle link
//! ([`engage`]), Ctrl-C and SIGTERM ([`signal`]) and a stream camera's exposure control
//! ([`control`]). Nothing here imports simulation code except, with the feature `sim`,
//! the site file's simulator sections.

/// `println!` for the command's report: a closed stdout (`markhold ... | head -1`)
/// ends the program quietly with status 0 instead of a panic; other write errors are
/// reported on stderr once the report is done.
#[macro_export]
macro_rules! outln {
    ($($arg:tt)*) => {
        $crate::print_report(format_args!($($arg)*))
    };
}

/// One line of a command's report on stdout (see [`outln!`]).
pub fn print_report(args: std::fmt::Arguments<'_>) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    if let Err(e) = out.write_fmt(args).and_then(|()| out.write_all(b"\n")) {
        if e.kind() == std::io::ErrorKind::BrokenPipe {
            // The reader has gone: nobody is left to tell.
            std::process::exit(0);
        }
        eprintln!("markhold: writing to stdout: {e}");
    }
}

pub mod control;
pub mod engage;
pub mod error;
pub mod feasibility;
pub mod observe;
pub mod params;
pub mod pipeline;
pub mod record;
pub mod signal;
pub mod web;

pub use error::CoreError;

/// Write `value` as pretty JSON to `path`: the `--summary` file of every command.
pub fn write_summary(
    path: &std::path::Path,
    value: &impl serde::Serialize,
) -> Result<(), CoreError> {
    let json = serde_json::to_string_pretty(value)?;
    std::fs::write(path, json + "\n").map_err(|source| CoreError::File {
        action: "writing --summary",
        path: path.to_path_buf(),
        source,
    })
}
