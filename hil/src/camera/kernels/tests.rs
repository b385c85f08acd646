//! The kernels' tests: every packed build against the portable one, bit for bit.

use super::*;

/// Marsaglia's xorshift64 from `seed`: the tests' reproducible inputs.
fn xorshift(seed: u64) -> impl FnMut() -> u64 {
    let mut x = seed;
    move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x
    }
}

/// The two runs hold the same values, bit for bit.
fn same_bits(a: &[f32], b: &[f32]) -> bool {
    a.iter().zip(b).all(|(a, b)| a.to_bits() == b.to_bits())
}

/// The macro's parts tile the run as one read per pixel would: pixel `p` in span
/// `(first + p) / 16` at offset `(first + p) % 16`, up to the last span.
#[test]
fn span_parts_tile_the_run() {
    let cells = vec![[0f32; 6]; 12];
    let walks: Vec<i32> = (0..12).collect();
    let nodes = RockNodes {
        cells: &cells,
        fy: 0.0,
        walks: [&walks, &walks],
    };
    for first in [0usize, 1, 7, 15, 16, 17, 40, 170, 176, 200] {
        for len in [0usize, 1, 8, 15, 16, 17, 31, 32, 33, 100, 200] {
            let mut out = vec![0f32; len];
            // Each pixel records its span (the node walk at the span's start) + 1 and its
            // offset in the span, written through the part it was given.
            let mut seen = vec![(0i32, 0usize); len];
            let base = out.as_ptr() as usize;
            for_span_parts!(&mut out, first, &nodes, |o, t0, span| {
                let at = (o.as_ptr() as usize - base) / 4;
                for k in 0..o.len() {
                    seen[at + k] = (span.walks[0][0] + 1, t0 + k);
                }
            });
            for (p, &got) in seen.iter().enumerate() {
                let pos = first + p;
                let want = if pos / 16 < cells.len() - 1 {
                    (pos as i32 / 16 + 1, pos % 16)
                } else {
                    (0, 0)
                };
                assert_eq!(got, want, "first {first} len {len} pixel {p}");
            }
        }
    }
}

/// The packed sensor loops (AVX-512 16, AVX2 16, then 8 pixels a step, then one) give the portable
/// loop's levels at every row length, for a table and a computed linear response,
/// over means from below zero to past the full well.
#[test]
#[cfg_attr(
    not(build_host_avx2),
    ignore = "the build host has no AVX2: nothing packed"
)]
fn packed_sensor_matches_portable_at_every_length() {
    assert_ne!(
        Isa::detect(false),
        Isa::Portable,
        "this CPU runs no packed loops, though the build host did"
    );
    let mut lut = Box::new([0u8; super::super::sensor::RESPONSE_LUT_LEN]);
    let last = lut.len() - 1;
    for (i, l) in lut.iter_mut().enumerate() {
        *l = ((i * 255) / last) as u8 ^ (i as u8 & 3);
    }
    let mut next = xorshift(0x9E37_79B9_7F4A_7C15u64);
    let n = 70;
    let mean: Vec<f32> = (0..n).map(|_| (next() % 24_000) as f32 - 500.0).collect();
    let na: Vec<i16> = (0..n).map(|_| (next() % 8001) as i16 - 4000).collect();
    let nb: Vec<i16> = (0..n).map(|_| (next() % 8001) as i16 - 4000).collect();
    let linear = super::super::sensor::Linear {
        per_e: 255.0 * 4.0 / 20_000.0,
        full_well_e: 20_000.0,
    };
    for lin in [None, Some(linear)] {
        let s = SensorRow {
            read_var: 9.0,
            per_s: 4095.0 / 150.0,
            top: 4095.0,
            lut: &lut,
            linear: lin,
        };
        for len in 0..=n {
            let (m, a, b) = (&mean[..len], &na[..len], &nb[..len]);
            let mut portable = vec![0u8; len];
            sensor_run(Isa::Portable, &mut portable, m, [a, b], &s);
            for isa in [Isa::Avx2, Isa::Avx512].map(Isa::best_up_to) {
                let mut packed = vec![0u8; len];
                sensor_run(isa, &mut packed, m, [a, b], &s);
                let linear = lin.is_some();
                assert_eq!(packed, portable, "{isa:?} length {len}, linear {linear}");
            }
            assert!(portable.iter().any(|&v| v > 0) || len < 8, "length {len}");
        }
    }
}

