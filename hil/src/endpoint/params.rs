//! The parameters of the simulated ArduSub, with ArduSub 4.5's defaults, and the reader of
//! a vehicle's parameter file (QGroundControl `.params` or MAVProxy `.parm`).
//!
//! Defaults and ranges, each from ArduSub 4.5's source: ArduSub/Parameters.cpp
//! (`GSCALAR` defaults and `@Range`), ArduSub/config.h (ACRO_YAW_P 3.375,
//! PILOT_VELZ_MAX 500, PILOT_SPEED_DEFAULT 200, PILOT_ACCEL_Z_DEFAULT 100, THR_DZ_DEFAULT
//! 100, DEFAULT_ANGLE_MAX 4500, FS_GCS_TIMEOUT_S 5, SURFACE_DEPTH_DEFAULT -10),
//! ArduSub/radio.cpp (`default_dead_zones`: RC1..RC3_DZ 30, RC4_DZ 40), Parameters.h's
//! defaults table (ATC_RATE_Y_MAX 180, ATC_ACCEL_Y_MAX 110000), libraries/AP_Motors/
//! AP_Motors6DOF.cpp (MOT_FV_CPLNG_K 1.0), libraries/RC_Channel/RC_Channels_VarInfo.h
//! (RC_OVERRIDE_TIME 3), libraries/AC_WPNav/AC_WPNav.cpp (WPNAV_SPEED_UP 250).

use std::path::Path;

use markhold_config::ConfigError;

/// ArduSub's parameters the simulated autopilot reads (ArduSub units: cm, cdeg, us).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArduSubParams {
    /// ACRO_YAW_P: yaw rate per unit of yaw stick (control_in -4500..4500 to cdeg/s).
    pub acro_yaw_p: f64,
    /// ANGLE_MAX: the largest lean angle, centidegrees.
    pub angle_max_cdeg: f64,
    /// PILOT_SPEED_UP: climb rate at full throttle stick (ALT_HOLD, POSHOLD), cm/s.
    pub pilot_speed_up_cms: f64,
    /// PILOT_SPEED_DN: descent rate at full stick, cm/s; 0 = PILOT_SPEED_UP.
    pub pilot_speed_dn_cms: f64,
    /// PILOT_SPEED: horizontal speed at full forward / lateral stick in POSHOLD, cm/s.
    pub pilot_speed_cms: f64,
    /// PILOT_ACCEL_Z: acceleration of the pilot's velocity targets, cm/s/s.
    pub pilot_accel_z_cmss: f64,
    /// THR_DZ: the climb-rate dead band about centre throttle (x the joystick gain).
    pub thr_dz: f64,
    /// RC1_DZ .. RC4_DZ (pitch, roll, throttle, yaw input dead zones), us.
    pub rc_dz_us: [u16; 4],
    /// JS_GAIN_DEFAULT: the joystick gain at boot.
    pub js_gain_default: f64,
    /// JS_THR_GAIN: the throttle's extra gain.
    pub js_thr_gain: f64,
    /// FS_PILOT_INPUT: 0 disabled, 1 warn only, 2 disarm.
    pub fs_pilot_input: u8,
    /// FS_PILOT_TIMEOUT, seconds.
    pub fs_pilot_timeout_s: f64,
    /// FS_GCS_ENABLE: 0 disabled, 1 warn only, 2 disarm, 3 depth hold (POSHOLD with a
    /// position), 4 surface.
    pub fs_gcs_enable: u8,
    /// FS_GCS_TIMEOUT, seconds.
    pub fs_gcs_timeout_s: f64,
    /// RC_OVERRIDE_TIME: an RC override is used this long after it was sent, seconds.
    pub rc_override_time_s: f64,
    /// MOT_FV_CPLNG_K: forward/vertical decoupling of the 6-thruster frame.
    pub mot_fv_cplng_k: f64,
    /// SURFACE_DEPTH: the depth reading at which the vehicle is at the surface, cm (<= 0).
    pub surface_depth_cm: f64,
    /// WPNAV_SPEED_UP: SURFACE mode's climb rate, cm/s.
    pub wpnav_speed_up_cms: f64,
    /// ATC_RATE_Y_MAX: the largest yaw rate the attitude controller asks for, deg/s.
    pub atc_rate_y_max_dps: f64,
    /// ATC_ACCEL_Y_MAX: the largest yaw acceleration of its targets, cdeg/s/s.
    pub atc_accel_y_max_cdss: f64,
}

