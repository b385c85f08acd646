//! The simulator's commands: `hil` (the loop against the simulated world, or the
//! simulated camera on an external vehicle) and `sitl` (ArduPilot's JSON physics).

use crate::error::{ensure, FileContext, SimError, StepContext};
use std::path::PathBuf;

use markhold_exposure::ExposureMethod;
use markhold_hil::camera::RenderLoops;
use markhold_hil::scene::LightingScenario;

use super::external::run_external;
use super::hil::{open_recorder, run_hil, HilOptions};
use super::summary::Summary;
use markhold_core::observe::{Progress, Snapshots, TraceWriter};
use markhold_core::params;
use markhold_core::pipeline::Observers;
use markhold_core::record::{RecordConfig, Recorder};

#[derive(clap::Args)]
pub struct SitlArgs {
    /// Dive-site file (the vehicle and its start pose come from it).
    #[arg(long, default_value = "params/pool.toml")]
    pub site: PathBuf,
    /// UDP port ArduPilot sends servo packets to (9002, +10 per extra instance).
    #[arg(long, default_value_t = 9002)]
    pub port: u16,
    /// Address to bind: loopback unless ArduPilot runs on another machine.
    #[arg(long, default_value = "127.0.0.1")]
    pub bind: std::net::IpAddr,
    /// Seed of the gusts and waves.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Stop after this many servo packets (default: serve until killed).
    #[arg(long)]
    pub max_packets: Option<u64>,
    /// With --max-packets: stop after this many wall seconds at most.
    #[arg(long, default_value_t = 60.0)]
    pub max_seconds: f64,
}

#[derive(clap::Args)]
pub struct HilArgs {
    /// Dive-site file.
    #[arg(long, default_value = "params/pool.toml")]
    pub site: PathBuf,
    /// Simulated seconds to run.
    #[arg(long, default_value_t = 60.0)]
    pub seconds: f64,
    /// Seed of the simulated world (noise, texture, gusts, caustics).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Write a JSON summary here.
    #[arg(long)]
    pub summary: Option<PathBuf>,
    #[arg(long, help = format!(
        "Exposure method: {} (overrides the site file)",
        ExposureMethod::names(", ", " or ")
    ))]
    pub exposure: Option<ExposureMethod>,
    /// Lighting scenario: normal, low, adversarial or caustics (overrides the site file).
    #[arg(long)]
    pub lighting: Option<LightingScenario>,
    /// Exposure at start, microseconds (overrides the site file).
    #[arg(long)]
    pub initial_exposure_us: Option<f64>,
    /// Save frames as PNG into this folder.
    #[arg(long)]
    pub snapshot: Option<PathBuf>,
    /// With --snapshot: save every n-th frame.
    #[arg(long, default_value_t = 30)]
    pub snapshot_every: u64,
    /// After the run, write its plots into this folder (created if missing), PNG and SVG:
    /// trajectory (top and side view, marker frame, ground truth), exposure and metric,
    /// detection and loop latency over time.
    #[arg(long, value_name = "DIR")]
    pub plots: Option<PathBuf>,
    /// Write one CSV row per frame (time, exposure, metric, detection, pose, effort).
    #[arg(long, value_name = "FILE.csv")]
    pub trace: Option<PathBuf>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// Camera-in-the-loop on an external MAVLink vehicle (e.g. ArduSub SITL:
    /// tcp:127.0.0.1:5762, the SITL port MAVProxy leaves free): its telemetry places the
    /// camera, markhold controls it.
    #[arg(long, value_name = "MAVLINK_URL")]
    pub vehicle: Option<String>,
    /// Inject a fault on simulation time, repeatable: KIND@START[+DURATION] seconds, KIND
    /// one of link_cut, occlude, out_of_view, drop_frames, late_frames, exposure_ignored,
    /// exposure_late, lamp_off, ambient_step (e.g. --fault link_cut@10+3 --fault occlude@20+0.5).
    /// occlude covers the origin marker; occlude:ID covers marker ID of the site's map
    /// (e.g. --fault occlude:2@20+5).
    #[arg(long = "fault", value_name = "KIND[:ID]@START[+DURATION]")]
    pub faults: Vec<super::faults::FaultSpec>,
    /// Record the run to this MCAP file (must not exist): frames, exposure, detections,
    /// pose, commands, vehicle state, failsafe events; `markhold replay` reads it.
    #[arg(long, value_name = "FILE.mcap")]
    pub record: Option<PathBuf>,
    /// Serve a Foxglove WebSocket live view (the same channels as --record; browser pages
    /// only from the site's [live] allowed_origins).
    #[arg(long)]
    pub foxglove: bool,
    /// Port of the live view (0: any free port).
    #[arg(long, default_value_t = 8765)]
    pub foxglove_port: u16,
    /// Address the live view listens on (0.0.0.0: every address).
    #[arg(long, value_name = "IP", default_value = "127.0.0.1")]
    pub foxglove_bind: std::net::IpAddr,
    #[command(flatten)]
    pub web: markhold_core::web::WebArgs,
    /// The renderer's loops: portable, avx2 or avx512 (the widest this CPU runs up to
    /// that; default: the widest). Every build renders the same frames, so the run is
    /// the same; only the world's speed differs (the summary says which ran).
    #[arg(long, value_name = "BUILD")]
    pub render_loops: Option<RenderLoops>,
    /// How the camera reaches the loop: in-process, or h264-rtp (H.264 encoded with
    /// GStreamer into RTP on loopback UDP, received by the same stream camera as `run`,
    /// exposure through a loopback camera-manager REST API).
    #[arg(long, value_name = "TRANSPORT", default_value = "in-process")]
    pub camera_transport: crate::stream::CameraTransport,
    /// The simulated camera's exposure actuation delay, frames (0..=8; default: the
    /// site's camera.actuation_delay_frames).
    #[arg(long, value_name = "N")]
    pub camera_delay_frames: Option<u32>,
}

