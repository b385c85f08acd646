//! Physics of the HIL vehicle: one 400 Hz step of our rapier3d vehicle beside a naive
//! textbook integrator of the same Fossen model (dense 6x6 mass matrix inverted every
//! step, heap-allocated matrices), in the same run; plus one camera frame of physics
//! (400 Hz / 30 fps = 13-14 steps with the autopilot's efforts and the mixer) and one full
//! HIL rig frame at 1440x1080 (physics + MAVLink poll + render).

#![allow(clippy::unwrap_used)] // A benchmark's setup fails loudly when broken, by design.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use markhold_exposure::{Camera, Frame, ResponseModel};
use markhold_hil::camera::CameraModel;
use markhold_hil::scene::{LightingConfig, LightingScenario, MarkerSpec, WaterConfig};
use markhold_hil::vehicle::{Hydrodynamics, GRAVITY_MPS2};
use markhold_hil::{
    EndpointConfig, HilRig, HilSetup, Mixer, ThrusterConfig, Vehicle, VehicleConfig, VehicleMotion,
};
use nalgebra::{
    DMatrix, DVector, Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3,
};

/// The textbook way: eta' = J(eta) nu, M nu' = tau - D(nu) nu - g(eta), M dense 6x6 with
/// the CG coupling terms, inverted every step, explicit Euler, fresh matrices each step.
struct NaiveFossen {
    h: Hydrodynamics,
    mixer: Mixer,
    thr: ThrusterConfig,
    thrust: [f64; 8],
    eta: DVector<f64>,
    nu: DVector<f64>,
}

impl NaiveFossen {
    fn new(frame: markhold_hil::Frame6Dof) -> Self {
        let mut eta = DVector::zeros(6);
        eta[2] = 5.0;
        Self {
            h: Hydrodynamics::for_frame(frame),
            mixer: Mixer::new(frame),
            thr: ThrusterConfig::default(),
            thrust: [0.0; 8],
            eta,
            nu: DVector::zeros(6),
        }
    }

    fn step(&mut self, pwm: &[u16; 8], dt: f64) {
        let h = &self.h;
        for (i, t) in self.thrust.iter_mut().enumerate() {
            let target = self.thr.steady_thrust_n(pwm[i] as f64, 14.8);
            *t += (1.0 - (-dt / self.thr.time_constant_s).exp()) * (target - *t);
        }
        let (f, m) = self.mixer.wrench(&self.thrust);
        let mut mass = DMatrix::<f64>::zeros(6, 6);
        for i in 0..3 {
            mass[(i, i)] = h.mass_kg + h.added_mass[i];
            mass[(i + 3, i + 3)] = h.inertia_kgm2[i] + h.added_mass[i + 3];
        }
        let mass_inv = mass
            .clone()
            .try_inverse()
            .unwrap_or_else(|| DMatrix::identity(6, 6));
        let (phi, theta, psi) = (self.eta[3], self.eta[4], self.eta[5]);
        let r = Rotation3::from_euler_angles(phi, theta, psi);
        let w = Vector3::new(0.0, 0.0, h.mass_kg * GRAVITY_MPS2);
        let b = Vector3::new(0.0, 0.0, -h.buoyancy_n);
        let fb = r.inverse() * (w + b);
        let mb = Vector3::from(h.cb_from_cg_m).cross(&(r.inverse() * b));
        let mut tau = DVector::<f64>::zeros(6);
        for i in 0..3 {
            tau[i] = f[i] + fb[i];
            tau[i + 3] = m[i] + mb[i];
        }
        let mut d = DMatrix::<f64>::zeros(6, 6);
        for i in 0..6 {
            d[(i, i)] = h.damping_linear[i] + h.damping_quadratic[i] * self.nu[i].abs();
        }
        let acc = &mass_inv * (tau - &d * &self.nu);
        self.nu += acc * dt;
        // Kinematics: J(eta) with the Euler-rate transform.
        let (sp, cp) = phi.sin_cos();
        let (tt, ct) = (theta.tan(), theta.cos().max(1e-6));
        let t_rate = Matrix3::new(1.0, sp * tt, cp * tt, 0.0, cp, -sp, 0.0, sp / ct, cp / ct);
        let v = r * Vector3::new(self.nu[0], self.nu[1], self.nu[2]);
        let e = t_rate * Vector3::new(self.nu[3], self.nu[4], self.nu[5]);
        for i in 0..3 {
            self.eta[i] += v[i] * dt;
            self.eta[i + 3] += e[i] * dt;
        }
    }
}