/// Every packed rock loop gives the portable loop's values, with and without
/// caustics, over walks that fit the AVX-512 build's two-row windows and walks that
/// do not (too wide, three rows, across the texture's edge, past i32), at run
/// offsets that leave part spans.
#[test]
#[cfg_attr(
    not(build_host_avx2),
    ignore = "the build host has no AVX2: nothing packed"
)]
fn packed_rock_loops_match_portable_over_all_kinds_of_walks() {
    let mut next = xorshift(0x2545_F491_4F6C_DD1Du64);
    let log2 = 7;
    let n = 1usize << (2 * log2);
    let rock = Texture {
        log2,
        data: (0..n).map(|_| next() as u8).collect(),
        scale: 0.01,
        offset: 0.2,
    };
    let lit = LitTexture {
        log2,
        data: (0..n).map(|_| next() as u16).collect(),
        rock_scale: 0.01,
        rock_offset: 0.2,
        caustic_scale: 0.004,
        caustic_offset: 0.5,
    };
    let side = 1i32 << log2;
    let nodes = 40;
    let cells: Vec<[f32; 6]> = (0..nodes)
        .map(|_| std::array::from_fn(|_| (next() % 1000) as f32 * 0.37))
        .collect();
    let mut builds = Vec::new();
    for kind in 0..6 {
        // Texel steps a pixel (16.16) and a start for each kind of walk.
        let (su, sv, at_u, at_v): (i32, i32, i32, i32) = match kind {
            0 => (45_000, 1_500, 3 << 16, 7 << 16),     // fits a window
            1 => (-52_000, -2_000, 90 << 16, 40 << 16), // fits, walking back
            2 => (300_000, 100, 0, 0),                  // too wide
            3 => (20_000, 30_000, 0, 0),                // over three rows
            4 => (60_000, 0, (side - 5) << 16, 0),      // across the edge in u
            _ => (40_000, 0, i32::MAX - (2 << 16), 0),  // leaves i32
        };
        let wu: Vec<i32> = (0..nodes as i32)
            .map(|k| at_u.wrapping_add(su.wrapping_mul(16 * k)))
            .collect();
        let wv: Vec<i32> = (0..nodes as i32)
            .map(|k| at_v.wrapping_add(sv.wrapping_mul(16 * k)))
            .collect();
        let run = RockNodes {
            cells: &cells,
            fy: 0.3,
            walks: [&wu, &wv],
        };
        // The kinds meant to fit the windows do, the others do not.
        #[cfg(target_arch = "x86_64")]
        for width in [64, 32] {
            let (u, v) = (
                Walk {
                    at: wu[0],
                    step: su,
                },
                Walk {
                    at: wv[0],
                    step: sv,
                },
            );
            let fits = avx512::span_window(log2, u, v, width).is_some();
            assert_eq!(fits, kind < 2, "kind {kind} width {width}");
        }
        for c in [None, Some(&lit)] {
            for (first, len) in [(0usize, 16 * (nodes - 1)), (5, 300), (16, 17), (3, 9)] {
                let mut want = vec![0f32; len];
                rock_nodes_run(Isa::Portable, &mut want, first, &run, &rock, c);
                for isa in [Isa::Avx2, Isa::Avx512].map(Isa::best_up_to) {
                    let mut got = vec![0f32; len];
                    rock_nodes_run(isa, &mut got, first, &run, &rock, c);
                    let same = same_bits(&got, &want);
                    assert!(
                        same,
                        "{isa:?} kind {kind} caustic {} first {first}",
                        c.is_some()
                    );
                    builds.push(isa);
                }
            }
        }
    }
    assert!(builds.iter().any(|&b| b != Isa::Portable));
}

