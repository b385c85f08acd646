//! The markhold command line.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use markhold::hil_run::{run_hil, HilOptions};
use markhold::params::{self, ParamsError, EXIT_CONFIG};
use markhold::summary::Summary;
use markhold_exposure::ExposureMethod;
use markhold_hil::scene::LightingScenario;

#[derive(Parser)]
#[command(
    name = "markhold",
    version,
    about = "Hold an ArduSub vehicle on station in front of a fiducial marker"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the station-keeping loop against the simulated vehicle, water and camera.
    Hil(HilArgs),
    /// Dive-site parameter files.
    Params {
        #[command(subcommand)]
        command: ParamsCommand,
    },
    /// Serve ArduPilot's SITL JSON physics interface with the simulated vehicle, for
    /// `sim_vehicle.py -v ArduSub -f vectored_6dof --model JSON`.
    Sitl(SitlArgs),
    /// Feed a recording (`--record`) through the loop again and compare its commands.
    Replay(ReplayArgs),
    /// Hold station on a real vehicle with a real camera (Ctrl-C: neutral input, exit 0).
    Run(RunArgs),
    /// The paper's four experiments for every exposure method x lighting x seed, in HIL:
    /// report.md, results.json and plots.
    Compare(markhold::compare::CompareArgs),
}

#[derive(clap::Args)]
struct SitlArgs {
    /// Dive-site file (the vehicle and its start pose come from it).
    #[arg(long, default_value = "params/pool.toml")]
    site: PathBuf,
    /// UDP port ArduPilot sends servo packets to (9002, +10 per extra instance).
    #[arg(long, default_value_t = 9002)]
    port: u16,
    /// Address to bind: loopback unless ArduPilot runs on another machine.
    #[arg(long, default_value = "127.0.0.1")]
    bind: std::net::IpAddr,
    /// Seed of the gusts and waves.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Stop after this many servo packets (default: serve until killed).
    #[arg(long)]
    max_packets: Option<u64>,
    /// With --max-packets: stop after this many wall seconds at most.
    #[arg(long, default_value_t = 60.0)]
    max_seconds: f64,
}

#[derive(Subcommand)]
enum ParamsCommand {
    /// Validate a site file and print the effective values (defaults filled in).
    Check { file: PathBuf },
}

#[derive(clap::Args)]
struct HilArgs {
    /// Dive-site file.
    #[arg(long, default_value = "params/pool.toml")]
    site: PathBuf,
    /// Simulated seconds to run.
    #[arg(long, default_value_t = 60.0)]
    seconds: f64,
    /// Seed of the simulated world (noise, texture, gusts, caustics).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Write a JSON summary here.
    #[arg(long)]
    summary: Option<PathBuf>,
    /// Exposure method: aaec, aec, gec or default (overrides the site file).
    #[arg(long)]
    exposure: Option<ExposureMethod>,
    /// Lighting scenario: normal, low, adversarial or caustics (overrides the site file).
    #[arg(long)]
    lighting: Option<LightingScenario>,
    /// Exposure at start, microseconds (overrides the site file).
    #[arg(long)]
    initial_exposure_us: Option<f64>,
    /// Save frames as PNG into this folder.
    #[arg(long)]
    snapshot: Option<PathBuf>,
    /// With --snapshot: save every n-th frame.
    #[arg(long, default_value_t = 30)]
    snapshot_every: u64,
    /// Write one CSV row per frame (time, exposure, metric, detection, pose, effort).
    #[arg(long, value_name = "FILE.csv")]
    trace: Option<PathBuf>,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
    /// Camera-in-the-loop on an external MAVLink vehicle (e.g. ArduSub SITL:
    /// tcpout:127.0.0.1:5760): its telemetry places the camera, markhold controls it.
    #[arg(long, value_name = "MAVLINK_URL")]
    vehicle: Option<String>,
    /// Inject a fault on simulation time, repeatable: KIND@START[+DURATION] seconds, KIND
    /// one of link_cut, occlude, out_of_view, drop_frames, late_frames, exposure_ignored,
    /// exposure_late, lamp_off, ambient_step (e.g. --fault link_cut@10+3 --fault occlude@20+0.5).
    #[arg(long = "fault", value_name = "KIND@START[+DURATION]")]
    faults: Vec<markhold::faults::FaultSpec>,
    /// Record the run to this MCAP file (must not exist): frames, exposure, detections,
    /// pose, commands, vehicle state, failsafe events; `markhold replay` reads it.
    #[arg(long, value_name = "FILE.mcap")]
    record: Option<PathBuf>,
    /// Serve a Foxglove WebSocket live view on 127.0.0.1 (the same channels as --record).
    #[arg(long)]
    foxglove: bool,
    /// Port of the live view (0: any free port).
    #[arg(long, default_value_t = 8765)]
    foxglove_port: u16,
    /// The renderer's loops: portable, avx2 or avx512 (the widest this CPU runs up to
    /// that; default: the widest). Every build renders the same frames, so the run is
    /// the same; only the world's speed differs (the summary says which ran).
    #[arg(long, value_name = "BUILD")]
    render_loops: Option<markhold_hil::camera::RenderLoops>,
}

