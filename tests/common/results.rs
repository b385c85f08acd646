//! HIL summaries compared with committed result files. A HIL run is a function of its seed
//! and build, so a summary with the wall clock's fields removed is compared exactly; a
//! change meant to move it rewrites the file when `MARKHOLD_BLESS=1`.

use std::path::Path;

use serde_json::Value;

/// The summary fields the wall clock changes, and the renderer's build (which changes the
/// speed only: `hil_e2e render_loops_change_the_speed_not_the_run`).
pub const NOT_COMPARED: [&str; 8] = [
    "wall_seconds",
    "realtime_factor",
    "world_wall_seconds",
    "world_realtime_factor",
    "loop_latency_p99_ms",
    "stream_added_latency_p50_ms",
    "stream_added_latency_p99_ms",
    "render_loops",
];

/// `summary` without the fields above.
pub fn without_wall_clock(mut summary: Value) -> Value {
    if let Some(m) = summary.as_object_mut() {
        for k in NOT_COMPARED {
            m.remove(k);
        }
    }
    summary
}

/// The fields of `now` and `want` that differ, one line each.
pub fn differences(now: &Value, want: &Value) -> String {
    let (a, b) = (now.as_object().unwrap(), want.as_object().unwrap());
    let mut keys: Vec<&String> = a.keys().chain(b.keys()).collect();
    keys.sort();
    keys.dedup();
    keys.into_iter()
        .filter(|k| a.get(*k) != b.get(*k))
        .map(|k| format!("  {k}: file {:?}, now {:?}\n", b.get(k), a.get(k)))
        .collect()
}

/// Whether this run rewrites result files (`MARKHOLD_BLESS=1`).
pub fn bless() -> bool {
    std::env::var_os("MARKHOLD_BLESS").is_some_and(|v| v == "1")
}

/// Fails unless `now` (wall-clock fields removed) equals the summary in `file`; with
/// `MARKHOLD_BLESS=1` writes it there instead. `rewrite` is the command that blesses.
pub fn same_as_file(file: &Path, now: &Value, what: &str, rewrite: &str) {
    if bless() {
        let text = serde_json::to_string_pretty(now).unwrap() + "\n";
        std::fs::create_dir_all(file.parent().unwrap()).unwrap();
        std::fs::write(file, text).unwrap();
        eprintln!("rewrote {}", file.display());
        return;
    }
    let text = std::fs::read_to_string(file).unwrap_or_else(|e| {
        panic!(
            "{}: {e}; MARKHOLD_BLESS=1 {rewrite} writes it",
            file.display()
        )
    });
    let want: Value = serde_json::from_str(&text).unwrap();
    assert!(
        *now == want,
        "{what} moved from {}:\n{}if the change is meant, MARKHOLD_BLESS=1 {rewrite} rewrites \
         the file (commit it with the reason)",
        file.display(),
        differences(now, &want)
    );
}
