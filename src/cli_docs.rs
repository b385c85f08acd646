//! Shell completions and man pages made from the command line's clap definitions
//! (`markhold completions SHELL`, `markhold man [--out DIR]`), with the clap project's
//! own generators: clap_complete and clap_mangen.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Context;

/// Writes the completion script for `shell` to `out`. The script is made in memory
/// first: clap_complete panics on a write error, `out` (a closed pipe) may fail.
pub fn completions(
    mut cmd: clap::Command,
    shell: clap_complete::Shell,
    out: &mut dyn Write,
) -> anyhow::Result<()> {
    let name = cmd.get_name().to_string();
    let mut script = Vec::new();
    clap_complete::generate(shell, &mut cmd, name, &mut script);
    out.write_all(&script)
        .and_then(|()| out.flush())
        .with_context(|| format!("writing the {shell} completion script"))
}

/// Renders the top man page (`markhold.1`) to `out`.
pub fn man_page(cmd: clap::Command, out: &mut dyn Write) -> anyhow::Result<()> {
    clap_mangen::Man::new(cmd)
        .render(out)
        .context("rendering the man page")
}

/// Writes `markhold.1` and one page per subcommand (`markhold-hil.1`, ...) into `dir`,
/// creating it; returns the command's pages now in `dir`, sorted.
pub fn man_pages_to(cmd: clap::Command, dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let prefix = cmd.get_name().to_string();
    std::fs::create_dir_all(dir).with_context(|| format!("creating --out {}", dir.display()))?;
    clap_mangen::generate_to(cmd, dir)
        .with_context(|| format!("writing man pages to --out {}", dir.display()))?;
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading --out {}", dir.display()))?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "1"))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with(&prefix))
        })
        .collect();
    files.sort();
    Ok(files)
}
