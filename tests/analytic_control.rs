//! Cancel, progress and bad input of the analytic algorithms, through `fbp_2d`/`fdk` and the dispatcher
//! `reconstruct`: typed errors before any large allocation, nothing panics.

use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use ctrecon::recon::algorithm::{AlgorithmSpec, FbpParams, OutputGrid, reconstruct};
use ctrecon::recon::analytic::{fbp_2d, fdk};
use ctrecon::recon::control::{Cancel, Control, NoProgress, unattended};
use ctrecon::recon::error::{GeometryError, ReconError};
use ctrecon::recon::geometry::{
    Angles, ConeBeam, FanBeam, FanDetector, Geometry, Panel, ParallelBeam, Views,
};
use ctrecon::recon::grid::{ImageGrid, Limits, VolumeGrid};
use ndarray::{Array2, Array3, ArrayD, IxDyn};

fn parallel(count: usize, range: f64) -> Geometry {
    Geometry::Parallel(ParallelBeam {
        angles: Angles::uniform(count, range),
        det_count: 64,
        det_spacing_mm: 1.0,
        det_offset_mm: 0.0,
    })
}

fn cone() -> Geometry {
    Geometry::Cone(ConeBeam {
        angles: Angles::uniform(36, 360.0),
        dso_mm: 300.0,
        dsd_mm: 600.0,
        detector: Panel {
            nu: 32,
            nv: 16,
            du_mm: 2.0,
            dv_mm: 2.0,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    })
}

fn run(
    geometry: &Geometry,
    data: ArrayD<f32>,
    grid: OutputGrid,
    limits: Limits,
) -> Result<ArrayD<f32>, ReconError> {
    let views = geometry.to_views()?;
    reconstruct(
        &AlgorithmSpec::Fbp(FbpParams::default()),
        &views,
        data.view(),
        &grid,
        &limits,
        unattended(),
    )
}

fn image(n: usize) -> OutputGrid {
    OutputGrid::Image(ImageGrid::square(n, 1.0))
}

#[test]
fn a_canceled_flag_stops_fbp_and_fdk_with_canceled() {
    let cancel = Cancel::new();
    cancel.cancel();
    let ctl = Control::new(&cancel, &NoProgress);
    let Ok(Views::D2(v2)) = parallel(90, 180.0).to_views() else {
        panic!("parallel views")
    };
    let sino = Array2::<f32>::ones((90, 64));
    let grid = ImageGrid::square(32, 1.0);
    let r = fbp_2d(&v2, sino.view(), &grid, &FbpParams::default(), ctl);
    assert_eq!(r.unwrap_err(), ReconError::Canceled);
    let Ok(Views::D3(v3)) = cone().to_views() else {
        panic!("cone views")
    };
    let proj = Array3::<f32>::ones((36, 16, 32));
    let r = fdk(
        &v3,
        proj.view(),
        &VolumeGrid::cube(16, 1.0),
        &FbpParams::default(),
        ctl,
    );
    assert_eq!(r.unwrap_err(), ReconError::Canceled);
}

#[test]
fn cancelling_midway_stops_fdk_and_progress_is_reported_per_view() {
    let cancel = Cancel::new();
    let reports = AtomicUsize::new(0);
    let progress = |stage: &str, fraction: f64, _: Option<usize>, _: Option<f64>| {
        if stage == "fdk" && fraction > 0.2 {
            cancel.cancel();
        }
        reports.fetch_add(1, Ordering::Relaxed);
    };
    let Ok(Views::D3(v3)) = cone().to_views() else {
        panic!("cone views")
    };
    let proj = Array3::<f32>::ones((36, 16, 32));
    let ctl = Control::new(&cancel, &progress);
    let r = fdk(
        &v3,
        proj.view(),
        &VolumeGrid::cube(16, 1.0),
        &FbpParams::default(),
        ctl,
    );
    assert_eq!(r.unwrap_err(), ReconError::Canceled);
    assert!(reports.load(Ordering::Relaxed) < 36, "stopped early");

    // Uncancelled, the filter stage reports once per view (plus its start).
    let fractions = Mutex::new(Vec::new());
    let record = |stage: &str, fraction: f64, _: Option<usize>, _: Option<f64>| {
        if stage == "filter" {
            fractions.lock().unwrap().push(fraction);
        }
    };
    let fresh = Cancel::new();
    let Ok(Views::D2(v2)) = parallel(90, 180.0).to_views() else {
        panic!("parallel views")
    };
    let sino = Array2::<f32>::ones((90, 64));
    let grid = ImageGrid::square(32, 1.0);
    fbp_2d(
        &v2,
        sino.view(),
        &grid,
        &FbpParams::default(),
        Control::new(&fresh, &record),
    )
    .unwrap();
    let f = fractions.into_inner().unwrap();
    assert_eq!(f.len(), 91);
    assert!((f.iter().cloned().fold(0.0, f64::max) - 1.0).abs() < 1e-12);
}

#[test]
fn mismatched_shapes_and_non_finite_values_are_typed_errors() {
    let g = parallel(90, 180.0);
    let wrong = ArrayD::<f32>::zeros(IxDyn(&[90, 63]));
    assert!(matches!(
        run(&g, wrong, image(32), Limits::default()),
        Err(ReconError::ShapeMismatch { .. })
    ));
    let mut nan = ArrayD::<f32>::zeros(IxDyn(&[90, 64]));
    nan[[3, 5]] = f32::NAN;
    assert_eq!(
        run(&g, nan, image(32), Limits::default()).unwrap_err(),
        ReconError::NonFinite { index: 3 * 64 + 5 }
    );
    let ok = ArrayD::<f32>::zeros(IxDyn(&[90, 64]));
    assert!(matches!(
        run(&cone(), ok.clone(), image(32), Limits::default()),
        Err(ReconError::ShapeMismatch { .. })
    ));
    // A 2D geometry with a volume grid.
    let vol = OutputGrid::Volume(VolumeGrid::cube(8, 1.0));
    assert!(matches!(
        run(&g, ok, vol, Limits::default()),
        Err(ReconError::InvalidParameter { name: "grid", .. })
    ));
}

#[test]
fn zero_negative_and_absurd_sizes_are_refused_before_allocating() {
    let g = parallel(90, 180.0);
    let data = || ArrayD::<f32>::zeros(IxDyn(&[90, 64]));
    let zero = OutputGrid::Image(ImageGrid {
        nx: 0,
        ..ImageGrid::square(32, 1.0)
    });
    assert!(matches!(
        run(&g, data(), zero, Limits::default()),
        Err(ReconError::Geometry(GeometryError::Zero { .. }))
    ));
    let negative = OutputGrid::Image(ImageGrid::square(32, -1.0));
    assert!(matches!(
        run(&g, data(), negative, Limits::default()),
        Err(ReconError::Geometry(GeometryError::NonPositive { .. }))
    ));
    // 30000² pixels need 3.6 GB: over a 1 GB limit, refused before anything is allocated.
    let huge = OutputGrid::Image(ImageGrid::square(30_000, 0.01));
    let limits = Limits { max_bytes: 1 << 30 };
    assert!(matches!(
        run(&g, data(), huge, limits),
        Err(ReconError::TooLarge { .. })
    ));
    // A 32768³ volume exceeds the default 8 GiB limit.
    let cube = OutputGrid::Volume(VolumeGrid::cube(32_768, 0.01));
    let proj = ArrayD::<f32>::zeros(IxDyn(&[36, 16, 32]));
    assert!(matches!(
        run(&cone(), proj, cube, Limits::default()),
        Err(ReconError::TooLarge { .. })
    ));
    // An absurd padding is refused as a parameter.
    let views = g.to_views().unwrap();
    let spec = AlgorithmSpec::Fbp(FbpParams {
        padded_len: Some(usize::MAX),
        ..FbpParams::default()
    });
    let r = reconstruct(
        &spec,
        &views,
        data().view(),
        &image(32),
        &Limits::default(),
        unattended(),
    );
    assert!(matches!(
        r,
        Err(ReconError::InvalidParameter {
            name: "padded_len",
            ..
        })
    ));
}

#[test]
fn unsupported_scans_are_typed_errors_never_silently_wrong_images() {
    // Parallel beam over 120°.
    let short = parallel(60, 120.0);
    let data = ArrayD::<f32>::zeros(IxDyn(&[60, 64]));
    assert!(matches!(
        run(&short, data, image(32), Limits::default()),
        Err(ReconError::InvalidParameter {
            name: "geometry",
            ..
        })
    ));
    // A fan beam over 200° with a ±20° fan: less than π + fan angle.
    let fan = |degrees: Vec<f64>, offset_deg: f64| {
        Geometry::Fan(FanBeam {
            angles: Angles::List { degrees },
            dso_mm: 300.0,
            dsd_mm: 600.0,
            detector: FanDetector::Arc {
                count: 80,
                spacing_deg: 0.5,
                offset_deg,
            },
            centre_mm: [0.0, 0.0],
        })
    };
    let degrees: Vec<f64> = (0..200).map(|k| k as f64).collect();
    let data = ArrayD::<f32>::zeros(IxDyn(&[200, 80]));
    assert!(matches!(
        run(&fan(degrees, 0.0), data, image(32), Limits::default()),
        Err(ReconError::Geometry(
            GeometryError::ShortScanTooShort { .. }
        ))
    ));
    // A short scan with an offset detector.
    let degrees: Vec<f64> = (0..=230).map(|k| k as f64).collect();
    let data = ArrayD::<f32>::zeros(IxDyn(&[231, 80]));
    assert!(matches!(
        run(&fan(degrees, 8.0), data, image(32), Limits::default()),
        Err(ReconError::InvalidParameter {
            name: "geometry",
            ..
        })
    ));
    // Two turns.
    let degrees: Vec<f64> = (0..720).map(|k| k as f64).collect();
    let data = ArrayD::<f32>::zeros(IxDyn(&[720, 80]));
    assert!(matches!(
        run(&fan(degrees, 0.0), data, image(32), Limits::default()),
        Err(ReconError::InvalidParameter {
            name: "geometry",
            ..
        })
    ));
}
