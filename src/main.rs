//! The markhold command line.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use clap::{CommandFactory, Parser, Subcommand};
use markhold::params::{self, ParamsError, EXIT_CONFIG};

#[derive(Parser)]
#[command(
    name = "markhold",
    version,
    about = "Hold an ArduSub vehicle on station in front of a fiducial marker"
)]
struct Cli {
    /// Also write the logs, as plain text, to this file (created or truncated).
    #[arg(long, global = true, value_name = "FILE")]
    log_file: Option<PathBuf>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the station-keeping loop against the simulated vehicle, water and camera.
    #[cfg(feature = "sim")]
    Hil(markhold::sim::cmd::HilArgs),
    /// Dive-site parameter files.
    Params {
        #[command(subcommand)]
        command: ParamsCommand,
    },
    /// Serve ArduPilot's SITL JSON physics interface with the simulated vehicle, for
    /// `sim_vehicle.py -v ArduSub -f vectored_6dof --model JSON`.
    #[cfg(feature = "sim")]
    Sitl(markhold::sim::cmd::SitlArgs),
    /// Fly the real ArduSub (SITL, `--model JSON`) with markhold's physics as its JSON
    /// backend and the camera rendered from the same physics state, in lockstep.
    #[cfg(feature = "sim")]
    SitlLoop(markhold::sim::sitl_loop::SitlLoopArgs),
    /// The same sites and seed on markhold's simulated ArduSub and on ArduSub SITL:
    /// hold figures and stick-step responses per mode, side by side.
    #[cfg(feature = "sim")]
    SitlCompare(markhold::sim::side_by_side::SitlCompareArgs),
    /// Feed a recording (`--record`) through the loop again and compare its commands.
    Replay(ReplayArgs),
    /// Hold station on a real vehicle with a real camera (Ctrl-C: neutral input, exit 0).
    Run(RunArgs),
    /// Check that the vehicle is set up for markhold (parameters, version, mode, link
    /// latency): a checklist with the fix for each item; exit 1 on a fail.
    Preflight(PreflightArgs),
    /// The paper's four experiments for every exposure method x lighting x seed, in HIL:
    /// report.md, results.json and plots.
    #[cfg(feature = "sim")]
    Compare(markhold::sim::compare::CompareArgs),
    /// The station keeper with the site's gains against a grid of model errors and
    /// disturbances, in HIL: report.md, results.json and a heat map; exit 1 when a cell
    /// did not hold.
    #[cfg(feature = "sim")]
    Robustness(markhold::sim::robustness::RobustnessArgs),
    /// Build the site's marker map ([[marker.map]]: each marker's pose in the site frame)
    /// from a recording or a frames folder in which several markers are seen together.
    Map(markhold::map::MapArgs),
    /// A printable marker at exact physical size (SVG, PDF or PNG) with its caption.
    Tag(markhold::tag::TagArgs),
    /// The camera's intrinsics and lens model from views of a printed target (ChArUco,
    /// checkerboard, AprilTag grid): the calibration file, per-view errors, a coverage
    /// picture; or the printable target (--print-target).
    Calibrate(Box<markhold::calibrate::CalibrateArgs>),
    /// The camera response: fit it from an exposure sweep (a regularised g' table, or the
    /// paper's polynomial form).
    Response {
        #[command(subcommand)]
        command: markhold::response_fit::ResponseCommand,
    },
    /// Print a shell completion script: bash, zsh, fish, elvish or powershell.
    Completions {
        /// The shell to complete for.
        shell: clap_complete::Shell,
    },
    /// Man pages: print markhold.1, or with --out write markhold.1 and one page per
    /// subcommand (markhold-hil.1, ...) into DIR.
    Man {
        /// Folder to write the pages into (created if missing).
        #[arg(long, value_name = "DIR")]
        out: Option<PathBuf>,
    },
    /// Print the Markdown command reference (docs/commands.md).
    #[command(hide = true)]
    Docs,
}

