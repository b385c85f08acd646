//! `markhold completions` and `markhold man` through the built binary: the scripts and
//! pages come from the same clap definitions the command line parses with.
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Runs markhold with `args`, killed after 30 s; its output (read on other threads, so
/// a long script never blocks the child on a full pipe).
fn markhold(args: &[&str]) -> Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_markhold"))
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let read = |mut r: Box<dyn std::io::Read + Send>| {
        std::thread::spawn(move || {
            let mut b = Vec::new();
            let _ = r.read_to_end(&mut b);
            b
        })
    };
    let out = read(Box::new(child.stdout.take().unwrap()));
    let err = read(Box::new(child.stderr.take().unwrap()));
    let deadline = Instant::now() + Duration::from_secs(30);
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("markhold {args:?} did not exit within 30 s");
        }
        std::thread::sleep(Duration::from_millis(10));
    };
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
    let help = String::from_utf8(markhold(&["--help"]).stdout).unwrap();
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
    let script = String::from_utf8(markhold(&["completions", "bash"]).stdout).unwrap();
    assert!(
        script.contains("complete -F _markhold"),
        "not a bash script"
    );
    for sub in subcommands() {
        assert!(script.contains(&sub), "bash completion lacks `{sub}`");
    }
    assert!(script.contains("--site") && script.contains("--link"));
    for shell in ["zsh", "fish", "elvish", "powershell"] {
        let s = markhold(&["completions", shell]).stdout;
        assert!(
            String::from_utf8(s).unwrap().contains("markhold"),
            "{shell}"
        );
    }
}

#[test]
fn man_page_renders_the_subcommands_and_flags() {
    let page = String::from_utf8(markhold(&["man"]).stdout).unwrap();
    assert!(page.contains(".TH markhold 1"), "{page}");
    assert!(page.contains(".SH SUBCOMMANDS"));
    for sub in subcommands() {
        // roff escapes '-' as '\-'.
        assert!(
            page.contains(&format!("markhold\\-{}(1)", sub.replace('-', "\\-"))),
            "markhold.1 lacks `{sub}`"
        );
    }

    let dir = std::env::temp_dir().join(format!("markhold-man-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let listed =
        String::from_utf8(markhold(&["man", "--out", dir.to_str().unwrap()]).stdout).unwrap();
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