pub fn sitl(args: SitlArgs) -> Result<(), SimError> {
    let site = params::load(&args.site)?;
    let cfg = markhold_hil::SitlConfig {
        bind_ip: args.bind,
        port: args.port,
    };
    if let Err(e) = cfg.validate() {
        return Err(SimError::Usage {
            reason: format!("--port {}: {e}", args.port),
        });
    }
    // The vehicle starts on station, in front of the marker.
    let start = site.t_world_marker() * site.site.station.t_marker_vehicle();
    let mut server = markhold_hil::SitlServer::bind(&cfg, &site.site.vehicle, &start, args.seed)
        .step(|| {
            format!(
                "binding the SITL JSON server on {}:{}",
                args.bind, args.port
            )
        })?;
    let addr = server.local_addr()?;
    eprintln!(
        "markhold sitl: ArduPilot JSON physics for site {} on udp {addr}\n  {}",
        site.site.site.name,
        sim_vehicle_hint(addr)
    );
    match args.max_packets {
        Some(n) => {
            let stats = server.run_bounded(
                n,
                std::time::Duration::from_secs_f64(args.max_seconds.clamp(0.0, 86_400.0)),
            )?;
            markhold_core::outln!(
                "markhold sitl: {} packets, {} replies, {} steps, {} repeated, {} resets, {} rejected",
                stats.packets, stats.replies, stats.steps, stats.repeated, stats.resets, stats.rejected
            );
        }
        None => server.run()?,
    }
    Ok(())
}

/// ArduPilot SITL's default JSON servo port (`SIM_OUT_PORT` in SITL_cmdline.cpp); each
/// instance `-I N` adds 10 * N to it, as to its MAVLink TCP port 5760.
const SITL_JSON_PORT: u16 = 9002;