#[derive(Subcommand)]
enum ParamsCommand {
    /// Validate a site file and print the effective values (defaults filled in).
    Check { file: PathBuf },
}

#[derive(clap::Args)]
struct RunArgs {
    /// Dive-site file.
    #[arg(long)]
    site: PathBuf,
    /// MAVLink connection string of the vehicle, as pymavlink reads it (default: the
    /// site's [link] url): tcp:HOST:PORT connects (on the BlueOS Pi: tcp:127.0.0.1:5777),
    /// udpin: or udp:HOST:PORT listens (topside: udpin:0.0.0.0:14551), udpout:HOST:PORT
    /// sends to, tcpin: accepts, /dev/ttyACM0,115200 or serial:/dev/ttyACM0:115200 is a
    /// serial port.
    #[arg(long, value_name = "URL")]
    link: Option<String>,
    /// Engage at once when the vehicle is heard (default: the pilot engages by arming in
    /// the site's [link] mode, or switching to it while armed, after markhold says ready).
    #[arg(long)]
    engage: bool,
    /// Skip the preflight check of the vehicle's parameters before arming.
    #[arg(long)]
    no_preflight: bool,
    /// Camera: v4l2:/dev/videoN, genicam:<device id> (Aravis; empty: the first camera
    /// found), or frames:DIR (a recorded-frames folder).
    #[arg(long, value_name = "URL")]
    camera: markhold::field::camera::CameraUrl,
    /// Record the run to this MCAP file (must not exist).
    #[arg(long, value_name = "FILE.mcap")]
    record: Option<PathBuf>,
    /// Serve a Foxglove WebSocket live view (browser pages only from the site's [live]
    /// allowed_origins).
    #[arg(long)]
    foxglove: bool,
    /// Port of the live view (0: any free port).
    #[arg(long, default_value_t = 8765)]
    foxglove_port: u16,
    /// Address the live view listens on: 127.0.0.1 for this machine alone, 0.0.0.0 to
    /// let the topside in (the BlueOS extension's).
    #[arg(long, value_name = "IP", default_value = "127.0.0.1")]
    foxglove_bind: std::net::IpAddr,
    #[command(flatten)]
    web: markhold::web::WebArgs,
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
    /// Write one CSV row per frame (time, exposure, metric, detection, pose, effort).
    #[arg(long, value_name = "FILE.csv")]
    trace: Option<PathBuf>,
    /// Save the camera's frames into this folder (PNG and frames.csv with each frame's
    /// stamp and exposure): `--camera frames:DIR` plays it back.
    #[arg(long, value_name = "DIR")]
    record_frames: Option<PathBuf>,
    /// With --record-frames: save every n-th frame.
    #[arg(long, default_value_t = 1)]
    record_frames_every: u64,
}

#[derive(clap::Args)]
struct PreflightArgs {
    /// Dive-site file.
    #[arg(long)]
    site: PathBuf,
    /// MAVLink connection string of the vehicle (default: the site's [link] url).
    #[arg(long, value_name = "URL")]
    link: Option<String>,
    /// Wall seconds to wait for the vehicle's heartbeat.
    #[arg(long, default_value_t = 5.0)]
    heartbeat_timeout_s: f64,
    /// Also write the checklist as JSON.
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
    let cli = Cli::parse();
    let result = init_logging(cli.log_file.as_deref()).and_then(|()| run(cli));
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("markhold: error: {e:#}");
            if is_site_error(&e) {
                ExitCode::from(EXIT_CONFIG as u8)
            } else {
                ExitCode::from(2)
            }
        }
    }
}

/// A site file that cannot be read or used, wherever in the chain it surfaced (the
/// crates' error enums carry it unchanged).
fn is_site_error(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.is::<ParamsError>()
            || c.downcast_ref::<markhold::error::CoreError>()
                .and_then(markhold::error::CoreError::params)
                .is_some()
            || c.downcast_ref::<markhold::field::FieldError>()
                .and_then(markhold::field::FieldError::params)
                .is_some()
            || is_sim_site_error(c)
    })
}

