//! The signing endpoint's per-message path allocates nothing after start-up: receiving
//! and verifying signed frames, rejecting unsigned ones, answering with signed frames.
//! Counted per thread by a wrapping global allocator.

use std::net::UdpSocket;
use std::time::Duration;

use markhold_hil::{EndpointConfig, Vehicle, VehicleConfig, VehicleEndpoint};
use markhold_testkit::thread_allocs as allocs;
use mavlink::dialects::ardupilotmega::*;
use mavlink::{MavHeader, SigningConfig, SigningData};
use nalgebra::Isometry3;

#[global_allocator]
static A: markhold_testkit::CountingAlloc = markhold_testkit::CountingAlloc;

#[test]
fn signed_receive_verify_and_send_allocate_nothing() {
    let key = [0x5a; 32];
    let path = std::env::temp_dir().join(format!("hil-alloc-key-{}", std::process::id()));
    std::fs::write(&path, key).unwrap();
    let mut ep = VehicleEndpoint::bind(&EndpointConfig {
        signing_key_file: Some(path.clone()),
        ..Default::default()
    })
    .unwrap();
    let vehicle = Vehicle::new(&VehicleConfig::default(), &Isometry3::identity(), 1).unwrap();
    let gcs = UdpSocket::bind("127.0.0.1:0").unwrap();
    gcs.set_read_timeout(Some(Duration::from_millis(5)))
        .unwrap();
    let signer = SigningData::from_config(SigningConfig::new(key, 1, true, false));
    let frame = |seq: u8, signed: bool| {
        let mut out = Vec::new();
        let h = MavHeader {
            system_id: 255,
            component_id: 190,
            sequence: seq,
        };
        let msg = MavMessage::RC_CHANNELS_OVERRIDE(RC_CHANNELS_OVERRIDE_DATA {
            chan5_raw: 1600,
            target_system: 1,
            target_component: 1,
            ..Default::default()
        });
        mavlink::write_v2_msg_signed(&mut out, h, &msg, signed.then_some(&signer)).unwrap();
        out
    };
    let state = vehicle.state();
    let pwm = [1500u16; 8];
    let mut buf = [0u8; 2048];
    let mut run = |k: u8, ep: &mut VehicleEndpoint| {
        // Frames are built before counting (the test's own Vecs).
        let (good, bad) = (frame(k, true), frame(k, false));
        let before = allocs();
        gcs.send_to(&good, ep.udp_addr()).unwrap();
        gcs.send_to(&bad, ep.udp_addr()).unwrap();
        ep.poll(f64::from(k) * 0.1).unwrap();
        ep.tick(&state, &pwm).unwrap();
        let n = allocs() - before;
        while gcs.recv_from(&mut buf).is_ok() {}
        n
    };
    // The counter sees this thread's allocations.
    let before = allocs();
    let v = std::hint::black_box(vec![1u8; 16]);
    assert!(allocs() > before && v.len() == 16);
    // Start-up: the first signed stream's timestamp entry, stream tables.
    for k in 0..5 {
        run(k, &mut ep);
    }
    let mut total = 0;
    for k in 5..105 {
        total += run(k, &mut ep);
    }
    let st = ep.stats();
    assert!(
        st.pilot_inputs >= 100 && st.rejected_unsigned >= 100,
        "{st:?}"
    );
    assert_eq!(total, 0, "allocations in 100 signed exchanges");
    std::fs::remove_file(&path).unwrap();
}
