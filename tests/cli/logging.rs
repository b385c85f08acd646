//! Log output: plain text when stderr is not a terminal or NO_COLOR is set, coloured on a
//! terminal otherwise, `--log-file` gets the same lines, a compare run's lines name their
//! run, and on a terminal log lines are printed above the progress bar, not through it.
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)]

use crate::common;

use std::process::{Command, Output, Stdio};

use common::{markhold, site_path, tmp_path};

const ESC: char = '\u{1b}';

/// A short HIL run that loses the marker (MarkerLost warnings from the supervisor).
fn occluded_run_args() -> Vec<String> {
    [
        "hil",
        "--seconds",
        "2",
        "--seed",
        "1",
        "--fault",
        "occlude@0.3+1.2",
        "--site",
    ]
    .iter()
    .map(|s| s.to_string())
    .chain([site_path().display().to_string()])
    .collect()
}

fn ok(out: &Output) {
    assert!(
        out.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn piped_stderr_is_plain_and_the_log_file_has_the_lines() {
    let log = tmp_path("logging", "hil.log");
    let out = markhold()
        .args(occluded_run_args())
        .arg("--log-file")
        .arg(&log)
        .env_remove("NO_COLOR")
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    ok(&out);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("MarkerLost"), "no warning on stderr: {err}");
    assert!(!err.contains(ESC), "escape sequences on a pipe: {err:?}");
    let file = std::fs::read_to_string(&log).unwrap();
    assert!(!file.contains(ESC), "escape sequences in the log file");
    let warn_lines = |s: &str| {
        s.lines()
            .filter(|l| l.contains(" WARN ") && l.contains("failsafe"))
            .map(|l| l.split_once(" WARN ").unwrap().1.to_string())
            .collect::<Vec<_>>()
    };
    let (in_file, on_stderr) = (warn_lines(&file), warn_lines(&err));
    assert!(!in_file.is_empty(), "no warning in the log file: {file}");
    assert_eq!(in_file, on_stderr, "the file and stderr differ");
}

#[test]
fn log_file_that_cannot_be_created_is_named() {
    let dir = tmp_path("logging-bad", "no-such-dir");
    let out = markhold()
        .args(["params", "check"])
        .arg(site_path())
        .arg("--log-file")
        .arg(dir.join("x.log"))
        .output()
        .unwrap();
    let err = common::stderr_of_exit(&out, 2);
    assert!(err.contains("--log-file"), "{err}");
}

#[test]
fn compare_lines_name_their_run() {
    let out_dir = tmp_path("logging-compare", "out");
    let log = tmp_path("logging-compare", "compare.log");
    let out = markhold()
        .args([
            "compare",
            "--seeds",
            "1",
            "--seconds",
            "1.5",
            "--methods",
            "default",
            "--lightings",
            "adversarial",
            "--jobs",
            "2",
            "--quiet",
            "--site",
        ])
        .arg(site_path())
        .arg("--out")
        .arg(&out_dir)
        .arg("--log-file")
        .arg(&log)
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    ok(&out);
    let file = std::fs::read_to_string(&log).unwrap();
    let lost: Vec<&str> = file.lines().filter(|l| l.contains("MarkerLost")).collect();
    assert!(
        !lost.is_empty(),
        "a camera's mean AE under a lamp loses the marker: {file}"
    );
    for kind in ["static", "motion", "station"] {
        let name = format!("run{{method=default lighting=adversarial seed=1 kind={kind}}}");
        assert!(
            lost.iter().any(|l| l.contains(&name)),
            "no warning names {name}: {lost:#?}"
        );
    }
    assert!(
        lost.iter().all(|l| l.contains("run{method=")),
        "a warning without its run: {lost:#?}"
    );
}

/// `markhold ARGS` on a pseudo-terminal (util-linux `script`); returns what the terminal got.
fn on_terminal(args: &[String], no_color: bool) -> String {
    let quote = |s: &str| format!("'{}'", s.replace('\'', r"'\''"));
    let bin = env!("CARGO_BIN_EXE_markhold");
    let cmd = std::iter::once(quote(bin))
        .chain(args.iter().map(|a| quote(a)))
        .collect::<Vec<_>>()
        .join(" ");
    let mut c = Command::new("script");
    c.args(["-q", "-e", "-c", &cmd, "/dev/null"])
        .stdin(Stdio::null())
        .env_remove("RUST_LOG")
        .env("TERM", "xterm");
    if no_color {
        c.env("NO_COLOR", "1");
    } else {
        c.env_remove("NO_COLOR");
    }
    let out = c
        .output()
        .expect("util-linux `script` runs the command on a terminal");
    ok(&out);
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn terminal_gets_colour_unless_no_color() {
    let mut args = occluded_run_args();
    args.push("--quiet".into());
    let coloured = on_terminal(&args, false);
    let warn = coloured
        .lines()
        .find(|l| l.contains("MarkerLost"))
        .unwrap_or_else(|| panic!("no warning on the terminal: {coloured:?}"));
    assert!(warn.contains(ESC), "no colour on a terminal: {warn:?}");
    let plain = on_terminal(&args, true);
    let warn = plain
        .lines()
        .find(|l| l.contains("MarkerLost"))
        .unwrap_or_else(|| panic!("no warning on the terminal: {plain:?}"));
    assert!(!warn.contains(ESC), "colour despite NO_COLOR: {warn:?}");
}

#[test]
fn terminal_log_lines_stay_off_the_progress_bar() {
    let term = on_terminal(&occluded_run_args(), true);
    // Every piece of terminal output between line starts (newline or carriage return)
    // that has a warning must not also have the bar's text.
    let pieces: Vec<&str> = term
        .split(['\n', '\r'])
        .filter(|p| p.contains("MarkerLost"))
        .collect();
    assert!(!pieces.is_empty(), "no warning on the terminal: {term:?}");
    for p in pieces {
        assert!(
            !p.contains(" frames"),
            "a log line shares its line with the progress bar: {p:?}"
        );
    }
}
