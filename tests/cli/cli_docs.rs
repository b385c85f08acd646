//! `markhold completions` and `markhold man` through the built binary: the scripts and
//! pages come from the same clap definitions the command line parses with.
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::process::{Output, Stdio};
use std::time::{Duration, Instant};

use crate::common::{exit_status_by, markhold, read_all, repo, tmp_path};

/// Runs markhold with `args`, killed after 30 s; its output (read on other threads, so
/// a long script never blocks the child on a full pipe).
fn run_bounded(args: &[&str]) -> Output {
    let mut child = markhold()
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let (out, err) = (child.stdout.take().unwrap(), child.stderr.take().unwrap());
    let out = std::thread::spawn(move || read_all(out));
    let err = std::thread::spawn(move || read_all(err));
    let deadline = Instant::now() + Duration::from_secs(30);
    let what = format!("markhold {args:?} did not exit within 30 s");
    let status = exit_status_by(&mut child, deadline, &what);
    let out = Output {
        status,
        stdout: out.join().unwrap(),
        stderr: err.join().unwrap(),
    };
    assert!(out.status.success(), "markhold {args:?}: {out:?}");
    out
}

/// The subcommands `markhold --help` lists (the build's own: with or without `sim`).
fn subcommands() -> Vec<String> {
    let help = String::from_utf8(run_bounded(&["--help"]).stdout).unwrap();
    let list = help
        .split("Commands:")
        .nth(1)
        .unwrap()
        .split("Options:")
        .next()
        .unwrap();
    let names: Vec<String> = list
        .lines()
        .filter_map(|l| l.split_whitespace().next())
        .filter(|w| *w != "help")
        .map(str::to_string)
        .collect();
    assert!(names.len() >= 6, "{names:?}");
    names
}

#[test]
fn bash_completion_mentions_every_subcommand() {
    let script = String::from_utf8(run_bounded(&["completions", "bash"]).stdout).unwrap();
    assert!(
        script.contains("complete -F _markhold"),
        "not a bash script"
    );
    for sub in subcommands() {
        assert!(script.contains(&sub), "bash completion lacks `{sub}`");
    }
    assert!(script.contains("--site") && script.contains("--link"));
    for shell in ["zsh", "fish", "elvish", "powershell"] {
        let s = run_bounded(&["completions", shell]).stdout;
        assert!(
            String::from_utf8(s).unwrap().contains("markhold"),
            "{shell}"
        );
    }
}

#[test]
fn man_page_renders_the_subcommands_and_flags() {
    let page = String::from_utf8(run_bounded(&["man"]).stdout).unwrap();
    assert!(page.contains(".TH markhold 1"), "{page}");
    assert!(page.contains(".SH SUBCOMMANDS"));
    for sub in subcommands() {
        // roff escapes '-' as '\-'.
        assert!(
            page.contains(&format!("markhold\\-{}(1)", sub.replace('-', "\\-"))),
            "markhold.1 lacks `{sub}`"
        );
    }

    let dir = tmp_path("cli-docs", "man");
    let listed =
        String::from_utf8(run_bounded(&["man", "--out", dir.to_str().unwrap()]).stdout).unwrap();
    assert!(listed.contains("markhold.1"), "{listed}");
    for sub in subcommands() {
        assert!(
            dir.join(format!("markhold-{sub}.1")).is_file(),
            "no markhold-{sub}.1 in {listed}"
        );
    }
    let run = std::fs::read_to_string(dir.join("markhold-run.1")).unwrap();
    for flag in ["\\-\\-site", "\\-\\-link", "\\-\\-camera", "\\-\\-arm"] {
        assert!(run.contains(flag), "markhold-run.1 lacks {flag}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// docs/commands.md is what `markhold docs` generates from the command line's definitions
/// (the default build, with the simulation commands): a flag added, renamed or described
/// differently without regenerating the file fails here.
#[cfg(feature = "sim")]
#[test]
fn commands_md_is_what_the_cli_generates() {
    let generated = String::from_utf8(run_bounded(&["docs"]).stdout).unwrap();
    let path = repo("").join("docs/commands.md");
    let file = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        generated.contains("## markhold hil\n") && generated.contains("--site <SITE>"),
        "{generated}"
    );
    if file != generated {
        let line = file
            .lines()
            .zip(generated.lines())
            .position(|(a, b)| a != b)
            .unwrap_or_else(|| file.lines().count().min(generated.lines().count()));
        panic!(
            "{} differs from `markhold docs` from line {}: regenerate it with \
             `cargo run --release -- docs > docs/commands.md`",
            path.display(),
            line + 1
        );
    }
}

/// The Markdown files a reader follows links through: README.md, CONTRIBUTING.md, each
/// crate's README.md and everything under docs/.
fn documents() -> Vec<std::path::PathBuf> {
    let root = repo("");
    let mut files = vec![root.join("README.md"), root.join("CONTRIBUTING.md")];
    for entry in std::fs::read_dir(&root).unwrap() {
        let dir = entry.unwrap().path();
        let readme = dir.join("README.md");
        if dir.is_dir() && dir.file_name().unwrap() != "target" && readme.is_file() {
            files.push(readme);
        }
    }
    let mut stack = vec![root.join("docs")];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let p = entry.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|e| e == "md") {
                files.push(p);
            }
        }
    }
    files.sort();
    files
}

