//! The seed's fan-beam experiment (examples/fan_seed.rs): PSNR rises as the arc sensors get finer, and at
//! 0.25° the RMSE against the slice is at most 0.06 (a MATLAB-style rebin-to-parallel reconstruction of
//! the same data reaches 0.069).

#[path = "../examples/fan_seed.rs"]
mod fan_seed;

#[test]
fn finer_sensor_spacing_raises_psnr_and_reaches_0_06_rmse_at_a_quarter_degree() {
    let results: Vec<(f64, f64, f64)> = [2.0, 1.0, 0.25]
        .into_iter()
        .map(|s| {
            let (p, e) = fan_seed::seed_experiment(s);
            println!("sensor spacing {s}°: PSNR {p:.2} dB, RMSE {e:.4}");
            (s, p, e)
        })
        .collect();
    assert!(results[1].1 > results[0].1, "{results:?}");
    assert!(results[2].1 > results[1].1, "{results:?}");
    assert!(results[2].2 <= 0.06, "RMSE at 0.25°: {}", results[2].2);
}