#[derive(clap::Args)]
struct RunArgs {
    /// Dive-site file.
    #[arg(long)]
    site: PathBuf,
    /// MAVLink URL of the vehicle (default: the site's [link] url, e.g. BlueOS on
    /// udpout:192.168.2.2:14550; or serial:/dev/ttyACM0:115200).
    #[arg(long, value_name = "URL")]
    link: Option<String>,
    /// Camera: v4l2:/dev/videoN, genicam:<device id> (Aravis; empty: the first camera
    /// found), or frames:DIR (a recorded-frames folder).
    #[arg(long, value_name = "URL")]
    camera: markhold::live::CameraUrl,
    /// Record the run to this MCAP file (must not exist).
    #[arg(long, value_name = "FILE.mcap")]
    record: Option<PathBuf>,
    /// Serve a Foxglove WebSocket live view on 127.0.0.1.
    #[arg(long)]
    foxglove: bool,
    /// Port of the live view (0: any free port).
    #[arg(long, default_value_t = 8765)]
    foxglove_port: u16,
    /// Wall seconds to wait for the vehicle's heartbeat at start-up.
    #[arg(long, default_value_t = 5.0)]
    heartbeat_timeout_s: f64,
    /// Request the site's flight mode and arm before the first frame.
    #[arg(long)]
    arm: bool,
    /// Stop after this many seconds of camera time.
    #[arg(long)]
    seconds: Option<f64>,
    /// With frames:, run as fast as possible instead of at the recorded pace.
    #[arg(long)]
    no_pace: bool,
    /// Write a JSON report (frames, detections, why it stopped, recording losses).
    #[arg(long)]
    summary: Option<PathBuf>,
}

#[derive(clap::Args)]
struct ReplayArgs {
    /// A recording made with --record.
    file: PathBuf,
    /// Write the replay summary (commands_match, first mismatch) here as JSON.
    #[arg(long)]
    summary: Option<PathBuf>,
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("markhold: error: {e:#}");
            if e.downcast_ref::<ParamsError>().is_some() {
                ExitCode::from(EXIT_CONFIG as u8)
            } else {
                ExitCode::from(2)
            }
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Hil(args) => hil(args),
        Command::Params {
            command: ParamsCommand::Check { file },
        } => params_check(&file),
        Command::Sitl(args) => sitl(args),
        Command::Replay(args) => replay(args),
        Command::Run(args) => run_cmd(args),
        Command::Compare(args) => markhold::compare::cli(args),
    }
}

fn params_check(file: &Path) -> anyhow::Result<()> {
    let site = params::load(file)?;
    let text = toml::to_string_pretty(&site.site).context("printing the effective values")?;
    println!(
        "# {}: valid. Effective values, defaults filled in:\n",
        file.display()
    );
    if let Some(note) = params::SIM_SECTIONS_NOTE {
        println!("# {note}\n");
    }
    println!("{text}");
    Ok(())
}