/// The targets of a Markdown text's inline links (`[text](target)`) and reference
/// definitions (`[name]: target`), outside fenced code blocks and code spans.
fn link_targets(text: &str) -> Vec<String> {
    let mut targets = Vec::new();
    let mut fenced = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced {
            continue;
        }
        // Code spans out: what is between backticks is not a link.
        let prose: String = line
            .split('`')
            .enumerate()
            .filter(|(i, _)| i % 2 == 0)
            .map(|(_, s)| s)
            .collect::<Vec<_>>()
            .join(" ");
        let mut rest = prose.as_str();
        while let Some(at) = rest.find("](") {
            let after = &rest[at + 2..];
            let end = after.find(')').unwrap_or(after.len());
            targets.push(after[..end].to_string());
            rest = &after[end..];
        }
        let t = prose.trim_start();
        if t.starts_with('[') && !t.starts_with("[[") {
            if let Some((_, target)) = t.split_once("]: ") {
                targets.push(target.to_string());
            }
        }
    }
    targets
}

/// Every relative link in the documents names a file or folder that exists (the part
/// before `#`; anchors are not checked). Links to web pages are not fetched.
#[test]
fn every_relative_link_in_the_documents_resolves() {
    let docs = documents();
    assert!(docs.len() >= 10, "{docs:?}");
    let mut broken = Vec::new();
    let mut checked = 0;
    for doc in &docs {
        let text = std::fs::read_to_string(doc).unwrap_or_else(|e| panic!("{doc:?}: {e}"));
        for target in link_targets(&text) {
            let target = target.split_whitespace().next().unwrap_or("");
            let file = target.split('#').next().unwrap_or("");
            if file.is_empty() || file.contains("://") || file.starts_with("mailto:") {
                continue;
            }
            checked += 1;
            let resolved = if let Some(abs) = file.strip_prefix('/') {
                repo("").join(abs)
            } else {
                doc.parent().unwrap().join(file)
            };
            if !resolved.exists() {
                broken.push(format!("{}: {target}", doc.display()));
            }
        }
    }
    assert!(
        checked >= 20,
        "only {checked} relative links found: {docs:?}"
    );
    assert!(
        broken.is_empty(),
        "links to no file:\n{}",
        broken.join("\n")
    );
}

/// The link scanner itself: inline links, reference definitions, and no link taken from
/// code.
#[test]
fn link_targets_reads_links_and_skips_code() {
    let text = "see [a](docs/a.md#x) and [b](b.md \"title\")\n\
                `[not](code.md)`\n```\n[nor](fenced.md)\n```\n[ref]: c/d.md\n\
                [[marker.map]]\n";
    assert_eq!(
        link_targets(text),
        ["docs/a.md#x", "b.md \"title\"", "c/d.md"]
    );
}
