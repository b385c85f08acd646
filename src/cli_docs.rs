//! Shell completions, man pages and the Markdown command reference made from the command
//! line's clap definitions (`markhold completions SHELL`, `markhold man [--out DIR]`, the
//! hidden `markhold docs`, which writes docs/commands.md). Completions and man pages come
//! from the clap project's own generators (clap_complete, clap_mangen); the Markdown is
//! written here, from clap's introspection API, because no maintained generator is among
//! the project's dependencies.

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

/// The command reference in Markdown: every visible subcommand (nested ones too) with its
/// description, usage line, arguments and options, in the order the help lists them.
/// Deterministic for a build, so docs/commands.md can be compared with it.
pub fn markdown(mut cmd: clap::Command) -> String {
    cmd.build();
    let name = cmd.get_name().to_string();
    let mut md = format!(
        "# {name} commands\n\n\
         Generated from the command line's definitions by `{name} docs > docs/commands.md`; \
         `tests/cli/cli_docs.rs` fails when this file differs from what the build generates. \
         `{name} COMMAND --help` prints the same text, `{name} man` the man pages.\n\n"
    );
    if let Some(about) = cmd.get_about() {
        md.push_str(&format!("{}\n\n", escape(&about.to_string())));
    }
    md.push_str(&options_section("Options of every command", &cmd, true));
    md.push_str("| command | what it does |\n|---|---|\n");
    for sub in visible(&cmd) {
        push_index_rows(&mut md, sub, &name);
    }
    md.push('\n');
    for sub in visible(&cmd) {
        push_command(&mut md, sub, &name);
    }
    md
}

/// The subcommands the help lists (not `help`, not hidden ones).
fn visible(cmd: &clap::Command) -> impl Iterator<Item = &clap::Command> {
    cmd.get_subcommands()
        .filter(|s| !s.is_hide_set() && s.get_name() != "help")
}

fn push_index_rows(md: &mut String, cmd: &clap::Command, parent: &str) {
    let path = format!("{parent} {}", cmd.get_name());
    let about = cmd.get_about().map(|a| one_line(&a.to_string()));
    md.push_str(&format!(
        "| [`{path}`](#{}) | {} |\n",
        path.replace(' ', "-"),
        about.unwrap_or_default().replace('|', "\\|")
    ));
    for sub in visible(cmd) {
        push_index_rows(md, sub, &path);
    }
}

fn push_command(md: &mut String, cmd: &clap::Command, parent: &str) {
    let path = format!("{parent} {}", cmd.get_name());
    md.push_str(&format!("## {path}\n\n"));
    if let Some(about) = cmd.get_long_about().or(cmd.get_about()) {
        md.push_str(&format!("{}\n\n", escape(&about.to_string())));
    }
    let usage = cmd.clone().render_usage().to_string();
    let usage = usage.trim_start_matches("Usage:").trim();
    md.push_str(&format!("```text\n{usage}\n```\n\n"));
    md.push_str(&options_section("Arguments and options", cmd, false));
    for sub in visible(cmd) {
        push_command(md, sub, &path);
    }
}

/// A bullet per argument: name and value, help, default and choices. `globals`: the
/// global options alone (listed once, at the top), else every other argument.
fn options_section(title: &str, cmd: &clap::Command, globals: bool) -> String {
    let args: Vec<&clap::Arg> = cmd
        .get_arguments()
        .filter(|a| !a.is_hide_set() && a.is_global_set() == globals)
        .filter(|a| !matches!(a.get_id().as_str(), "help" | "version"))
        .collect();
    if args.is_empty() {
        return String::new();
    }
    let mut md = format!("{title}:\n\n");
    for arg in args {
        md.push_str(&format!("- `{}`", arg_name(arg)));
        if let Some(help) = arg.get_long_help().or(arg.get_help()) {
            md.push_str(&format!(": {}", escape(&one_line(&help.to_string()))));
        }
        let defaults: Vec<String> = arg
            .get_default_values()
            .iter()
            .map(|v| v.to_string_lossy().into_owned())
            .collect();
        if !defaults.is_empty() && arg.get_action().takes_values() {
            md.push_str(&format!(" [default: `{}`]", defaults.join(",")));
        }
        let choices: Vec<String> = arg
            .get_possible_values()
            .iter()
            .filter(|p| !p.is_hide_set())
            .map(|p| format!("`{}`", p.get_name()))
            .collect();
        if !choices.is_empty() && arg.get_action().takes_values() {
            md.push_str(&format!(" [possible values: {}]", choices.join(", ")));
        }
        md.push('\n');
    }
    md.push('\n');
    md
}

/// `--site <SITE>`, `-o, --out <DIR>`, `<FILE>`: as the help writes them.
fn arg_name(arg: &clap::Arg) -> String {
    let values: Vec<String> = match arg.get_value_names() {
        Some(names) => names.iter().map(|n| format!("<{n}>")).collect(),
        None => vec![format!("<{}>", arg.get_id().as_str().to_uppercase())],
    };
    if arg.is_positional() {
        return values.join(" ");
    }
    let mut name = String::new();
    if let Some(short) = arg.get_short() {
        name.push_str(&format!("-{short}"));
    }
    if let Some(long) = arg.get_long() {
        if !name.is_empty() {
            name.push_str(", ");
        }
        name.push_str(&format!("--{long}"));
    }
    if arg.get_action().takes_values() {
        name.push(' ');
        name.push_str(&values.join(" "));
    }
    name
}

/// The help's lines joined into one (a Markdown list item or table cell).
fn one_line(text: &str) -> String {
    text.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// `<` and `>` outside code spans escaped, so `<device id>` shows instead of being read
/// as an HTML tag.
fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut in_code = false;
    for c in text.chars() {
        match c {
            '`' => {
                in_code = !in_code;
                out.push(c);
            }
            '<' if !in_code => out.push_str("&lt;"),
            '>' if !in_code => out.push_str("&gt;"),
            _ => out.push(c),
        }
    }
    out
}
