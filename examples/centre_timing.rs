//! Wall-clock time of the automatic centre search on a 2000-wide panel (issue 47 §4: under 2 s on 2
//! cores), and of the preprocessing steps per view.
//!
//! `cargo run --release --example centre_timing -- [runs]`. The scan: 1800 views over a full turn of a
//! 2000 × 1000 panel (0.1 mm pixels, DSO 200 mm, DSD 400 mm) of the 3D modified Shepp–Logan phantom, the
//! panel offset by 7.3 px and rolled by 0.4°. Only the views and rows the searches read are projected
//! (exactly, before timing); the source then copies them as a reader of decoded views would.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::Instant;

use ctrecon::recon::ReconError;
use ctrecon::recon::geometry::{Angles, ConeBeam, Panel, Views3};
use ctrecon::recon::phantom::{Phantom3, Table3};
use ctrecon::recon::prep::{
    CentreOptions, ConjugateOptions, Normalise, SortingStripeFilter, ViewSource, find_centre,
    find_centre_conjugate, roll_views,
};
use ndarray::{Array2, ArrayViewMut2, s};

/// Rows of views projected on first use and kept.
struct Lazy {
    views: Views3,
    phantom: Phantom3,
    cache: Mutex<HashMap<(usize, usize, usize), Array2<f32>>>,
}

impl ViewSource for Lazy {
    fn view_count(&self) -> usize {
        self.views.views.len()
    }
    fn read_view(&self, _: usize, _: ArrayViewMut2<'_, f32>) -> Result<(), ReconError> {
        Err(ReconError::param("view", "this source reads rows only"))
    }
    fn read_rows(
        &self,
        index: usize,
        first_row: usize,
        _nv: usize,
        mut out: ArrayViewMut2<'_, f32>,
    ) -> Result<(), ReconError> {
        let key = (index, first_row, out.nrows());
        if let Some(rows) = self
            .cache
            .lock()
            .map_err(|_| ReconError::Canceled)?
            .get(&key)
        {
            out.assign(rows);
            return Ok(());
        }
        // Project only these rows: a panel of the rows alone, shifted to where they lie.
        let det = self.views.detector;
        let rows = out.nrows();
        let mut one = Views3 {
            detector: det,
            views: vec![self.views.views[index]],
        };
        one.detector.nv = rows;
        let centre_row = first_row as f64 + (rows as f64 - 1.0) / 2.0;
        one.detector.offset_v_mm =
            (centre_row - (det.nv as f64 - 1.0) / 2.0) * det.dv_mm + det.offset_v_mm;
        let p = self.phantom.project(&one);
        out.assign(&p.slice(s![0, .., ..]));
        self.cache
            .lock()
            .map_err(|_| ReconError::Canceled)?
            .insert(key, out.to_owned());
        Ok(())
    }
}

fn main() -> Result<(), ReconError> {
    let runs: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(3);
    let du = 0.1;
    let cone = |offset_px: f64| ConeBeam {
        angles: Angles::uniform(1800, 360.0),
        dso_mm: 200.0,
        dsd_mm: 400.0,
        detector: Panel {
            nu: 2000,
            nv: 1000,
            du_mm: du,
            dv_mm: du,
            offset_u_mm: offset_px * du,
            offset_v_mm: 0.0,
        },
    };
    let mut truth = cone(7.3).to_views()?;
    roll_views(&mut truth, 0.4);
    let nominal = cone(0.0).to_views()?;
    let source = Lazy {
        views: truth,
        phantom: Phantom3::from_table(Table3::ModifiedSheppLogan, 40.0),
        cache: Mutex::new(HashMap::new()),
    };
    let threads = rayon::current_num_threads();
    let opts = CentreOptions::default();
    let copts = ConjugateOptions::default();
    // Warm-up: projects what the searches read.
    let t = Instant::now();
    find_centre(&nominal, &source, &opts)?;
    find_centre_conjugate(&nominal, 400.0, &source, &copts)?;
    println!(
        "simulation (not timed below): {:.1} s",
        t.elapsed().as_secs_f64()
    );
    for _ in 0..runs {
        let t = Instant::now();
        let e = find_centre(&nominal, &source, &opts)?;
        let a = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let c = find_centre_conjugate(&nominal, 400.0, &source, &copts)?;
        let b = t.elapsed().as_secs_f64();
        println!(
            "{threads} threads: opposite views {a:.3} s (offset {:.3} px, tilt {:.4}°, {} pairs); \
             conjugate rays {b:.3} s (offset {:.3} px, {} views)",
            e.offset_u_px,
            e.tilt_deg.unwrap_or(f64::NAN),
            e.views_used,
            c.offset_u_px,
            c.views_used
        );
    }
    // Per-view steps on one 2000 × 2000 view of uint16-like counts.
    let mut view = Array2::<f32>::from_shape_fn((2000, 2000), |(r, c)| {
        1000.0 + ((r * 7 + c * 13) % 500) as f32
    });
    let white = Normalise::WhiteLevel {
        white_level: 60000.0,
        floor_ratio: 1e-6,
    };
    let t = Instant::now();
    for _ in 0..10 {
        white.apply_view(None, 0, view.view_mut())?;
        view.mapv_inplace(|p| 1000.0 + p);
    }
    let per = t.elapsed().as_secs_f64() / 10.0;
    println!(
        "white-level normalisation (+ one pass to refill): {:.1} ms per 2000² view, {:.2} GB/s of uint16",
        per * 1e3,
        0.008 / per
    );
    let mut sino = Array2::<f32>::from_shape_fn((1800, 2000), |(k, c)| ((k * 3 + c) % 97) as f32);
    let t = Instant::now();
    SortingStripeFilter::default().apply(sino.view_mut())?;
    println!(
        "sorting stripe filter: {:.3} s per 1800 × 2000 sinogram",
        t.elapsed().as_secs_f64()
    );
    Ok(())
}
