//! The command line, site files and packaging: `params check` and its messages, shell
//! completions, man pages and docs/commands.md, the results tables generated from result
//! files, `markhold tag`, log output, and the BlueOS extension's files.
//!
//! One test binary, one link (tests/common holds the helpers); each module carries its own
//! `#![cfg(...)]`: the builds it runs in.

#[path = "../common/mod.rs"]
mod common;

mod cli_docs;
mod extension;
mod logging;
mod params_check;
mod result_tables;
mod tag;
