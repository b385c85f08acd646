//! The results tables of README.md and docs/results.md are generated from the result files
//! the HIL runs write (`docs/results/hil/SITE.json`, compared exactly with a fresh 60 s run
//! by `tests/sim/hil_e2e.rs`): a figure edited by hand, or a result file that moved without
//! its tables, fails here. `MARKHOLD_BLESS=1 cargo test --release --test cli
//! result_tables::` rewrites the tables' rows from the files.
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use serde_json::Value;

use crate::common::{bless, repo};

/// The sites of the tables, in their order.
const SITES: [&str; 4] = ["pool", "connecticut-river", "night-harbor", "reef-caustics"];

/// The README's table: detection, position RMS, final error, final exposure.
const README_HEADER: &str = "| site | detection | position RMS | final error | final exposure |";

/// docs/results.md's table adds the final yaw error and the exposure's convergence.
const RESULTS_HEADER: &str = "| site | detection | position RMS | final error | final yaw error \
                              | exposure convergence frames | final exposure |";

fn result(site: &str) -> Value {
    let file = repo(&format!("docs/results/hil/{site}.json"));
    let text = std::fs::read_to_string(&file).unwrap_or_else(|e| {
        panic!(
            "{}: {e}; MARKHOLD_BLESS=1 cargo test --release --test sim hil_e2e:: writes it",
            file.display()
        )
    });
    serde_json::from_str(&text).unwrap()
}

fn num(v: &Value, k: &str) -> f64 {
    v[k].as_f64()
        .unwrap_or_else(|| panic!("result file has no number {k}: {v}"))
}

/// The row a result file gives; `wide` for docs/results.md's columns.
fn row(site: &str, wide: bool) -> String {
    let v = result(site);
    let mut cells = vec![
        site.to_string(),
        format!("{:.1} %", 100.0 * num(&v, "detection_rate")),
        format!("{:.1} mm", 1000.0 * num(&v, "position_rms_m")),
        format!("{:.1} mm", 1000.0 * num(&v, "final_position_error_m")),
    ];
    if wide {
        cells.push(format!("{:.2} deg", num(&v, "final_yaw_error_deg")));
        cells.push(format!("{:.0}", num(&v, "exposure_convergence_frames")));
    }
    cells.push(format!("{:.0} us", num(&v, "final_exposure_us")));
    format!("| {} |", cells.join(" | "))
}

/// The rows under `header` in `text` (the file `doc`) that differ from the result files,
/// one line each naming the line and both texts, and `text` with those rows generated.
fn differences(doc: &str, text: &str, header: &str, wide: bool) -> (String, String) {
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    let at = lines
        .iter()
        .position(|l| l == header)
        .unwrap_or_else(|| panic!("{doc} has no line {header:?}"));
    let first = at + 2; // the header's separator line between
    assert!(
        lines.len() >= first + SITES.len(),
        "{doc}: the table ends early"
    );
    let mut wrong = String::new();
    for (i, site) in SITES.iter().enumerate() {
        let want = row(site, wide);
        if lines[first + i] != want {
            wrong += &format!(
                "  {doc}:{}: {:?}\n    the result file gives {want:?}\n",
                first + i + 1,
                lines[first + i]
            );
            lines[first + i] = want;
        }
    }
    (wrong, lines.join("\n") + "\n")
}

/// Checks (or with `MARKHOLD_BLESS=1` rewrites) the rows under `header` in `doc`.
fn table_is_generated(doc: &str, header: &str, wide: bool) {
    let path = repo(doc);
    let text = std::fs::read_to_string(&path).unwrap();
    let (wrong, generated) = differences(doc, &text, header, wide);
    if bless() {
        if !wrong.is_empty() {
            std::fs::write(&path, generated).unwrap();
            eprintln!("rewrote the table of {doc}:\n{wrong}");
        }
        return;
    }
    assert!(
        wrong.is_empty(),
        "the results table differs from docs/results/hil/*.json:\n{wrong}\
         MARKHOLD_BLESS=1 cargo test --release --test cli result_tables:: rewrites the rows"
    );
}

