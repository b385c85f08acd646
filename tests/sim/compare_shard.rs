//! `markhold compare --shard I/N` and `markhold compare merge`: three shards merged give
//! the unsharded run's results.json byte for byte (and its report and plots); merge refuses
//! missing, duplicate and foreign shards naming them; and the SLURM job-array script runs
//! the shards on a single-node SLURM cluster this test starts (munged, slurmctld, slurmd
//! from Debian's munge and slurm-wlm, as the current user, in a temporary folder, on
//! loopback ports).
#![cfg(feature = "sim")]
#![allow(clippy::unwrap_used)] // Tests fail loudly on a broken setup, by design.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use crate::common::{markhold, tmp_dir};

const SITE: &str = "tests/fixtures/pool-640.toml";
/// The small sweep: 640x480, 5 s, 1 seed, an AAEC and two others in two lightings (six
/// cases: two per shard).
const SWEEP: &[&str] = &[
    "--site",
    SITE,
    "--seeds",
    "1",
    "--seconds",
    "5",
    "--methods",
    "aaec,gec,default",
    "--lightings",
    "adversarial,normal",
    "--quiet",
];

fn tmp(name: &str) -> PathBuf {
    tmp_dir("compare-shard", name)
}

/// `markhold ARGS EXTRA` run to its end, logging errors only.
fn run(args: &[&str], extra: &[&Path]) -> Output {
    let out = markhold()
        .args(args)
        .args(extra)
        .env("RUST_LOG", "error")
        .output()
        .expect("running markhold");
    out
}

