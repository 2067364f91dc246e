//! The fast 2D kernels against the safe reference walk ([`Walk2::dot`] / [`Walk2::axpy`] on the plain
//! image): random images, views at 0°, 45°, 90°, 135° and random angles, rays through the interior,
//! along the grid edges (grazing), through corners and just outside, on a non-square grid with
//! unequal pixel sizes. Tolerances: the scalar form is bit-identical to the walk (same f32 operations
//! in the same order); the AVX2 form has the same pairs and weights but sums 8 lanes with FMA, so its
//! dot products agree within 1e-6 × Σ|value·weight| and its single-ray back projections exactly.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::{Kernel, Segment};
use crate::recon::geometry::Ray2;
use crate::recon::grid::ImageGrid;
use crate::recon::projector::joseph2::Walk2;
use crate::recon::projector::padded2::{Layouts2, Needs};

fn grid() -> ImageGrid {
    ImageGrid {
        nx: 37,
        ny: 23,
        dx_mm: 1.0,
        dy_mm: 1.25,
        centre_mm: [0.5, -0.25],
    }
}

/// Rays at `deg` whose signed distance from the grid centre sweeps across the grid and just beyond,
/// including the distances of the grid's edges and corners (grazing rays).
fn rays(g: &ImageGrid, deg: f64, rng: &mut StdRng) -> Vec<Ray2> {
    let th = deg.to_radians();
    let dir = [th.cos(), th.sin()];
    let normal = [-th.sin(), th.cos()];
    let (hx, hy) = (g.nx as f64 * g.dx_mm / 2.0, g.ny as f64 * g.dy_mm / 2.0);
    let mut offsets: Vec<f64> = (-60..=60).map(|k| k as f64 * 0.37).collect();
    for (cx, cy) in [(hx, hy), (hx, -hy), (-hx, hy), (-hx, -hy)] {
        let d = cx * normal[0] + cy * normal[1];
        offsets.extend([d, d - 1e-6, d + 1e-6, d - 0.5, d + 0.5]);
    }
    offsets.extend([hx, -hx, hy, -hy, hx - 1e-9, -hy + 1e-9]);
    offsets.extend((0..20).map(|_| rng.random_range(-30.0..30.0)));
    offsets
        .into_iter()
        .map(|d| Ray2 {
            origin: [
                g.centre_mm[0] + d * normal[0] - 100.0 * dir[0],
                g.centre_mm[1] + d * normal[1] - 100.0 * dir[1],
            ],
            direction: dir,
        })
        .collect()
}

fn angles(rng: &mut StdRng) -> Vec<f64> {
    let mut a = vec![0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0];
    a.extend((0..12).map(|_| rng.random_range(0.0..360.0)));
    a
}

fn kernels() -> Vec<Kernel> {
    let mut k = vec![Kernel::Scalar];
    #[cfg(target_arch = "x86_64")]
    if super::super::joseph2_avx2::available() {
        k.push(Kernel::Avx2);
    }
    if !k.contains(&Kernel::Avx2) {
        println!("skipped: the AVX2 + FMA Joseph loops (this CPU lacks AVX2 or FMA)");
    }
    k
}

#[test]
fn forward_kernels_match_the_reference_walk() {
    let g = grid();
    let mut rng = StdRng::seed_from_u64(11);
    let image: Vec<f32> = (0..g.nx * g.ny).map(|_| rng.random::<f32>()).collect();
    let layouts = Layouts2::from_image(&image, g.nx, g.ny, Needs::BOTH);
    let mut checked = 0;
    for deg in angles(&mut rng) {
        for ray in rays(&g, deg, &mut rng) {
            let Some(w) = Walk2::new(&ray, &g) else {
                continue;
            };
            let reference = w.dot(&image);
            let mut scale = 0.0f32;
            w.visit(|p, wt| scale += (image[p] * wt).abs());
            let seg = Segment::of(&w);
            let lines = layouts.lines(w.along_x);
            for k in kernels() {
                let got = k.dot(&lines.data, lines.width, 0, &seg, w.start, w.end);
                match k {
                    Kernel::Scalar => assert_eq!(got, reference, "{deg}° {ray:?}"),
                    Kernel::Avx2 => assert!(
                        (got - reference).abs() <= 1e-6 * scale,
                        "{deg}° {ray:?}: {got} vs {reference}"
                    ),
                }
                // Split in two bands of lines, the second read from its own sub-slice.
                let mid = (w.start + w.end) / 2;
                let band = &lines.data[mid * lines.width..];
                let split = k.dot(&lines.data, lines.width, 0, &seg, w.start, mid)
                    + k.dot(band, lines.width, mid, &seg, mid, w.end);
                assert!((split - reference).abs() <= 1e-6 * scale.max(1e-30));
            }
            checked += 1;
        }
    }
    assert!(checked > 1000, "{checked} rays checked");
}

#[test]
fn back_kernels_match_the_reference_walk() {
    let g = grid();
    let mut rng = StdRng::seed_from_u64(12);
    let mut checked = 0;
    for deg in angles(&mut rng) {
        for ray in rays(&g, deg, &mut rng) {
            let Some(w) = Walk2::new(&ray, &g) else {
                continue;
            };
            let alpha = rng.random_range(-2.0f32..2.0);
            let mut reference = vec![0.0f32; g.nx * g.ny];
            w.axpy(alpha, &mut reference);
            let seg = Segment::of(&w);
            for k in kernels() {
                let mut acc = Layouts2::zeros(g.nx, g.ny, Needs::BOTH);
                let lines = if w.along_x {
                    &mut acc.cols
                } else {
                    &mut acc.rows
                };
                let width = lines.width;
                let mid = (w.start + 2 * w.end) / 3;
                k.axpy(&mut lines.data, width, 0, &seg, w.start, mid, alpha);
                k.axpy(
                    &mut lines.data[mid * width..],
                    width,
                    mid,
                    &seg,
                    mid,
                    w.end,
                    alpha,
                );
                let mut got = vec![f32::NAN; g.nx * g.ny];
                acc.sum_into(&mut got);
                assert_eq!(got, reference, "{k:?} {deg}° {ray:?}");
            }
            checked += 1;
        }
    }
    assert!(checked > 1000, "{checked} rays checked");
}

#[test]
fn lanes_without_a_pixel_add_nothing_even_for_infinite_values() {
    let g = grid();
    let mut image = vec![1.0f32; g.nx * g.ny];
    image[0] = f32::INFINITY;
    let layouts = Layouts2::from_image(&image, g.nx, g.ny, Needs::BOTH);
    // A horizontal ray along the top row never touches pixel [0][0], which sits at value 1 of the
    // column layout: the lanes past the ray's last sample that read it must not turn the sum to NaN.
    let ray = Ray2 {
        origin: [0.0, g.y(g.ny - 1)],
        direction: [1.0, 0.0],
    };
    let w = Walk2::new(&ray, &g).expect("hits");
    let seg = Segment::of(&w);
    let lines = layouts.lines(w.along_x);
    for k in kernels() {
        let got = k.dot(&lines.data, lines.width, 0, &seg, w.start, w.end);
        assert_eq!(got.is_finite(), w.dot(&image).is_finite(), "{k:?}");
    }
}

#[test]
#[should_panic(expected = "kernel range outside the lines")]
fn a_range_past_the_lines_is_refused() {
    let l = Layouts2::zeros(4, 4, Needs::BOTH);
    let seg = Segment {
        start: 0,
        end: 5,
        c0: 1.0,
        dc: 0.0,
        weight: 1.0,
    };
    Kernel::Scalar.dot(&l.rows.data, l.rows.width, 0, &seg, 0, 5);
}