/// Every packed plate loop gives the portable loop's values, bit for bit: runs that
/// cross the whole table and its border on both sides (the clamped cells), at
/// lengths that leave 8-pixel and scalar tails, with and without caustics, for the
/// table as bits (with and without the AVX-512 row pairs) and as gathered cells.
#[test]
#[cfg_attr(
    not(build_host_avx2),
    ignore = "the build host has no AVX2: nothing packed"
)]
fn packed_plate_loops_match_portable_across_the_table_and_its_border() {
    let mut next = xorshift(0x9E37_79B9_7F4A_7C15u64);
    let (w, b) = (0.85f32, 0.05f32);
    let side = 10usize;
    let cells: Vec<f32> = (0..side * side)
        .map(|k| {
            let (c, r) = (k % side, k / side);
            let border = c == 0 || r == 0 || c == side - 1 || r == side - 1;
            if border || next().is_multiple_of(2) {
                w
            } else {
                b
            }
        })
        .collect();
    let rows = CellRows::new(&cells, side, w, b).expect("two albedos, 10 x 10");
    assert!(rows.pairs.is_some());
    let no_pairs = CellRows {
        pairs: None,
        ..rows
    };
    let log2 = 6;
    let lit = LitTexture {
        log2,
        data: (0..1usize << (2 * log2)).map(|_| next() as u16).collect(),
        rock_scale: 0.01,
        rock_offset: 0.2,
        caustic_scale: 0.004,
        caustic_offset: 0.5,
    };
    let caustic = PlateCaustics {
        tex: &lit,
        strength: 0.6,
        texels_per_m: 600.0,
    };
    let mut compared = 0;
    for (k, table) in [Some(&rows), Some(&no_pairs), None].into_iter().enumerate() {
        for c in [None, Some(caustic)] {
            // Rows from above the plate to below it, each from left of it to right.
            for row in 0..7 {
                let v = -0.12 + 0.04 * row as f32;
                let r = PlateRun {
                    d: Ramp {
                        at: 1.0,
                        step: 2e-4,
                    },
                    nu: Ramp {
                        at: -0.13,
                        step: 0.26 / 97.0,
                    },
                    nv: Ramp { at: v, step: 1e-4 },
                    half_marker: 0.06,
                    cell_per_m: (side - 2) as f32 / 0.12,
                    inv_wu: 1.0 / 0.04,
                    inv_wv: 1.0 / 0.05,
                    cells: &cells,
                    side: side as i32,
                    rows: table,
                    caustic: c,
                    ambient: Ramp {
                        at: 30.0,
                        step: 0.1,
                    },
                    lamp: Ramp {
                        at: 5.0,
                        step: -0.02,
                    },
                    add: Ramp {
                        at: 2.0,
                        step: 0.01,
                    },
                };
                for (first, len) in [(0usize, 97usize), (3, 40), (16, 16), (5, 7), (0, 0)] {
                    let mut want = vec![0f32; len];
                    plate_run(Isa::Portable, &mut want, first, &r);
                    for isa in [Isa::Avx2, Isa::Avx512].map(Isa::best_up_to) {
                        let mut got = vec![0f32; len];
                        plate_run(isa, &mut got, first, &r);
                        let same = same_bits(&got, &want);
                        assert!(
                            same,
                            "{isa:?} table {k} caustic {} row {row} first {first}",
                            c.is_some()
                        );
                        compared += 1;
                    }
                    // Rows over the printed cells see both albedos: the comparison means something.
                    if len == 97 {
                        let (lo, hi) = want
                            .iter()
                            .fold((f32::MAX, f32::MIN), |(l, h), &m| (l.min(m), h.max(m)));
                        assert!(
                            hi > 2.0 * lo || !(2..=4).contains(&row),
                            "row {row}: {lo}..{hi}"
                        );
                    }
                }
            }
        }
    }
    assert!(compared > 0);
}

#[test]
fn cell_rows_hold_the_table_as_bits_or_decline() {
    let (w, b) = (0.85f32, 0.05f32);
    let side = 10;
    let cells: Vec<f32> = (0..side * side)
        .map(|k| if (k * 7 + k / 3) % 3 == 0 { w } else { b })
        .collect();
    let rows = CellRows::new(&cells, side, w, b).expect("a 10 x 10 table of two albedos");
    for (k, &v) in cells.iter().enumerate() {
        let bit = rows.bits[k / side] >> (k % side) & 1;
        assert_eq!(bit == 1, v == w, "cell {k}");
    }
    // Too large for two registers of eight rows, or a third value: the gathers.
    let big = vec![w; 17 * 17];
    assert!(CellRows::new(&big, 17, w, b).is_none());
    let mut odd = cells.clone();
    odd[37] = 0.5;
    assert!(CellRows::new(&odd, side, w, b).is_none());
    assert!(CellRows::new(&cells[1..], side, w, b).is_none());
}
