//! Each crate validates its own section; here their errors become (section, key, value,
//! expected) so the site loader can add the file and line.

use markhold_autopilot::AutopilotError;
use markhold_exposure::ExposureError;
use markhold_hil::HilError;
use markhold_vision::VisionError;

use crate::params::Site;

type Bad = (&'static str, String, String, String);

fn exposure(e: ExposureError) -> Bad {
    match e {
        ExposureError::InvalidConfig {
            key,
            value,
            expected,
        } => ("exposure", key, value, expected),
        other => (
            "exposure",
            "exposure".into(),
            String::new(),
            other.to_string(),
        ),
    }
}

fn hil(section: &'static str, e: HilError) -> Bad {
    match e {
        HilError::InvalidConfig {
            key,
            value,
            expected,
        } => (section, key, value, expected),
        other => (section, section.into(), String::new(), other.to_string()),
    }
}

fn vision(section: &'static str, e: VisionError) -> Bad {
    match e {
        VisionError::InvalidConfig {
            key,
            value,
            expected,
        } => (section, key, value, expected),
        other => (section, section.into(), String::new(), other.to_string()),
    }
}

fn autopilot(section: &'static str, e: AutopilotError) -> Bad {
    match e {
        AutopilotError::InvalidConfig { key, value, reason } => {
            // autopilot phrases it "must be ...": keep one style, "expected ...".
            let expected = reason.strip_prefix("must be ").unwrap_or(reason);
            (section, key, value, expected.to_string())
        }
        other => (section, section.into(), String::new(), other.to_string()),
    }
}

/// Validate every crate-owned section of a parsed site.
pub(crate) fn validate_sections(site: &Site) -> Result<(), Bad> {
    site.water.validate().map_err(|e| hil("water", e))?;
    site.lighting.validate().map_err(|e| hil("lighting", e))?;
    site.vehicle.validate().map_err(|e| hil("vehicle", e))?;
    site.camera
        .sensor
        .validate()
        .map_err(|e| hil("camera", e))?;
    site.marker.validate().map_err(|e| vision("marker", e))?;
    site.vision.validate().map_err(|e| vision("vision", e))?;
    site.exposure.validate().map_err(exposure)?;
    site.station
        .validate()
        .map_err(|e| autopilot("station", e))?;
    site.controller
        .validate()
        .map_err(|e| autopilot("controller", e))?;
    site.link.validate().map_err(|e| autopilot("link", e))?;
    Ok(())
}
