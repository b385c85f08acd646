//! markhold: keeps an ArduSub vehicle on station in front of a fiducial marker.
//!
//! The loop ([`pipeline`]) is built in one place from a site file ([`params`]); runners
//! differ only in their camera, their link and the observers they attach
//! ([`observe`], [`record`]). [`field`] runs it on a real vehicle; [`sim`] (feature
//! `sim`, on by default) against the simulated world.

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

pub mod calibrate;
pub mod cli_docs;
pub mod feasibility;
pub mod field;
pub mod map;
pub mod observe;
pub mod params;
pub mod pipeline;
pub mod record;
pub mod response_fit;
#[cfg(feature = "sim")]
pub mod sim;
pub mod tag;
pub mod web;

/// Write `value` as pretty JSON to `path`: the `--summary` file of every command.
pub fn write_summary(path: &std::path::Path, value: &impl serde::Serialize) -> anyhow::Result<()> {
    use anyhow::Context;
    let json = serde_json::to_string_pretty(value)?;
    std::fs::write(path, json + "\n")
        .with_context(|| format!("writing --summary {}", path.display()))
}
