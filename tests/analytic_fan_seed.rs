//! The seed's fan-beam experiment (examples/fan_seed.rs): PSNR rises as the arc sensors get finer, and at
//! 0.25° the RMSE against the slice is at most 0.06 (a MATLAB-style rebin-to-parallel reconstruction of
//! the same data reaches 0.069). Both the MATLAB-style pixel-driven projection of the seed and ctrecon's
//! Joseph projector (`projector::forward_2d`) are checked.

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

#[test]
fn with_the_joseph_projector_finer_sensor_spacing_also_raises_psnr_and_reaches_0_06() {
    let joseph: Vec<(f64, f64)> = [2.0, 1.0, 0.25]
        .into_iter()
        .map(|s| fan_seed::seed_experiment_with(s, fan_seed::Projector::Joseph))
        .collect();
    println!("Joseph projector: {joseph:?}");
    assert!(
        joseph[1].0 > joseph[0].0 && joseph[2].0 > joseph[1].0,
        "{joseph:?}"
    );
}