fn sitl(args: SitlArgs) -> anyhow::Result<()> {
    let site = params::load(&args.site)?;
    let cfg = markhold_hil::SitlConfig {
        bind_ip: args.bind,
        port: args.port,
    };
    if let Err(e) = cfg.validate() {
        anyhow::bail!("--port {}: {e}", args.port);
    }
    // The vehicle starts on station, in front of the marker.
    let start = site.t_world_marker() * site.site.station.t_marker_vehicle();
    let mut server = markhold_hil::SitlServer::bind(&cfg, &site.site.vehicle, &start, args.seed)
        .with_context(|| {
            format!(
                "binding the SITL JSON server on {}:{}",
                args.bind, args.port
            )
        })?;
    eprintln!(
        "markhold sitl: ArduPilot JSON physics for site {} on udp {}\n  start ArduSub with: sim_vehicle.py -v ArduSub -f vectored_6dof --model JSON",
        site.site.site.name,
        server.local_addr()?
    );
    match args.max_packets {
        Some(n) => {
            let stats = server.run_bounded(
                n,
                std::time::Duration::from_secs_f64(args.max_seconds.clamp(0.0, 86_400.0)),
            )?;
            println!(
                "markhold sitl: {} packets, {} replies, {} steps, {} repeated, {} resets, {} rejected",
                stats.packets, stats.replies, stats.steps, stats.repeated, stats.resets, stats.rejected
            );
        }
        None => server.run()?,
    }
    Ok(())
}

fn hil(args: HilArgs) -> anyhow::Result<()> {
    let site = params::load(&args.site)?;
    anyhow::ensure!(
        args.seconds > 0.0 && args.seconds.is_finite(),
        "--seconds {}: expected a positive number of simulated seconds",
        args.seconds
    );
    if let Some(dir) = &args.snapshot {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("creating --snapshot {}", dir.display()))?;
    }
    let opts = HilOptions {
        seconds: args.seconds,
        seed: args.seed,
        exposure: args.exposure,
        lighting: args.lighting,
        initial_exposure_us: args.initial_exposure_us,
        snapshot_dir: args.snapshot.clone(),
        snapshot_every: args.snapshot_every.max(1),
        faults: args.faults.clone(),
        render_loops: args.render_loops,
        ..HilOptions::default()
    };
    let frames = (args.seconds * site.site.camera.fps).round() as u64;
    let bar = if args.quiet {
        ProgressBar::hidden()
    } else {
        let b = ProgressBar::new(frames);
        b.set_style(
            ProgressStyle::with_template(
                "{spinner} {elapsed_precise} [{bar:30}] {pos}/{len} frames {msg}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
        );
        b
    };
    let mut snap_err = None;
    let mut trace = match &args.trace {
        Some(p) => Some(markhold::trace::TraceWriter::create(p)?),
        None => None,
    };
    let mut on_frame =
        |rec: &markhold::pipeline::FrameRecord, time_s: f64, frame: &markhold_exposure::Frame| {
            bar.inc(1);
            if let Some(t) = trace.as_mut() {
                t.row(rec);
            }
            if rec.seq.is_multiple_of(15) {
                bar.set_message(format!(
                    "t={:.1}s exp={:.0}us {}",
                    time_s,
                    rec.exposure.exposure_us,
                    if rec.detected { "marker" } else { "no marker" }
                ));
            }
            if let Some(dir) = &opts.snapshot_dir {
                if rec.seq.is_multiple_of(opts.snapshot_every) && snap_err.is_none() {
                    let path = dir.join(format!("frame-{:06}.png", rec.seq));
                    if let Err(e) = markhold::snapshot::save_png(frame, &path) {
                        snap_err = Some(e);
                    }
                }
            }
        };
    anyhow::ensure!(
        args.record.is_none() || args.vehicle.is_none(),
        "--record with --vehicle is not supported: record a simulated run, or use `markhold run`"
    );
    anyhow::ensure!(
        !args.foxglove || args.vehicle.is_none(),
        "--foxglove with --vehicle is not supported: watch a simulated run, or use `markhold run`"
    );
    let mut recorder = match &args.record {
        Some(p) => Some(markhold::record::open_hil_recorder(&site, &opts, p)?),
        // A live view alone: frames the viewer cannot keep up with are dropped, the loop
        // never waits for it.
        None if args.foxglove => Some(markhold::record::Recorder::live_only(
            markhold::record::RecordConfig::default(),
        )?),
        None => None,
    };
    if let (true, Some(r)) = (args.foxglove, recorder.as_mut()) {
        let port = r
            .serve_live(args.foxglove_port)
            .with_context(|| format!("--foxglove-port {}", args.foxglove_port))?;
        eprintln!("markhold: Foxglove live view on ws://127.0.0.1:{port}");
    }
    let summary = match &args.vehicle {
        Some(url) => markhold::external::run_external(&site, url, &opts, &mut |rec, frame| {
            on_frame(rec, rec.stamp_s, frame)
        })?,
        None => match recorder.as_mut() {
            Some(r) => {
                markhold::record::run_hil_recorded(&site, &opts, r, &mut |rec, truth, frame| {
                    on_frame(rec, truth.time_s, frame)
                })?
            }
            None => run_hil(&site, &opts, &mut |rec, truth, frame| {
                on_frame(rec, truth.time_s, frame)
            })?,
        },
    };
    bar.finish_and_clear();
    match (recorder, &args.record) {
        (Some(r), Some(p)) => {
            markhold::record::finish_and_report(r, p)?;
        }
        (Some(r), None) => {
            r.finish().context("stopping the live view")?;
        }
        _ => {}
    }
    if let Some(t) = trace {
        t.finish()?;
    }
    if let Some(e) = snap_err {
        return Err(e.context("saving snapshots"));
    }
    print_table(&site.site.site.name, &summary);
    if let Some(path) = &args.summary {
        let json = serde_json::to_string_pretty(&summary)?;
        std::fs::write(path, json + "\n")
            .with_context(|| format!("writing --summary {}", path.display()))?;
    }
    Ok(())
}

