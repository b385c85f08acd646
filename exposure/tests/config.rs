//! The `[exposure]` section: parsing, defaults, validation messages.
use markhold_exposure::*;

#[test]
fn full_section_parses_and_builds_every_method() {
    let text = r#"
        method = "aaec"
        [default]
        target_grey = 110.0
        [aaec]
        percentile = 0.8
        fallback = "aec"
        lost_hold_frames = 10
        [aec]
        rate = 0.3
        [gec]
        kp = 0.4
    "#;
    let mut cfg: ExposureConfig = toml::from_str(text).unwrap();
    // The response comes from the site's [camera] section, not from [exposure].
    assert_eq!(cfg.response, ResponseModel::Linear);
    cfg.response = ResponseModel::Gamma { gamma: 2.2 };
    assert_eq!(cfg.aaec.percentile, 0.8);
    assert_eq!(cfg.aaec.fallback, AaecFallback::Aec);
    assert_eq!(cfg.aec.rate, 0.3);
    assert_eq!(cfg.gec.kp, 0.4);
    assert_eq!(cfg.response, ResponseModel::Gamma { gamma: 2.2 });
    let limits = ExposureLimits {
        min_us: 10.0,
        max_us: 20_000.0,
        fps: 30.0,
    };
    for m in ExposureMethod::ALL {
        let c = build_controller(&cfg, m, limits, 1000.0).unwrap();
        assert_eq!(c.method(), m);
        assert_eq!(c.commanded_us(), 1000.0);
    }
    // An empty section is the defaults.
    let d: ExposureConfig = toml::from_str("").unwrap();
    assert_eq!(d, ExposureConfig::default());
}

#[test]
fn unknown_keys_are_rejected() {
    for text in [
        "[aaec]\nlearning_rat = 0.1",
        "[aec]\nratee = 1.0",
        "[gec]\nkpp = 1.0",
        "response = { model = \"gamma\", gamma = 2.2, extra = 1 }",
        "response = { model = \"spline\" }",
    ] {
        assert!(toml::from_str::<ExposureConfig>(text).is_err(), "{text}");
    }
}

#[test]
#[allow(clippy::too_many_lines)] // A flat list of cases, one per key.
fn bad_values_name_the_key() {
    let limits = ExposureLimits {
        min_us: 10.0,
        max_us: 20_000.0,
        fps: 30.0,
    };
    let cases: Vec<(ExposureConfig, &str)> = vec![
        (
            ExposureConfig {
                aaec: AaecConfig {
                    percentile: 1.5,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.aaec.percentile = 1.5",
        ),
        (
            ExposureConfig {
                aaec: AaecConfig {
                    weight_power: 4,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.aaec.weight_power = 4",
        ),
        (
            ExposureConfig {
                aaec: AaecConfig {
                    max_ratio_per_frame: 1.0,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.aaec.max_ratio_per_frame",
        ),
        (
            ExposureConfig {
                aaec: AaecConfig {
                    knee_quantile: 1.0,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.aaec.knee_quantile = 1",
        ),
        (
            ExposureConfig {
                aaec: AaecConfig {
                    knee_margin: 0.9,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.aaec.knee_margin = 0.9",
        ),
        (
            ExposureConfig {
                aaec: AaecConfig {
                    knee_hold_z: 0.0,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.aaec.knee_hold_z = 0",
        ),
        (
            ExposureConfig {
                aaec: AaecConfig {
                    knee_hold_slope: 0.1,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.aaec.knee_hold_slope = 0.1",
        ),
        (
            ExposureConfig {
                aaec: AaecConfig {
                    sweep_ratio: 1.0,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.aaec.sweep_ratio = 1",
        ),
        (
            ExposureConfig {
                aaec: AaecConfig {
                    sweep_dwell_frames: 0,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.aaec.sweep_dwell_frames = 0",
        ),
        (
            ExposureConfig {
                aaec: AaecConfig {
                    sweep_span: 1.5,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.aaec.sweep_span = 1.5",
        ),
        (
            ExposureConfig {
                aec: AecConfig {
                    max_change_frac: 0.0,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.aec.max_change_frac = 0",
        ),
        (
            ExposureConfig {
                aec: AecConfig {
                    mean_high_grey: 50.0,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.aec.mean_high_grey = 50",
        ),
        (
            ExposureConfig {
                gec: GecConfig {
                    delta: 1.5,
                    ..Default::default()
                },
                ..Default::default()
            },
            "exposure.gec.delta = 1.5",
        ),
        (
            ExposureConfig {
                response: ResponseModel::Gamma { gamma: -1.0 },
                ..Default::default()
            },
            "camera.response.gamma = -1",
        ),
    ];
    for (cfg, want) in cases {
        let e = build_controller(&cfg, ExposureMethod::Aaec, limits, 1000.0)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains(want), "{e} should contain {want}");
    }
    // A missing table file is named in the error.
    let cfg = ExposureConfig {
        response: ResponseModel::Table {
            file: "/nonexistent/crf.txt".into(),
        },
        ..Default::default()
    };
    let e = build_controller(&cfg, ExposureMethod::Aec, limits, 1000.0)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("/nonexistent/crf.txt"), "{e}");
}