#[test]
fn the_readme_results_table_is_the_result_files() {
    table_is_generated("README.md", README_HEADER, false);
}

#[test]
fn the_results_md_table_is_the_result_files() {
    table_is_generated("docs/results.md", RESULTS_HEADER, true);
}

/// The check itself: one figure of the generated README table edited by hand is found,
/// named with its line, and generating again puts the file's figure back.
#[test]
fn a_figure_edited_by_hand_is_found() {
    let text = std::fs::read_to_string(repo("README.md")).unwrap();
    let (_, generated) = differences("README.md", &text, README_HEADER, false);
    let pool = row("pool", false);
    let edited = generated.replacen(&pool, &pool.replacen(" mm |", "1 mm |", 1), 1);
    assert_ne!(
        edited, generated,
        "the pool row is not in the generated README"
    );
    let (wrong, again) = differences("README.md", &edited, README_HEADER, false);
    assert!(
        wrong.contains("README.md:") && wrong.contains(&pool),
        "{wrong}"
    );
    assert_eq!(again, generated);
}

/// `scripts/long-tier-section.py RESULTS DOC CHECK` on `doc` with the committed results.
fn long_tier_check(results: &std::path::Path, doc: &std::path::Path) -> std::process::Output {
    std::process::Command::new("python3")
        .arg(repo("scripts/long-tier-section.py"))
        .arg(results)
        .arg(doc)
        .arg("1")
        .output()
        .expect("python3 runs (scripts/install-deps)")
}

/// docs/results.md's long-tier section is what docs/results/long/ gives.
#[test]
fn the_long_tier_section_is_the_result_files() {
    let out = long_tier_check(&repo("docs/results/long"), &repo("docs/results.md"));
    assert!(
        out.status.success(),
        "{}scripts/long-checks docs rewrites the section",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The check can fail: a long-tier figure edited by hand, and a result file that moved
/// without the section, are both found.
#[test]
fn a_long_tier_figure_edited_by_hand_is_found() {
    let dir = crate::common::tmp_path("result-tables", "long-tier");
    std::fs::create_dir_all(&dir).unwrap();
    let results = dir.join("long");
    std::fs::create_dir_all(&results).unwrap();
    for e in std::fs::read_dir(repo("docs/results/long"))
        .into_iter()
        .flatten()
    {
        let e = e.unwrap();
        std::fs::copy(e.path(), results.join(e.file_name())).unwrap();
    }
    let doc = dir.join("results.md");
    let text = std::fs::read_to_string(repo("docs/results.md")).unwrap();
    // A result file that moved: a soak status the section does not show.
    let status = serde_json::json!({
        "component": "soak", "exit_code": 0, "wall_s": 1234, "date": "2000-01-01",
        "host": "a test host", "commit": "abc1234", "scale": 1
    });
    std::fs::write(&doc, &text).unwrap();
    std::fs::write(results.join("soak.status.json"), status.to_string()).unwrap();
    let out = long_tier_check(&results, &doc);
    assert!(!out.status.success(), "a moved result file went unnoticed");
    assert!(String::from_utf8_lossy(&out.stderr).contains("long-tier section differs"));
    // Rewritten from the files, it passes; then one character of it edited by hand fails.
    let rewrite = std::process::Command::new("python3")
        .arg(repo("scripts/long-tier-section.py"))
        .arg(&results)
        .arg(&doc)
        .arg("0")
        .status()
        .unwrap();
    assert!(rewrite.success());
    assert!(long_tier_check(&results, &doc).status.success());
    let generated = std::fs::read_to_string(&doc).unwrap();
    assert!(
        generated.contains("1234 s wall"),
        "the section shows the status"
    );
    std::fs::write(&doc, generated.replacen("1234 s wall", "1233 s wall", 1)).unwrap();
    assert!(!long_tier_check(&results, &doc).status.success());
}