fn print_table(site: &str, s: &Summary) {
    let pct = |v: f64| format!("{:.1} %", 100.0 * v);
    let rows = [
        ("site", site.to_string()),
        ("exposure method", s.exposure_method.clone()),
        ("lighting", s.lighting.clone()),
        ("seed", s.seed.to_string()),
        ("frames", s.frames.to_string()),
        ("simulated time", format!("{:.1} s", s.sim_seconds)),
        (
            "wall time",
            format!(
                "{:.1} s ({:.1}x real time)",
                s.wall_seconds, s.realtime_factor
            ),
        ),
        (
            "HIL world (physics, render)",
            format!(
                "{:.1} s ({:.1}x real time{})",
                s.world_wall_seconds,
                s.world_realtime_factor,
                match s.render_loops.as_str() {
                    "" => String::new(),
                    loops => format!(", {loops} loops"),
                }
            ),
        ),
        ("marker detected", pct(s.detection_rate)),
        (
            "position RMS (last half)",
            format!("{:.3} m", s.position_rms_m),
        ),
        (
            "final position error",
            format!("{:.3} m", s.final_position_error_m),
        ),
        (
            "final yaw error",
            format!("{:.2} deg", s.final_yaw_error_deg),
        ),
        (
            "exposure converged after",
            format!("{} frames", s.exposure_convergence_frames),
        ),
        ("final exposure", format!("{:.0} us", s.final_exposure_us)),
        (
            "loop latency p99",
            format!("{:.2} ms", s.loop_latency_p99_ms),
        ),
    ];
    println!("markhold hil");
    let width = rows.iter().map(|(k, _)| k.len()).max().unwrap_or(0);
    for (k, v) in rows {
        println!("  {k:<width$} {v}");
    }
    print_faults(&s.faults);
}