fn physics_step(c: &mut Criterion) {
    let mut g = c.benchmark_group("physics_step");
    let cfg = VehicleConfig::default();
    let start = Isometry3::translation(0.0, 0.0, 5.0);
    let pwm = [1300, 1300, 1700, 1700, 1550, 1550, 1450, 1450];
    let mut v = Vehicle::new(&cfg, &start, 1).unwrap();
    g.bench_function("rapier_vehicle", |b| {
        b.iter(|| v.step(std::hint::black_box(&pwm)))
    });
    let mut n = NaiveFossen::new(cfg.frame);
    let dt = cfg.dt_s();
    g.bench_function("naive_dense_fossen", |b| {
        b.iter(|| n.step(std::hint::black_box(&pwm), dt))
    });
    g.finish();
}

fn rot(cols: [[f64; 3]; 3]) -> UnitQuaternion<f64> {
    let m = Matrix3::from_columns(&cols.map(Vector3::from));
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m))
}

fn setup(camera: CameraModel) -> HilSetup {
    let cells = 6;
    let white = (0..cells * cells)
        .map(|k| {
            let (i, j) = (k % cells, k / cells);
            i > 0 && j > 0 && i < cells - 1 && j < cells - 1 && (i * 5 + j * 3) % 4 < 2
        })
        .collect();
    HilSetup {
        vehicle: VehicleConfig::default(),
        endpoint: EndpointConfig::default(),
        water: WaterConfig::default(),
        lighting: LightingConfig::default(),
        camera,
        t_vehicle_cam: Isometry3::from_parts(
            Translation3::new(0.2, 0.0, 0.0),
            rot([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
        ),
        marker: MarkerSpec {
            cells,
            white,
            size_m: 0.15,
            plate_margin_m: 0.03,
        },
        t_world_marker: Isometry3::from_parts(
            Translation3::new(0.0, 0.0, 5.0),
            rot([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]]),
        ),
        map: Vec::new(),
        t_world_vehicle_start: Isometry3::translation(-1.0, 0.0, 5.0),
        motion: VehicleMotion::Free,
        seed: 1,
        lock_step: false,
    }
}

fn rig_frame(c: &mut Criterion) {
    let mut g = c.benchmark_group("rig_frame");
    for (w, h) in [(160u32, 120u32), (1440, 1080)] {
        let mut cam = CameraModel::blackfly_s(ResponseModel::default());
        let s = w as f64 / 1440.0;
        cam.width = w;
        cam.height = h;
        cam.fx *= s;
        cam.fy *= s;
        cam.cx = (w as f64 - 1.0) / 2.0;
        cam.cy = (h as f64 - 1.0) / 2.0;
        let scenarios: &[LightingScenario] = if w == 1440 {
            &LightingScenario::ALL
        } else {
            &[LightingScenario::Normal]
        };
        for &sc in scenarios {
            let mut s = setup(cam.clone());
            s.lighting = LightingConfig {
                scenario: sc,
                ..LightingConfig::default()
            };
            let mut rig = HilRig::new(s).unwrap();
            let mut f = Frame::default();
            g.throughput(Throughput::Elements(w as u64 * h as u64));
            g.bench_with_input(
                BenchmarkId::new("physics_and_render", format!("{w}x{h}/{sc}")),
                &(),
                |b, _| b.iter(|| rig.grab(&mut f).unwrap()),
            );
        }
    }
    g.finish();
}

criterion_group!(benches, physics_step, rig_frame);
criterion_main!(benches);