impl Default for ArduSubParams {
    fn default() -> Self {
        Self {
            acro_yaw_p: 3.375,
            angle_max_cdeg: 4500.0,
            pilot_speed_up_cms: 500.0,
            pilot_speed_dn_cms: 0.0,
            pilot_speed_cms: 200.0,
            pilot_accel_z_cmss: 100.0,
            thr_dz: 100.0,
            rc_dz_us: [30, 30, 30, 40],
            js_gain_default: 0.5,
            js_thr_gain: 1.0,
            fs_pilot_input: 2,
            fs_pilot_timeout_s: 3.0,
            fs_gcs_enable: 2,
            fs_gcs_timeout_s: 5.0,
            rc_override_time_s: 3.0,
            mot_fv_cplng_k: 1.0,
            surface_depth_cm: -10.0,
            wpnav_speed_up_cms: 250.0,
            atc_rate_y_max_dps: 180.0,
            atc_accel_y_max_cdss: 110_000.0,
        }
    }
}

/// One known parameter: its name, the values accepted, and where it goes.
struct Known {
    name: &'static str,
    lo: f64,
    hi: f64,
    integer: bool,
    set: fn(&mut ArduSubParams, f64),
}

/// The parameters read from a file, with the ranges accepted: ArduSub's `@Range` where it
/// gives one, else the range its code constrains to.
#[rustfmt::skip]
const KNOWN: [Known; 23] = [
    Known { name: "ACRO_YAW_P", lo: 1.0, hi: 10.0, integer: false, set: |p, v| p.acro_yaw_p = v },
    Known { name: "ANGLE_MAX", lo: 1000.0, hi: 8000.0, integer: false, set: |p, v| p.angle_max_cdeg = v },
    Known { name: "PILOT_SPEED_UP", lo: 20.0, hi: 500.0, integer: false, set: |p, v| p.pilot_speed_up_cms = v },
    Known { name: "PILOT_SPEED_DN", lo: 0.0, hi: 500.0, integer: false, set: |p, v| p.pilot_speed_dn_cms = v },
    Known { name: "PILOT_SPEED", lo: 10.0, hi: 500.0, integer: false, set: |p, v| p.pilot_speed_cms = v },
    Known { name: "PILOT_ACCEL_Z", lo: 50.0, hi: 500.0, integer: false, set: |p, v| p.pilot_accel_z_cmss = v },
    Known { name: "THR_DZ", lo: 0.0, hi: 400.0, integer: true, set: |p, v| p.thr_dz = v },
    Known { name: "RC1_DZ", lo: 0.0, hi: 200.0, integer: true, set: |p, v| p.rc_dz_us[0] = v as u16 },
    Known { name: "RC2_DZ", lo: 0.0, hi: 200.0, integer: true, set: |p, v| p.rc_dz_us[1] = v as u16 },
    Known { name: "RC3_DZ", lo: 0.0, hi: 200.0, integer: true, set: |p, v| p.rc_dz_us[2] = v as u16 },
    Known { name: "RC4_DZ", lo: 0.0, hi: 200.0, integer: true, set: |p, v| p.rc_dz_us[3] = v as u16 },
    Known { name: "JS_GAIN_DEFAULT", lo: 0.1, hi: 1.0, integer: false, set: |p, v| p.js_gain_default = v },
    Known { name: "JS_THR_GAIN", lo: 0.5, hi: 4.0, integer: false, set: |p, v| p.js_thr_gain = v },
    Known { name: "FS_PILOT_INPUT", lo: 0.0, hi: 2.0, integer: true, set: |p, v| p.fs_pilot_input = v as u8 },
    Known { name: "FS_PILOT_TIMEOUT", lo: 0.1, hi: 3.0, integer: false, set: |p, v| p.fs_pilot_timeout_s = v },
    Known { name: "FS_GCS_ENABLE", lo: 0.0, hi: 4.0, integer: true, set: |p, v| p.fs_gcs_enable = v as u8 },
    Known { name: "FS_GCS_TIMEOUT", lo: 0.1, hi: 120.0, integer: false, set: |p, v| p.fs_gcs_timeout_s = v },
    Known { name: "RC_OVERRIDE_TIME", lo: 0.0, hi: 120.0, integer: false, set: |p, v| p.rc_override_time_s = v },
    Known { name: "MOT_FV_CPLNG_K", lo: 0.0, hi: 1.5, integer: false, set: |p, v| p.mot_fv_cplng_k = v },
    Known { name: "SURFACE_DEPTH", lo: -100.0, hi: 0.0, integer: false, set: |p, v| p.surface_depth_cm = v },
    Known { name: "WPNAV_SPEED_UP", lo: 10.0, hi: 1000.0, integer: false, set: |p, v| p.wpnav_speed_up_cms = v },
    Known { name: "ATC_RATE_Y_MAX", lo: 1.0, hi: 1080.0, integer: false, set: |p, v| p.atc_rate_y_max_dps = v },
    Known { name: "ATC_ACCEL_Y_MAX", lo: 0.0, hi: 180_000.0, integer: false, set: |p, v| p.atc_accel_y_max_cdss = v },
];

