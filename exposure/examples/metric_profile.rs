//! Time (min over batches) of one metric evaluation on a noisy 300x300 RoI; under
//! `valgrind --tool=cachegrind` with REPS=1 and REPS=3 the difference / 10 is the
//! instruction count of one evaluation, a figure that does not depend on machine load.
use markhold_exposure::*;
use std::time::Instant;
fn main() {
    let (w, h) = (300usize, 300usize);
    let mut data = vec![0u8; w * h];
    for y in 0..h {
        for x in 0..w {
            let inside = (25..275).contains(&x) && (25..275).contains(&y);
            let cell = inside.then(|| ((x / 42) * 7 + (y / 42) * 3) % 2 == 1);
            data[y * w + x] = markhold_testkit::synthetic_grey(x, y, cell);
        }
    }
    let v = ImageView::new(w, h, &data).expect("the buffer holds w * h pixels");
    let mut gm = GradientMetric::new(&Response::linear(), AaecConfig::default().metric_params());
    let reps: usize = std::env::var("REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(300);
    let mut best = f64::MAX;
    let mut acc = 0.0;
    for _ in 0..reps {
        let t = Instant::now();
        for _ in 0..5 {
            acc += gm
                .evaluate(v)
                .expect("a 300x300 view is large enough for the metric")
                .m;
        }
        best = best.min(t.elapsed().as_secs_f64() * 1e6 / 5.0);
    }
    println!("evaluate min {best:.1} us ({acc})");
}
