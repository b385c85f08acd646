//! Which packed render loops the build host runs, as cfgs for the tests that compare them
//! with the portable loops (tests/camera_fast.rs): a test for loops this host lacks is
//! reported as ignored by the test runner instead of passing without its check.
fn main() {
    println!("cargo::rustc-check-cfg=cfg(build_host_avx2)");
    println!("cargo::rustc-check-cfg=cfg(build_host_avx512)");
    println!("cargo::rerun-if-changed=build.rs");
    #[cfg(target_arch = "x86_64")]
    {
        // The same features `Isa::best_up_to` checks at run time.
        let avx2 = std::arch::is_x86_feature_detected!("avx2");
        let avx512 = avx2
            && std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx512vl")
            && std::arch::is_x86_feature_detected!("avx512vbmi");
        let target_x86_64 = std::env::var("CARGO_CFG_TARGET_ARCH").is_ok_and(|a| a == "x86_64");
        if target_x86_64 && avx2 {
            println!("cargo::rustc-cfg=build_host_avx2");
        }
        if target_x86_64 && avx512 {
            println!("cargo::rustc-cfg=build_host_avx512");
        }
    }
}