/// Parameter files larger than this are refused (a full ArduSub dump is about 40 kB).
const MAX_FILE_BYTES: u64 = 4 << 20;

impl ArduSubParams {
    /// Speed the pilot may ask downward, cm/s (`Sub::get_pilot_speed_dn`).
    pub fn pilot_speed_dn(&self) -> f64 {
        if self.pilot_speed_dn_cms == 0.0 {
            self.pilot_speed_up_cms.abs()
        } else {
            self.pilot_speed_dn_cms.abs()
        }
    }

    /// Every value against the range a file may give it (`vehicle.params` in errors).
    pub fn validate(&self) -> Result<(), ConfigError> {
        for k in &KNOWN {
            let v = self.get(k.name).unwrap_or(f64::NAN);
            check(k, v).map_err(|expected| {
                ConfigError::new(format!("vehicle.params.{}", k.name), v, expected)
            })?;
        }
        Ok(())
    }

    /// The value of parameter `name` (one of the known ones).
    pub fn get(&self, name: &str) -> Option<f64> {
        Some(match name {
            "ACRO_YAW_P" => self.acro_yaw_p,
            "ANGLE_MAX" => self.angle_max_cdeg,
            "PILOT_SPEED_UP" => self.pilot_speed_up_cms,
            "PILOT_SPEED_DN" => self.pilot_speed_dn_cms,
            "PILOT_SPEED" => self.pilot_speed_cms,
            "PILOT_ACCEL_Z" => self.pilot_accel_z_cmss,
            "THR_DZ" => self.thr_dz,
            "RC1_DZ" => f64::from(self.rc_dz_us[0]),
            "RC2_DZ" => f64::from(self.rc_dz_us[1]),
            "RC3_DZ" => f64::from(self.rc_dz_us[2]),
            "RC4_DZ" => f64::from(self.rc_dz_us[3]),
            "JS_GAIN_DEFAULT" => self.js_gain_default,
            "JS_THR_GAIN" => self.js_thr_gain,
            "FS_PILOT_INPUT" => f64::from(self.fs_pilot_input),
            "FS_PILOT_TIMEOUT" => self.fs_pilot_timeout_s,
            "FS_GCS_ENABLE" => f64::from(self.fs_gcs_enable),
            "FS_GCS_TIMEOUT" => self.fs_gcs_timeout_s,
            "RC_OVERRIDE_TIME" => self.rc_override_time_s,
            "MOT_FV_CPLNG_K" => self.mot_fv_cplng_k,
            "SURFACE_DEPTH" => self.surface_depth_cm,
            "WPNAV_SPEED_UP" => self.wpnav_speed_up_cms,
            "ATC_RATE_Y_MAX" => self.atc_rate_y_max_dps,
            "ATC_ACCEL_Y_MAX" => self.atc_accel_y_max_cdss,
            _ => return None,
        })
    }

    /// ArduSub 4.5's defaults with the values of the parameter file at `path`.
    pub fn read(path: &Path) -> Result<Self, ConfigError> {
        let key = "vehicle.params_file";
        let unreadable = |e: std::io::Error| {
            ConfigError::new(
                key,
                path.display(),
                format!("a readable parameter file ({e})"),
            )
        };
        let mut file = markhold_config::open_regular(path, MAX_FILE_BYTES).map_err(unreadable)?;
        let mut text = String::new();
        std::io::Read::read_to_string(&mut file, &mut text).map_err(unreadable)?;
        Self::parse(&text).map_err(|e| {
            let line = e.line.unwrap_or(0);
            e.at(path, line)
        })
    }