fn print_faults(faults: &[markhold::faults::FaultReport]) {
    let at = |v: Option<f64>| v.map_or("-".to_string(), |t| format!("{t:.2} s"));
    for f in faults {
        let end = f.end_s.map_or("end".to_string(), |t| format!("{t:.2} s"));
        println!("  fault {} {:.2} s .. {end}", f.kind, f.start_s);
        let rows = [
            ("silent (no vehicle) at", at(f.silent_at_s)),
            ("neutral at", at(f.neutral_at_s)),
            ("heartbeat lost at", at(f.heartbeat_lost_at_s)),
            ("heartbeat restored at", at(f.heartbeat_restored_at_s)),
            ("vehicle disarmed at", at(f.vehicle_disarmed_at_s)),
            ("marker missed at", at(f.marker_missed_at_s)),
            ("marker lost at", at(f.marker_lost_at_s)),
            ("marker detected again at", at(f.marker_detected_again_at_s)),
            ("station regained at", at(f.station_regained_at_s)),
            (
                "max position error",
                format!("{:.3} m", f.max_position_error_m),
            ),
            (
                "exposure range",
                format!("{:.0} .. {:.0} us", f.exposure_min_us, f.exposure_max_us),
            ),
        ];
        for (k, v) in rows {
            println!("    {k:<24} {v}");
        }
    }
}

fn replay(args: ReplayArgs) -> anyhow::Result<()> {
    let out = markhold::replay::replay(&args.file)?;
    println!(
        "markhold replay {}: {} frames replayed of {}, {} commands compared, commands_match: {}",
        args.file.display(),
        out.frames_replayed,
        out.frames_recorded,
        out.commands_compared,
        out.commands_match
    );
    if let Some(m) = &out.first_mismatch {
        println!(
            "  first mismatch: frame {} at {:.3} s, {}: recorded {}, replayed {}",
            m.seq, m.stamp_s, m.field, m.recorded, m.replayed
        );
    }
    if let Some(path) = &args.summary {
        let json = serde_json::to_string_pretty(&out)?;
        std::fs::write(path, json + "\n")
            .with_context(|| format!("writing --summary {}", path.display()))?;
    }
    if !out.commands_match {
        // Not an error of the tool: the recording and this build disagree.
        std::process::exit(1);
    }
    Ok(())
}

fn run_cmd(args: RunArgs) -> anyhow::Result<()> {
    let site = params::load(&args.site)?;
    anyhow::ensure!(
        args.heartbeat_timeout_s.is_finite() && args.heartbeat_timeout_s >= 0.0,
        "--heartbeat-timeout-s {}: expected a non-negative number of seconds",
        args.heartbeat_timeout_s
    );
    let stop = markhold::signal::install()?;
    let opts = markhold::live::RunOptions {
        link_url: args.link.clone(),
        camera: args.camera.clone(),
        record: args.record.clone(),
        foxglove_port: args.foxglove.then_some(args.foxglove_port),
        heartbeat_timeout_s: args.heartbeat_timeout_s,
        arm: args.arm,
        max_seconds: args.seconds,
        pace_frames: !args.no_pace,
    };
    let report = markhold::live::run_live(&site, &opts, &stop)?;
    println!(
        "markhold run: {} frames, marker in {}, {:.1} s of camera time, stopped by {:?}",
        report.frames, report.detected, report.loop_seconds, report.stopped_by
    );
    if report.frames_passed_over > 0 {
        println!(
            "  {} camera frames passed over: the loop was slower than the camera and acted on the newest",
            report.frames_passed_over
        );
    }
    if let (Some(r), Some(p)) = (&report.record, &args.record) {
        println!(
            "  recorded to {} ({} images dropped, {} frames dropped)",
            p.display(),
            r.images_dropped,
            r.frames_dropped
        );
        if let Some(e) = &r.write_error {
            eprintln!("markhold: the recording is incomplete: {e}");
        }
    }
    if let Some(path) = &args.summary {
        let json = serde_json::to_string_pretty(&report)?;
        std::fs::write(path, json + "\n")
            .with_context(|| format!("writing --summary {}", path.display()))?;
    }
    Ok(())
}