/// The `sim_vehicle.py` line that sends servo packets to `addr`, the address the SITL
/// server bound. ArduPilot's JSON backend sends to `JSON:<ip>` (127.0.0.1 without one) on
/// port 9002 + 10 * instance; a port off that ladder is reached only by the SITL binary's
/// own `--sim-port-out`, passed through `-A`.
pub fn sim_vehicle_hint(addr: std::net::SocketAddr) -> String {
    let ip = addr.ip();
    let model = if ip.is_loopback() && ip.is_ipv4() {
        "--model JSON".to_string()
    } else if ip.is_unspecified() {
        "--model JSON (SITL on another machine: --model JSON:<this machine's address>)".to_string()
    } else {
        format!("--model JSON:{ip}")
    };
    let base = format!("sim_vehicle.py -v ArduSub -f vectored_6dof {model}");
    let port = addr.port();
    match port.checked_sub(SITL_JSON_PORT) {
        Some(d) if d % 10 == 0 => {
            let n = d / 10;
            let instance = if n == 0 {
                String::new()
            } else {
                format!(" -I {n}")
            };
            format!(
                "start ArduSub with: {base}{instance}\n  (instance {n} sends to port {port}; \
                 its MAVLink is on tcp:127.0.0.1:{})",
                5760 + u32::from(n) * 10
            )
        }
        _ => format!(
            "port {port} is not 9002 + 10 * N, so no instance number (-I N) reaches it; \
             start ArduSub with: {base} -A \"--sim-port-out {port}\"\n  \
             (or run markhold sitl --port 9002, or 9002 + 10 * N for instance N)"
        ),
    }
}

/// `markhold hil`: check the options, attach the observers asked for, run, report.
pub fn hil(args: HilArgs) -> Result<(), SimError> {
    let site = params::load(&args.site)?;
    let start = super::hil::start_in_marker(&site.site, site.site.vehicle.initial_offset_m);
    markhold_core::feasibility::warn_site(&site, Some(&start));
    super::hil::check_start(&site)?;
    ensure(
        args.seconds > 0.0 && args.seconds <= super::summary::MAX_SECONDS,
        || SimError::Usage {
            reason: format!(
                "--seconds {}: expected a positive number of simulated seconds, at most {} (a day)",
                args.seconds,
                super::summary::MAX_SECONDS
            ),
        },
    )?;
    if let Some(v) = args.initial_exposure_us {
        params::check_initial_exposure(&site.site, v)?;
    }
    ensure(args.record.is_none() || args.vehicle.is_none(), || {
        SimError::Usage {
            reason: "--record with --vehicle is not supported: \
                     record a simulated run, or use `markhold run`"
                .into(),
        }
    })?;
    ensure(!args.foxglove || args.vehicle.is_none(), || {
        SimError::Usage {
            reason: "--foxglove with --vehicle is not supported: \
                     watch a simulated run, or use `markhold run`"
                .into(),
        }
    })?;
    ensure(
        args.camera_transport == crate::stream::CameraTransport::InProcess
            || args.vehicle.is_none(),
        || SimError::Usage {
            reason: "--camera-transport h264-rtp with --vehicle is not supported: the stream \
                         carries the simulated camera"
                .into(),
        },
    )?;
    let opts = HilOptions {
        seconds: args.seconds,
        seed: args.seed,
        exposure: args.exposure,
        lighting: args.lighting,
        initial_exposure_us: args.initial_exposure_us,
        faults: args.faults.clone(),
        render_loops: args.render_loops,
        plots_dir: args.plots.clone(),
        // Ctrl-C / SIGTERM: neutral input, the recording finalized, exit 130.
        stop: Some(markhold_core::signal::install()?),
        camera_transport: args.camera_transport,
        camera_delay_frames: args.camera_delay_frames,
        ..HilOptions::default()
    };
    if let Some(dir) = &args.plots {
        std::fs::create_dir_all(dir).file("creating --plots", dir)?;
    }
    let observers = hil_observers(&args, &site, &opts)?;
    let summary = match &args.vehicle {
        Some(url) => run_external(&site, url, &opts, observers)?,
        None => run_hil(&site, &opts, observers)?,
    };
    print_table(&site.site.site.name, &summary);
    if let Some(path) = &args.summary {
        markhold_core::write_summary(path, &summary)?;
    }
    if summary.interrupted {
        eprintln!(
            "markhold: stopped by a signal after {:.1} simulated seconds",
            summary.sim_seconds
        );
        std::process::exit(markhold_core::signal::INTERRUPTED_EXIT);
    }
    Ok(())
}