    /// ArduSub 4.5's defaults with the values of a parameter file's text: QGroundControl
    /// (`vehicle<TAB>component<TAB>NAME<TAB>value<TAB>type`) or MAVProxy (`NAME value`,
    /// separated by spaces, tabs or a comma). `#` starts a comment; unknown names are
    /// ignored; a known name with a value outside its range is an error naming the line.
    pub fn parse(text: &str) -> Result<Self, ConfigError> {
        let mut p = Self::default();
        for (i, raw) in text.lines().enumerate() {
            let line_no = i + 1;
            let line = raw.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let fields: Vec<&str> = if line.contains('\t') && line.split('\t').count() >= 4 {
                line.split('\t').map(str::trim).collect()
            } else {
                line.split(|c: char| c == ',' || c.is_whitespace())
                    .filter(|s| !s.is_empty())
                    .collect()
            };
            let (name, value) = match fields.as_slice() {
                // QGroundControl: vehicle, component, name, value, type.
                [sys, comp, name, value, ..]
                    if sys.parse::<u8>().is_ok() && comp.parse::<u8>().is_ok() =>
                {
                    (*name, *value)
                }
                [name, value] => (*name, *value),
                _ => {
                    return Err(ConfigError::new(
                        "vehicle.params_file",
                        raw.trim(),
                        "NAME VALUE (MAVProxy) or vehicle, component, NAME, value, type \
                         separated by tabs (QGroundControl)",
                    )
                    .on_line(line_no));
                }
            };
            let Some(k) = KNOWN.iter().find(|k| k.name == name) else {
                continue;
            };
            let located =
                |expected: String| ConfigError::new(name, value, expected).on_line(line_no);
            let v: f64 = value.parse().map_err(|_| located("a number".to_string()))?;
            check(k, v).map_err(located)?;
            (k.set)(&mut p, v);
        }
        Ok(p)
    }
}

/// A parse error's line (the file is added by [`ArduSubParams::read`]).
trait OnLine {
    fn on_line(self, line: usize) -> Self;
}

impl OnLine for ConfigError {
    fn on_line(mut self, line: usize) -> Self {
        self.line = Some(line);
        self
    }
}

fn check(k: &Known, v: f64) -> Result<(), String> {
    let whole = !k.integer || v.fract() == 0.0;
    if v.is_finite() && (k.lo..=k.hi).contains(&v) && whole {
        Ok(())
    } else {
        let kind = if k.integer {
            "a whole number"
        } else {
            "a number"
        };
        Err(format!("{kind} in {}..={}", k.lo, k.hi))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_file_formats_set_known_names_and_ignore_the_rest() {
        let qgc = "# Onboard parameters for Vehicle 1\n#\n# MAV ID  COMPONENT ID  PARAM NAME  VALUE (FLOAT) TYPE\n\
                   1\t1\tACRO_YAW_P\t1.6875\t9\n1\t1\tSOME_OTHER\t7\t2\n1\t1\tTHR_DZ\t80\t4\n";
        let p = ArduSubParams::parse(qgc).unwrap();
        assert_eq!((p.acro_yaw_p, p.thr_dz), (1.6875, 80.0));
        let parm = "PILOT_SPEED_UP 250  # halved\nRC4_DZ,20\nFRAME_CONFIG 2\n\n";
        let p = ArduSubParams::parse(parm).unwrap();
        assert_eq!((p.pilot_speed_up_cms, p.rc_dz_us[3]), (250.0, 20));
        assert_eq!(p.acro_yaw_p, ArduSubParams::default().acro_yaw_p);
        ArduSubParams::default().validate().unwrap();
    }

    #[test]
    fn a_bad_value_names_the_line_the_name_and_the_value() {
        let e = ArduSubParams::parse("ACRO_YAW_P 3\nANGLE_MAX 9000\n").unwrap_err();
        assert_eq!(e.line, Some(2));
        let s = e.to_string();
        assert!(
            s.contains("ANGLE_MAX = 9000") && s.contains("1000..=8000"),
            "{s}"
        );
        let e = ArduSubParams::parse("THR_DZ 10.5\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("whole number"), "{e}");
        let e = ArduSubParams::parse("PILOT_SPEED x\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("PILOT_SPEED = x"), "{e}");
        let e = ArduSubParams::parse("just-one-field\n").unwrap_err();
        assert_eq!(e.line, Some(1));
    }

    #[test]
    fn reading_a_file_puts_its_path_in_the_error() {
        let dir = std::env::temp_dir().join(format!("markhold-params-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("bad.parm");
        std::fs::write(&f, "# vehicle\nMOT_FV_CPLNG_K 2\n").unwrap();
        let e = ArduSubParams::read(&f).unwrap_err().to_string();
        assert!(
            e.starts_with(&format!("{}:2: MOT_FV_CPLNG_K = 2", f.display())),
            "{e}"
        );
        let e = ArduSubParams::read(&dir.join("missing.parm"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("vehicle.params_file"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