#[cfg(feature = "sim")]
fn is_sim_site_error(e: &(dyn std::error::Error + 'static)) -> bool {
    e.downcast_ref::<markhold::sim::SimError>()
        .and_then(markhold::sim::SimError::params)
        .is_some()
}

#[cfg(not(feature = "sim"))]
fn is_sim_site_error(_: &(dyn std::error::Error + 'static)) -> bool {
    false
}

/// The logs: on stderr, printed above the progress bars (tracing-indicatif draws the bars,
/// which are spans, and its writer suspends them for each line), coloured only when stderr
/// is a terminal and `NO_COLOR` is unset or empty; with `--log-file`, also as plain text to
/// that file. `RUST_LOG` filters both (default: warnings and errors).
fn init_logging(log_file: Option<&Path>) -> anyhow::Result<()> {
    use std::io::IsTerminal;
    use tracing_subscriber::layer::SubscriberExt;
    use tracing_subscriber::util::SubscriberInitExt;
    use tracing_subscriber::{EnvFilter, Layer};

    let filter = || EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("warn"));
    let colour = std::io::stderr().is_terminal()
        && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
    let bars = tracing_indicatif::IndicatifLayer::new();
    let stderr = tracing_subscriber::fmt::layer()
        .with_writer(bars.get_stderr_writer())
        .with_ansi(colour)
        .with_filter(filter());
    let file = match log_file {
        Some(path) => {
            let f = std::fs::File::create(path)
                .with_context(|| format!("creating --log-file {}", path.display()))?;
            Some(
                tracing_subscriber::fmt::layer()
                    .with_writer(std::sync::Mutex::new(f))
                    .with_ansi(false)
                    .fmt_fields(PlainFields::default())
                    .with_filter(filter()),
            )
        }
        None => None,
    };
    tracing_subscriber::registry()
        .with(stderr)
        .with(file)
        .with(bars.with_filter(tracing_indicatif::filter::IndicatifFilter::new(false)))
        .try_init()
        .context("setting up the logs")
}

/// The log file's field formatter: the default one under its own type, so the span fields
/// the file's layer keeps are formatted without colour (fmt layers share what one field
/// formatter type cached for a span, and the terminal's may be coloured).
#[derive(Default)]
struct PlainFields(tracing_subscriber::fmt::format::DefaultFields);

impl<'w> tracing_subscriber::fmt::FormatFields<'w> for PlainFields {
    fn format_fields<R: tracing_subscriber::field::RecordFields>(
        &self,
        writer: tracing_subscriber::fmt::format::Writer<'w>,
        fields: R,
    ) -> std::fmt::Result {
        self.0.format_fields(writer, fields)
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        #[cfg(feature = "sim")]
        Command::Hil(args) => Ok(markhold::sim::cmd::hil(args)?),
        Command::Params {
            command: ParamsCommand::Check { file },
        } => params_check(&file),
        #[cfg(feature = "sim")]
        Command::Sitl(args) => Ok(markhold::sim::cmd::sitl(args)?),
        #[cfg(feature = "sim")]
        Command::SitlLoop(args) => Ok(markhold::sim::sitl_loop::cli(args)?),
        #[cfg(feature = "sim")]
        Command::SitlCompare(args) => Ok(markhold::sim::side_by_side::cli(args)?),
        Command::Replay(args) => replay(args),
        Command::Run(args) => run_cmd(args),
        Command::Preflight(args) => preflight_cmd(args),
        #[cfg(feature = "sim")]
        Command::Compare(args) => Ok(markhold::sim::compare::cli(args)?),
        #[cfg(feature = "sim")]
        Command::Robustness(args) => Ok(markhold::sim::robustness::cli(args)?),
        Command::Map(args) => markhold::map::cli(args),
        Command::Tag(args) => markhold::tag::cli(args),
        Command::Calibrate(args) => markhold::calibrate::cli(*args),
        Command::Response { command } => markhold::response_fit::cli(command),
        Command::Completions { shell } => {
            markhold::cli_docs::completions(Cli::command(), shell, &mut std::io::stdout())
        }
        Command::Man { out: None } => {
            markhold::cli_docs::man_page(Cli::command(), &mut std::io::stdout())
        }
        Command::Man { out: Some(dir) } => {
            for page in markhold::cli_docs::man_pages_to(Cli::command(), &dir)? {
                markhold::outln!("{}", page.display());
            }
            Ok(())
        }
        Command::Docs => {
            markhold::outln!(
                "{}",
                markhold::cli_docs::markdown(Cli::command()).trim_end()
            );
            Ok(())
        }
    }
}

fn params_check(file: &Path) -> anyhow::Result<()> {
    let site = params::load(file)?;
    let text =
        toml::to_string_pretty(&site.effective()).context("printing the effective values")?;
    markhold::outln!(
        "# {}: valid. Effective values, defaults filled in:",
        file.display()
    );
    match &site.site.camera.calibration_file {
        Some(calib) => markhold::outln!(
            "# camera intrinsics and distortion from {} ({} coefficients)",
            calib.display(),
            site.calibration.dist.len()
        ),
        None => markhold::outln!("# camera intrinsics from [camera]"),
    }
    if site.calibration.dist.len() > 5
        || site.calibration.model != markhold_vision::DistortionModel::PlumbBob
    {
        markhold::outln!(
            "# lens model {}: {:?}",
            site.calibration.model,
            site.calibration.dist
        );
    }
    for w in markhold::calibrate::site_warnings(&site, false) {
        markhold::outln!("# WARNING: {w}");
        tracing::warn!("{}: {w}", file.display());
    }
    // The simulator's start pose, in a build that has the simulator.
    #[cfg(feature = "sim")]
    let start = Some(markhold::sim::hil::start_in_marker(
        &site.site,
        site.site.vehicle.initial_offset_m,
    ));
    #[cfg(not(feature = "sim"))]
    let start = None;
    markhold::feasibility::print_check(&site, start.as_ref());
    print_map(&site.site.marker);
    if let Some(note) = params::SIM_SECTIONS_NOTE {
        markhold::outln!("# {note}");
    }
    markhold::outln!("\n{text}");
    Ok(())
}

/// `params check`'s lines about a marker map (nothing for a map of one).
fn print_map(m: &markhold_vision::MarkerConfig) {
    if m.map.is_empty() {
        return;
    }
    markhold::outln!(
        "# marker map: {} markers of {}; the site frame is marker {}'s (x right, y up, z out \
         of its face)",
        m.len(),
        m.family,
        m.id
    );
    markhold::outln!("#   id {:>4}  size {:.3} m  origin", m.id, m.size_m);
    for e in &m.map {
        let [x, y, z] = e.position_m;
        let [r, p, w] = e.rpy_deg;
        markhold::outln!(
            "#   id {:>4}  size {:.3} m  at ({x:.3}, {y:.3}, {z:.3}) m  rpy ({r:.1}, {p:.1}, \
             {w:.1}) deg",
            e.id,
            e.size_m
        );
    }
}

fn replay(args: ReplayArgs) -> anyhow::Result<()> {
    let out = markhold::record::replay::replay(&args.file)?;
    markhold::outln!(
        "markhold replay {}: {} frames replayed of {}, {} commands compared, commands_match: {}",
        args.file.display(),
        out.frames_replayed,
        out.frames_recorded,
        out.commands_compared,
        out.commands_match
    );
    if let Some(m) = &out.first_mismatch {
        markhold::outln!(
            "  first mismatch: frame {} at {:.3} s, {}: recorded {}, replayed {}",
            m.seq,
            m.stamp_s,
            m.field,
            m.recorded,
            m.replayed
        );
    }
    if let Some(r) = &out.recovered {
        markhold::outln!(
            "  the file ends early ({} bytes; {}): replayed what its complete chunks hold, \
             {} frames",
            r.file_bytes,
            r.reason,
            out.frames_recorded
        );
    }
    if out.lossy_images > 0 {
        markhold::outln!(
            "  not bit-exact: {} images were recorded as JPEG (lossy), so the loop saw other \
             pixels than when recording; record with image_format = \"png\" for an exact replay",
            out.lossy_images
        );
    }
    if let Some(path) = &args.summary {
        markhold::write_summary(path, &out)?;
    }
    if !out.commands_match && out.lossy_images == 0 {
        // Not an error of the tool: the recording and this build disagree.
        std::process::exit(1);
    }
    Ok(())
}

/// `--heartbeat-timeout-s`: finite and not negative.
fn check_heartbeat_timeout(s: f64) -> anyhow::Result<()> {
    anyhow::ensure!(
        s.is_finite() && s >= 0.0,
        "--heartbeat-timeout-s {s}: expected a non-negative number of seconds"
    );
    Ok(())
}

fn run_cmd(args: RunArgs) -> anyhow::Result<()> {
    let site = params::load(&args.site)?;
    markhold::feasibility::warn_site(&site, None);
    for w in markhold::calibrate::site_warnings(&site, true) {
        tracing::warn!("{}: {w}", args.site.display());
    }
    check_heartbeat_timeout(args.heartbeat_timeout_s)?;
    let stop = markhold::field::signal::install()?;
    let opts = markhold::field::run::RunOptions {
        link_url: args.link.clone(),
        camera: args.camera.clone(),
        record: args.record.clone(),
        foxglove_port: args.foxglove.then_some(args.foxglove_port),
        heartbeat_timeout_s: args.heartbeat_timeout_s,
        arm: args.arm,
        max_seconds: args.seconds,
        pace_frames: !args.no_pace,
        trace: args.trace.clone(),
        frames_dir: args.record_frames.clone(),
        frames_every: args.record_frames_every.max(1),
        engage: args.engage,
        preflight: !args.no_preflight,
        web: args.web.clone(),
        foxglove_bind: args.foxglove_bind,
    };
    let report = markhold::field::run::run_live(&site, &opts, &stop)?;
    markhold::outln!(
        "markhold run: {} frames, marker in {}, {:.1} s of camera time, stopped by {:?}",
        report.frames,
        report.detected,
        report.loop_seconds,
        report.stopped_by
    );
    if report.frames_passed_over > 0 {
        markhold::outln!(
            "  {} camera frames passed over: the loop was slower than the camera and acted on the newest",
            report.frames_passed_over
        );
    }
    if let Some(e) = &report.record_error {
        eprintln!("markhold: the recording is incomplete: {e}");
    }
    if let Some(path) = &args.summary {
        markhold::write_summary(path, &report)?;
    }
    if report.stopped_by == markhold::field::run::StopReason::CameraLost {
        // The vehicle was left as the site says; the run itself failed.
        eprintln!("markhold run: stopped because the camera gave no frames (camera.stall_exit_s)");
        std::process::exit(1);
    }
    Ok(())
}

fn preflight_cmd(args: PreflightArgs) -> anyhow::Result<()> {
    let site = params::load(&args.site)?;
    check_heartbeat_timeout(args.heartbeat_timeout_s)?;
    let stop = markhold::field::signal::install()?;
    let list = markhold::field::preflight::preflight(
        &site,
        args.link.as_deref(),
        args.heartbeat_timeout_s,
        &stop,
    )?;
    print!("{}", list.render());
    if let Some(path) = &args.summary {
        markhold::write_summary(path, &list)?;
    }
    if list.failed() > 0 {
        // The vehicle is not ready; the tool itself worked.
        std::process::exit(1);
    }
    Ok(())
}