fn ok(out: &Output, what: &str) {
    assert!(
        out.status.success(),
        "{what} failed: {}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The unsharded run and the three shards, once for every test of this file.
struct Runs {
    reference: PathBuf,
    parts: PathBuf,
}

fn runs() -> &'static Runs {
    static RUNS: OnceLock<Runs> = OnceLock::new();
    RUNS.get_or_init(|| {
        let reference = tmp("shard-reference");
        let parts = tmp("shard-parts");
        let mut args = vec!["compare"];
        args.extend(SWEEP);
        args.extend(["--jobs", "2", "--out"]);
        ok(&run(&args, &[&reference]), "unsharded compare");
        for i in 1..=3 {
            let s = format!("{i}/3");
            let mut a = vec!["compare"];
            a.extend(SWEEP);
            a.extend(["--jobs", "2", "--shard", &s, "--out"]);
            ok(&run(&a, &[&parts]), &format!("compare --shard {s}"));
        }
        Runs { reference, parts }
    })
}

fn read(p: &Path) -> Vec<u8> {
    std::fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// results.json byte for byte, and the report and every plot too.
fn assert_same_outputs(reference: &Path, merged: &Path) {
    assert_eq!(
        String::from_utf8(read(&merged.join("results.json"))).unwrap(),
        String::from_utf8(read(&reference.join("results.json"))).unwrap(),
        "merged results.json differs from the unsharded run's"
    );
    let mut n = 0;
    for e in std::fs::read_dir(reference).unwrap() {
        let name = e.unwrap().file_name().into_string().unwrap();
        if name == "timings.json" {
            continue; // wall time: not a function of the seed
        }
        assert!(
            read(&reference.join(&name)) == read(&merged.join(&name)),
            "{name} differs between the unsharded run and the merge"
        );
        n += 1;
    }
    // results.json, report.md, four plots x two lightings x PNG and SVG.
    assert_eq!(n, 2 + 4 * 2 * 2, "files compared");
}

#[test]
fn sharded_then_merged_equals_unsharded() {
    let r = runs();
    for i in 1..=3 {
        assert!(r.parts.join(format!("shard-{i}-of-3.json")).is_file());
    }
    let merged = tmp("shard-merged");
    let out = run(
        &["compare", "merge"],
        &[&r.parts, Path::new("--out"), &merged],
    );
    ok(&out, "compare merge");
    assert_same_outputs(&r.reference, &merged);
    let report = String::from_utf8(read(&merged.join("report.md"))).unwrap();
    assert!(report.contains("## 5. The paper's claims, paired over seeds"));
    assert!(report.contains(
        "| detects the marker more often, static | adversarial | AAEC (markhold) | Default |"
    ));
}

fn merge_err(dirs: &[&Path]) -> String {
    let out_dir = tmp("shard-merge-err-out");
    let mut c = markhold();
    c.args(["compare", "merge"])
        .args(dirs)
        .arg("--out")
        .arg(&out_dir);
    let out = c.output().unwrap();
    assert!(!out.status.success(), "merge of {dirs:?} succeeded");
    assert!(
        !out_dir.join("results.json").exists(),
        "a refused merge wrote results"
    );
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn copy_shards(from: &Path, to: &Path, which: &[u32]) {
    for i in which {
        let name = format!("shard-{i}-of-3.json");
        std::fs::copy(from.join(&name), to.join(&name)).unwrap();
    }
}

#[test]
fn merge_refuses_missing_duplicate_and_foreign_shards() {
    let r = runs();
    let a = tmp("shard-err-a");
    let b = tmp("shard-err-b");
    copy_shards(&r.parts, &a, &[1, 3]);
    let e = merge_err(&[&a]);
    assert!(e.contains("missing shard(s) 2/3 of 3"), "{e}");

    copy_shards(&r.parts, &b, &[2, 3]);
    let e = merge_err(&[&a, &b]);
    assert!(e.contains("duplicate shard 3/3"), "{e}");
    assert!(
        e.contains(&a.join("shard-3-of-3.json").display().to_string())
            && e.contains(&b.join("shard-3-of-3.json").display().to_string()),
        "{e}"
    );

    // Shard 2 of another sweep (other seconds): refused, the files and the field named.
    let c = tmp("shard-err-c");
    let mut args = vec!["compare"];
    args.extend(SWEEP);
    let i = args.iter().position(|x| *x == "--seconds").unwrap();
    args[i + 1] = "0.2";
    args.extend(["--shard", "2/3", "--jobs", "2", "--out"]);
    ok(&run(&args, &[&c]), "foreign shard");
    copy_shards(&r.parts, &c, &[1, 3]);
    let e = merge_err(&[&c]);
    assert!(e.contains("shards of different sweeps"), "{e}");
    assert!(
        e.contains("seconds 5 vs 0.2") || e.contains("seconds 0.2 vs 5"),
        "{e}"
    );
    assert!(e.contains("shard-2-of-3.json"), "{e}");

    let empty = tmp("shard-err-empty");
    let e = merge_err(&[&empty]);
    assert!(e.contains("no shard files"), "{e}");
}

/// A single-node SLURM cluster in a temporary folder: munged, slurmctld and slurmd run
/// as the current user on loopback ports; stopped on drop.
struct Slurm {
    dir: PathBuf,
    conf: PathBuf,
    munge_socket: PathBuf,
    children: Vec<(&'static str, Child)>,
}

impl Drop for Slurm {
    fn drop(&mut self) {
        for (_, c) in self.children.iter_mut().rev() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

fn which(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .chain([PathBuf::from("/usr/sbin"), PathBuf::from("/sbin")])
        .map(|d| d.join(program))
        .find(|p| p.is_file())
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn tail(p: &Path) -> String {
    let s = std::fs::read_to_string(p).unwrap_or_default();
    let lines: Vec<&str> = s.lines().collect();
    format!(
        "--- {} ---\n{}",
        p.display(),
        lines[lines.len().saturating_sub(15)..].join("\n")
    )
}

impl Slurm {
    fn logs(&self) -> String {
        [
            "munged.log",
            "slurmctld.log",
            "slurmd.log",
            "slurmctld.out",
            "slurmd.out",
        ]
        .iter()
        .map(|f| tail(&self.dir.join(f)))
        .collect::<Vec<_>>()
        .join("\n")
    }

    fn spawn(&mut self, name: &'static str, program: &Path, args: &[String]) {
        let log = std::fs::File::create(self.dir.join(format!("{name}.out"))).unwrap();
        let child = Command::new(program)
            .args(args)
            .env("SLURM_CONF", &self.conf)
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .stdin(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("starting {}: {e}", program.display()));
        self.children.push((name, child));
    }

    fn client(&self, program: &str) -> Command {
        let mut c = Command::new(which(program).unwrap());
        c.env("SLURM_CONF", &self.conf);
        c
    }

    /// Start the cluster; panics (the test fails) naming what is missing or what failed.
    fn start() -> Slurm {
        let need = ["munged", "slurmctld", "slurmd", "sbatch", "squeue", "sinfo"];
        let missing: Vec<&str> = need
            .iter()
            .copied()
            .filter(|p| which(p).is_none())
            .collect();
        assert!(
            missing.is_empty(),
            "the SLURM test needs Debian's slurm-wlm and munge (scripts/install-deps \
             installs them); not found: {}",
            missing.join(", ")
        );
        let dir = tmp("slurm");
        let munge = dir.join("munge");
        std::fs::create_dir_all(&munge).unwrap();
        std::fs::create_dir_all(dir.join("state")).unwrap();
        std::fs::create_dir_all(dir.join("spool")).unwrap();
        use std::os::unix::fs::PermissionsExt as _;
        // munged wants its socket folder searchable by all but writable only by itself.
        std::fs::set_permissions(&munge, std::fs::Permissions::from_mode(0o711)).unwrap();
        let key = munge.join("munge.key");
        let mut bytes = vec![0u8; 1024];
        std::io::Read::read_exact(
            &mut std::fs::File::open("/dev/urandom").unwrap(),
            &mut bytes,
        )
        .unwrap();
        std::fs::write(&key, &bytes).unwrap();
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o400)).unwrap();
        let user = String::from_utf8(Command::new("id").arg("-un").output().unwrap().stdout)
            .unwrap()
            .trim()
            .to_string();
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .unwrap()
            .trim()
            .split('.')
            .next()
            .unwrap()
            .to_string();
        let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
        let socket = munge.join("munge.socket");
        let d = dir.display();
        let conf = dir.join("slurm.conf");
        std::fs::write(
            &conf,
            format!(
                "ClusterName=markhold-test\nSlurmctldHost={host}(127.0.0.1)\n\
                 SlurmctldPort={}\nSlurmdPort={}\nSlurmUser={user}\nSlurmdUser={user}\n\
                 AuthType=auth/munge\nCredType=cred/munge\nAuthInfo=socket={}\n\
                 StateSaveLocation={d}/state\nSlurmdSpoolDir={d}/spool\n\
                 SlurmctldPidFile={d}/slurmctld.pid\nSlurmdPidFile={d}/slurmd.pid\n\
                 SlurmctldLogFile={d}/slurmctld.log\nSlurmdLogFile={d}/slurmd.log\n\
                 ProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\n\
                 JobAcctGatherType=jobacct_gather/none\n\
                 AccountingStorageType=accounting_storage/none\nJobCompType=jobcomp/none\n\
                 SchedulerType=sched/builtin\nSelectType=select/cons_tres\n\
                 SelectTypeParameters=CR_Core\nReturnToService=2\nMpiDefault=none\n\
                 NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} State=UNKNOWN\n\
                 PartitionName=test Nodes={host} Default=YES MaxTime=INFINITE State=UP\n",
                free_port(),
                free_port(),
                socket.display()
            ),
        )
        .unwrap();
        let mut s = Slurm {
            dir: dir.clone(),
            conf: conf.clone(),
            munge_socket: socket.clone(),
            children: Vec::new(),
        };
        let m = |p: &Path| p.display().to_string();
        s.spawn(
            "munged",
            &which("munged").unwrap(),
            &[
                "-F".into(),
                "--force".into(),
                format!("--socket={}", m(&socket)),
                format!("--key-file={}", m(&key)),
                format!("--pid-file={}", m(&munge.join("munged.pid"))),
                format!("--log-file={}", m(&dir.join("munged.log"))),
                format!("--seed-file={}", m(&munge.join("munged.seed"))),
            ],
        );
        s.wait_for("munged's socket", Duration::from_secs(20), |s| {
            s.munge_socket.exists()
        });
        let c = m(&conf);
        s.spawn(
            "slurmctld",
            &which("slurmctld").unwrap(),
            &["-D".into(), "-f".into(), c.clone()],
        );
        s.spawn(
            "slurmd",
            &which("slurmd").unwrap(),
            &["-D".into(), "-f".into(), c, "-N".into(), host],
        );
        s.wait_for("the node to be idle", Duration::from_secs(60), |s| {
            s.client("sinfo")
                .args(["-h", "-o", "%T"])
                .output()
                .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "idle")
        });
        s
    }

    /// Poll `ready` every 200 ms until `limit`; fail with the daemons' logs.
    fn wait_for(&mut self, what: &str, limit: Duration, ready: impl Fn(&Slurm) -> bool) {
        let t0 = Instant::now();
        while !ready(self) {
            let exited = self
                .children
                .iter_mut()
                .find_map(|(name, c)| c.try_wait().ok().flatten().map(|st| (*name, st)));
            if let Some((name, st)) = exited {
                panic!("{name} exited ({st}) waiting for {what}\n{}", self.logs());
            }
            assert!(
                t0.elapsed() < limit,
                "waited {limit:?} for {what}\n{}",
                self.logs()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

#[test]
fn slurm_job_array_runs_the_shards_and_the_merge_matches() {
    let r = runs();
    let mut slurm = Slurm::start();
    let parts = tmp("slurm-parts");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/slurm/compare.sbatch");
    let mut sbatch = slurm.client("sbatch");
    sbatch
        .args(["--parsable", "--array=1-3"])
        .arg(format!("--chdir={}", env!("CARGO_MANIFEST_DIR")))
        .arg(format!("--output={}/task-%a.out", slurm.dir.display()))
        .arg(&script)
        .arg("3")
        .args(SWEEP)
        .arg("--out")
        .arg(&parts)
        .env("MARKHOLD", env!("CARGO_BIN_EXE_markhold"))
        .env("RUST_LOG", "error");
    let out = sbatch.output().unwrap();
    assert!(
        out.status.success(),
        "sbatch: {}\n{}",
        String::from_utf8_lossy(&out.stderr),
        slurm.logs()
    );
    let job = String::from_utf8(out.stdout).unwrap().trim().to_string();
    slurm.wait_for(
        &format!("job array {job} to finish"),
        Duration::from_secs(1200),
        |s| {
            s.client("squeue")
                .args(["-h", "-j", &job])
                .output()
                .is_ok_and(|o| o.status.success() && o.stdout.iter().all(u8::is_ascii_whitespace))
        },
    );
    let tasks: String = (1..=3)
        .map(|i| tail(&slurm.dir.join(format!("task-{i}.out"))))
        .collect::<Vec<_>>()
        .join("\n");
    for i in 1..=3 {
        assert!(
            parts.join(format!("shard-{i}-of-3.json")).is_file(),
            "task {i} wrote no shard\n{tasks}\n{}",
            slurm.logs()
        );
    }
    drop(slurm);
    let merged = tmp("slurm-merged");
    let out = run(
        &["compare", "merge"],
        &[&parts, Path::new("--out"), &merged],
    );
    ok(&out, "compare merge of the SLURM shards");
    assert_same_outputs(&r.reference, &merged);
}

/// The three shards of the small sweep copied to a fresh folder, each passed through
/// `edit` (its JSON) first.
fn edited_shards(name: &str, edit: impl Fn(&mut serde_json::Value)) -> PathBuf {
    let r = runs();
    let d = tmp(name);
    for i in 1..=3 {
        let f = format!("shard-{i}-of-3.json");
        let mut v: serde_json::Value = serde_json::from_slice(&read(&r.parts.join(&f))).unwrap();
        edit(&mut v);
        std::fs::write(d.join(&f), serde_json::to_vec(&v).unwrap()).unwrap();
    }
    d
}

#[test]
fn merge_refuses_hostile_shard_files_and_escapes_report_text() {
    // Values no sweep produces: refused, the file, the field and the value named.
    for (field, value, needle) in [
        (
            "station_keeping.detection_rate",
            -5.0f64,
            "station_keeping.detection_rate = -5",
        ),
        (
            "motion_tracking.frames",
            1e12,
            "motion_tracking.frames = 1000000000000",
        ),
    ] {
        let d = edited_shards("shard-bad-value", |v| {
            let (a, b) = field.split_once('.').unwrap();
            v["cases"][0][a][b] = if f64::fract(value) == 0.0 && value > 0.0 {
                serde_json::json!(value as u64)
            } else {
                serde_json::json!(value)
            };
        });
        let e = merge_err(&[&d]);
        assert!(e.contains(needle) && e.contains("shard-"), "{field}: {e}");
    }
    for (key, value, needle) in [
        ("fps", serde_json::json!(0.0), "sweep.header.fps = 0"),
        (
            "seconds",
            serde_json::json!(-1.0),
            "sweep.header.seconds = -1",
        ),
    ] {
        let d = edited_shards("shard-bad-header", |v| {
            v["sweep"]["header"][key] = value.clone()
        });
        let e = merge_err(&[&d]);
        assert!(e.contains(needle), "{key}: {e}");
    }
    // A shard count of 10^8: refused from the file, before anything is made for it.
    let d = tmp("shard-huge-count");
    let mut v: serde_json::Value =
        serde_json::from_slice(&read(&runs().parts.join("shard-1-of-3.json"))).unwrap();
    v["shard"]["count"] = serde_json::json!(100_000_000u32);
    std::fs::write(
        d.join("shard-1-of-100000000.json"),
        serde_json::to_vec(&v).unwrap(),
    )
    .unwrap();
    let e = merge_err(&[&d]);
    assert!(e.contains("1 <= I <= N <= 10000"), "{e}");
    let out = run(&["compare", "--shard", "1/100000000", "--out"], &[&d]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("N <= 10000"));

    // Not regular files: a link to /dev/zero (endless), a FIFO (a reader waits for a
    // writer). Refused at once.
    let d = tmp("shard-special");
    std::os::unix::fs::symlink("/dev/zero", d.join("shard-1-of-1.json")).unwrap();
    let t0 = Instant::now();
    let e = merge_err(&[&d]);
    assert!(e.contains("not a regular file"), "{e}");
    let d = tmp("shard-fifo");
    let fifo = d.join("shard-1-of-1.json");
    let made = Command::new("mkfifo").arg(&fifo).status().unwrap();
    assert!(made.success());
    let e = merge_err(&[&d]);
    assert!(e.contains("not a regular file"), "{e}");
    assert!(t0.elapsed() < Duration::from_secs(30), "{:?}", t0.elapsed());

    // A site name with a newline, a heading and an escape: merged, and written inline.
    let d = edited_shards("shard-name", |v| {
        v["sweep"]["header"]["site"] = serde_json::json!("pool\n# injected\n\u{1b}[31m");
    });
    let merged = tmp("shard-name-out");
    let out = run(&["compare", "merge"], &[&d, Path::new("--out"), &merged]);
    ok(&out, "merge with an odd site name");
    let report = String::from_utf8(read(&merged.join("report.md"))).unwrap();
    assert!(
        !report.lines().any(|l| l.starts_with("# injected")),
        "{report}"
    );
    assert!(!report.contains('\u{1b}'));
    assert!(
        report.starts_with("# markhold compare: pool\\n# injected\\n\\u{1b}[31m\n"),
        "{}",
        &report[..200.min(report.len())]
    );
}