/// The observers `hil`'s flags ask for, in the order they see a frame.
fn hil_observers(
    args: &HilArgs,
    site: &params::LoadedSite,
    opts: &HilOptions,
) -> Result<Observers, SimError> {
    let frames = (args.seconds * site.site.camera.fps).round() as u64;
    let mut list = Observers::new().with(Progress::new(frames, args.quiet));
    if let Some(p) = &args.trace {
        list.push(TraceWriter::create(p)?);
    }
    if let Some(dir) = &args.snapshot {
        list.push(Snapshots::create(dir, args.snapshot_every)?);
    }
    let mut recorder = match &args.record {
        Some(p) => Some(open_recorder(site, opts, p)?),
        // A live view alone: frames the viewer cannot keep up with are dropped, the loop
        // never waits for it.
        None if args.foxglove => Some(Recorder::live_only(RecordConfig::default())?),
        None => None,
    };
    let mut live = None;
    if let (true, Some(r)) = (args.foxglove, recorder.as_mut()) {
        let port = r
            .serve_live_on(args.foxglove_bind, args.foxglove_port, &site.site.live)
            .step(|| format!("--foxglove-port {}", args.foxglove_port))?;
        eprintln!(
            "markhold: Foxglove live view on ws://{}",
            std::net::SocketAddr::new(args.foxglove_bind, port)
        );
        live = Some(markhold_core::web::LiveInfo {
            port,
            loopback: args.foxglove_bind.is_loopback(),
        });
    }
    let control = recorder
        .as_ref()
        .filter(|_| args.record.is_some())
        .map(Recorder::control);
    if let Some(r) = recorder {
        list.push(r);
    }
    markhold_core::web::attach(site, &args.web, "hil", control, live, &mut list)?;
    Ok(list)
}

pub fn print_table(site: &str, s: &Summary) {
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
            "markers in the pose (mean)",
            format!("{:.2}", s.markers_in_view_mean),
        ),
        (
            "position RMS (last half)",
            format!("{:.3} m", s.position_rms_m),
        ),
        (
            "pose position RMS (last half)",
            format!("{:.4} m", s.pose_position_rms_m),
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
            "exposure first within 5 % after",
            format!("{} frames", s.exposure_first_within_frames),
        ),
        (
            "exposure stays within 5 % after",
            format!("{} frames", s.exposure_convergence_frames),
        ),
        ("final exposure", format!("{:.0} us", s.final_exposure_us)),
        (
            "loop latency p99",
            format!("{:.2} ms", s.loop_latency_p99_ms),
        ),
    ];
    markhold_core::outln!("markhold hil");
    let width = rows.iter().map(|(k, _)| k.len()).max().unwrap_or(0);
    for (k, v) in rows {
        markhold_core::outln!("  {k:<width$} {v}");
    }
    print_faults(&s.faults);
}

fn print_faults(faults: &[super::faults::FaultReport]) {
    let at = |v: Option<f64>| v.map_or("-".to_string(), |t| format!("{t:.2} s"));
    for f in faults {
        let end = f.end_s.map_or("end".to_string(), |t| format!("{t:.2} s"));
        markhold_core::outln!("  fault {} {:.2} s .. {end}", f.kind, f.start_s);
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
            markhold_core::outln!("    {k:<24} {v}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::sim_vehicle_hint;

    fn hint(addr: &str) -> String {
        sim_vehicle_hint(addr.parse().expect("a socket address"))
    }

    #[test]
    fn the_sitl_hint_reaches_the_port_and_address_bound() {
        let h = hint("127.0.0.1:9002");
        assert!(h.contains("--model JSON\n") && !h.contains("-I "), "{h}");
        let h = hint("127.0.0.1:19002");
        assert!(h.contains("--model JSON -I 1000"), "{h}");
        assert!(
            h.contains("port 19002") && h.contains("tcp:127.0.0.1:15760"),
            "{h}"
        );
        let h = hint("127.0.0.1:9012");
        assert!(
            h.contains(" -I 1\n") && h.contains("tcp:127.0.0.1:5770"),
            "{h}"
        );
        for off in ["127.0.0.1:9003", "127.0.0.1:8992", "127.0.0.1:40001"] {
            let h = hint(off);
            let port = off.rsplit(':').next().unwrap_or_default();
            assert!(h.contains("no instance number"), "{h}");
            assert!(h.contains(&format!("-A \"--sim-port-out {port}\"")), "{h}");
            assert!(!h.contains(" -I "), "{h}");
        }
        let h = hint("192.168.2.1:9022");
        assert!(h.contains("--model JSON:192.168.2.1 -I 2"), "{h}");
        let h = hint("0.0.0.0:9002");
        assert!(h.contains("JSON:<this machine's address>"), "{h}");
    }
}
