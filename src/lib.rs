//! markhold: keeps an ArduSub vehicle on station in front of a fiducial marker.
//!
//! The loop ([`pipeline`]) is built in one place from a site file ([`params`]); runners
//! differ only in their camera, their link and the observers they attach
//! ([`observe`], [`record`]). [`field`] runs it on a real vehicle; [`sim`] (feature
//! `sim`, on by default) against the simulated world.

pub mod cli_docs;
pub mod field;
pub mod observe;
pub mod params;
pub mod pipeline;
pub mod record;
#[cfg(feature = "sim")]
pub mod sim;
pub mod tag;

/// Write `value` as pretty JSON to `path`: the `--summary` file of every command.
pub fn write_summary(path: &std::path::Path, value: &impl serde::Serialize) -> anyhow::Result<()> {
    use anyhow::Context;
    let json = serde_json::to_string_pretty(value)?;
    std::fs::write(path, json + "\n")
        .with_context(|| format!("writing --summary {}", path.display()))
}
