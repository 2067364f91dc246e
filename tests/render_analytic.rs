//! The renderer against pictures known in closed form: silhouettes, face-on shading, first-hit depths,
//! compositing of semi-transparent slabs, cut-away caps and the named views' screen directions.

use ctrecon::render::{
    Camera, Clip, ClipPlane, ControlPoint, NamedView, Projection, RgbImage, Scene, Shading,
    SsdOptions, Surface, TransferFunction, VrOptions, surface_render, volume_render,
};
use ctrecon::volume::{Frame, Volume};
use ndarray::Array3;

/// `n³` voxels of `spacing` mm centred on the origin holding `f(p)` at each voxel's patient position `p`.
fn field(n: usize, spacing: f64, f: impl Fn([f64; 3]) -> f64) -> Volume {
    let h = (n as f64 - 1.0) / 2.0 * spacing;
    let frame = Frame {
        spacing_mm: [spacing; 3],
        origin_mm: [-h, -h, -h],
        direction: Frame::AXIS_ALIGNED,
    };
    let data = Array3::from_shape_fn((n, n, n), |(k, j, i)| {
        f(frame.position(k as f64, j as f64, i as f64)) as f32
    });
    Volume { data, frame }
}

fn len(p: [f64; 3]) -> f64 {
    (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
}

/// A ball of radius `r` (mm) as a signed distance ×100, clamped to ±1000 (inside positive): iso 0 is the sphere.
fn ball(n: usize, spacing: f64, r: f64) -> Volume {
    field(n, spacing, |p| {
        ((r - len(p)) * 100.0).clamp(-1000.0, 1000.0)
    })
}

fn ssd(iso: f64) -> SsdOptions {
    SsdOptions {
        surfaces: vec![Surface {
            iso,
            color: [1.0, 1.0, 1.0],
            opacity: 1.0,
        }],
        shading: Shading::default(),
        depth_cue: 0.0,
        clip: Clip::default(),
        background: [0.0; 3],
        step_mm: None,
    }
}

fn hits(img: &RgbImage) -> usize {
    img.depth_mm.iter().filter(|d| d.is_finite()).count()
}

#[test]
fn a_spheres_orthographic_silhouette_is_a_disc_of_its_radius_in_pixels() {
    let vol = ball(64, 1.0, 20.0);
    let scene = Scene::new(&vol).unwrap();
    for view in NamedView::ALL {
        let cam = Camera {
            view,
            zoom: 1.5,
            ..Camera::default()
        };
        let rays = cam
            .rays(&vol.frame, vol.data.dim(), 160, 160, 4096)
            .unwrap();
        let img = surface_render(&scene, &rays, &ssd(0.0)).unwrap();
        let r_px = (hits(&img) as f64 / std::f64::consts::PI).sqrt();
        let want = 20.0 / rays.pixel;
        assert!(
            (r_px - want).abs() < 0.01 * want,
            "{view:?}: disc radius {r_px:.3} px, want {want:.3} px"
        );
    }
}

#[test]
fn the_first_hit_lies_at_the_analytic_distance_within_half_a_voxel() {
    let vol = ball(64, 1.0, 20.0);
    let scene = Scene::new(&vol).unwrap();
    let cam = Camera {
        distance_mm: Some(100.0),
        ..Camera::default()
    };
    let rays = cam.rays(&vol.frame, vol.data.dim(), 96, 96, 4096).unwrap();
    let img = surface_render(&scene, &rays, &ssd(0.0)).unwrap();
    let mut worst: f64 = 0.0;
    let mut n = 0;
    for r in 0..96 {
        for c in 0..96 {
            let (o, _) = rays.ray(r as f64, c as f64);
            let rho = (o[0] * o[0] + o[2] * o[2]).sqrt();
            if rho < 0.95 * 20.0 {
                let want = 100.0 - (400.0f64 - rho * rho).sqrt();
                worst = worst.max((img.depth(r, c) as f64 - want).abs());
                n += 1;
            }
        }
    }
    assert!(n > 700, "{n} pixels on the sphere");
    assert!(
        worst < 0.5,
        "largest depth error {worst:.3} mm (voxel 1 mm)"
    );
}

#[test]
fn a_cube_seen_face_on_is_a_square_of_uniform_diffuse_shade() {
    // A cube of half-side 15 mm as a signed distance (inside positive).
    let vol = field(64, 1.0, |p| {
        let d = p.iter().map(|c| c.abs() - 15.0).fold(f64::MIN, f64::max);
        (-d * 100.0).clamp(-1000.0, 1000.0)
    });
    let scene = Scene::new(&vol).unwrap();
    let rays = Camera::default()
        .rays(&vol.frame, vol.data.dim(), 128, 128, 4096)
        .unwrap();
    let mut opts = ssd(0.0);
    opts.shading = Shading {
        ambient: 0.1,
        diffuse: 0.6,
        specular: 0.0,
        shininess: 1.0,
    };
    let img = surface_render(&scene, &rays, &opts).unwrap();
    let side_px = (hits(&img) as f64).sqrt();
    let want = 30.0 / rays.pixel;
    assert!(
        (side_px - want).abs() < 1.0,
        "square side {side_px:.2} px, want {want:.2}"
    );
    // Face-on: n·L = 1 everywhere on the face, so (ambient + diffuse) × 255.
    let expect = ((0.1 + 0.6) * 255.0f64).round() as i32;
    let half = (want / 2.0 - 2.0) as i32;
    for r in (64 - half)..(64 + half) {
        for c in (64 - half)..(64 + half) {
            let v = img.pixel(r as usize, c as usize)[0] as i32;
            assert!((v - expect).abs() <= 1, "({r}, {c}): {v} vs {expect}");
        }
    }
}

fn points(p: &[(f64, [f64; 3], f64)]) -> TransferFunction {
    TransferFunction {
        points: p
            .iter()
            .map(|&(value, color, opacity)| ControlPoint {
                value,
                color,
                opacity,
            })
            .collect(),
    }
}

fn vr(tf: TransferFunction, shading: Shading) -> VrOptions {
    VrOptions {
        transfer_function: tf,
        shading,
        clip: Clip::default(),
        background: [0.2, 0.4, 0.6],
        step_mm: None,
    }
}

#[test]
fn a_fully_transparent_transfer_function_shows_the_background() {
    let vol = ball(32, 1.0, 10.0);
    let scene = Scene::new(&vol).unwrap();
    let rays = Camera::default()
        .rays(&vol.frame, vol.data.dim(), 48, 48, 4096)
        .unwrap();
    let tf = points(&[(-1000.0, [1.0; 3], 0.0), (1000.0, [1.0; 3], 0.0)]);
    let img = volume_render(&scene, &rays, &vr(tf, Shading::default())).unwrap();
    let bg = [51u8, 102, 153];
    assert!(img.rgb.chunks(3).all(|p| p == bg));
    assert_eq!(hits(&img), 0);
}

#[test]
fn a_constant_opaque_transfer_function_shows_the_shaded_front_face_of_the_box() {
    // Values grow along the viewing direction, so the gradient (the normal) faces the eye everywhere.
    let vol = field(32, 1.0, |p| p[1]);
    let scene = Scene::new(&vol).unwrap();
    let rays = Camera::default()
        .rays(&vol.frame, vol.data.dim(), 64, 64, 4096)
        .unwrap();
    let c = [0.5, 0.4, 0.3];
    let tf = points(&[(-100.0, c, 1.0), (100.0, c, 1.0)]);
    let sh = Shading::default();
    let img = volume_render(&scene, &rays, &vr(tf, sh)).unwrap();
    let lit = sh.ambient + sh.diffuse;
    let want: Vec<u8> = c
        .iter()
        .map(|&x| ((x * lit + sh.specular) * 255.0).round() as u8)
        .collect();
    // The front face is the box's 31 mm square; its edge pixels are partly covered.
    let side = 31.0 / rays.pixel;
    let mut inside = 0;
    for r in 0..64 {
        for col in 0..64 {
            let (dx, dy) = ((col as f64 - 31.5).abs(), (r as f64 - 31.5).abs());
            let px = img.pixel(r, col);
            if dx < side / 2.0 - 1.0 && dy < side / 2.0 - 1.0 {
                assert_eq!(px.to_vec(), want, "({r}, {col})");
                inside += 1;
            } else if dx > side / 2.0 + 1.0 || dy > side / 2.0 + 1.0 {
                assert_eq!(px, [51, 102, 153], "({r}, {col}) is background");
            }
        }
    }
    assert!(inside > 1000);
}

#[test]
fn two_semi_transparent_slabs_composite_as_the_closed_form_says() {
    // Slab A (value 1) 10 mm thick in front of slab B (value 2) 14 mm thick, seen from anterior (along +y).
    // Slab A holds +1, slab B −1: interpolation at their faces never passes through the other's values.
    let vol = field(64, 1.0, |p| {
        let y = p[1];
        if (-20.0..-10.0).contains(&(y + 0.5)) {
            1.0
        } else if (0.0..14.0).contains(&(y + 0.5)) {
            -1.0
        } else {
            0.0
        }
    });
    let scene = Scene::new(&vol).unwrap();
    let rays = Camera::default()
        .rays(&vol.frame, vol.data.dim(), 16, 16, 4096)
        .unwrap();
    let (ca, aa, cb, ab) = ([1.0, 0.0, 0.0], 0.08, [0.0, 0.0, 1.0], 0.05);
    // Steps at the half-way values, so each slab is exactly its thickness of opacity (the faces of the
    // interpolated slabs lie half-way between voxels; 0.4 mm steps never sample exactly on them).
    let tf = points(&[
        (-1.0, cb, ab),
        (-0.5, cb, ab),
        (-0.4999, [0.0; 3], 0.0),
        (0.4999, [0.0; 3], 0.0),
        (0.5, ca, aa),
        (1.0, ca, aa),
    ]);
    let mut opts = vr(tf, Shading::FLAT);
    opts.step_mm = Some(0.4);
    opts.background = [0.0, 1.0, 0.0];
    let img = volume_render(&scene, &rays, &opts).unwrap();
    let ta = (1.0f64 - aa).powf(10.0);
    let tb = (1.0f64 - ab).powf(14.0);
    let want = [(1.0 - ta), ta * tb, ta * (1.0 - tb)];
    let px = img.pixel(8, 8);
    for ch in 0..3 {
        let got = px[ch] as f64 / 255.0;
        assert!(
            (got - want[ch]).abs() < 0.005,
            "channel {ch}: {got:.4} vs closed form {:.4}",
            want[ch]
        );
    }
}

#[test]
fn clipping_a_sphere_through_its_centre_shows_the_cap_at_the_centre_plane() {
    let vol = ball(64, 1.0, 20.0);
    let scene = Scene::new(&vol).unwrap();
    let cam = Camera {
        distance_mm: Some(100.0),
        ..Camera::default()
    };
    let rays = cam.rays(&vol.frame, vol.data.dim(), 96, 96, 4096).unwrap();
    let mut opts = ssd(0.0);
    // Keep the posterior half (+y): the anterior view looks straight at the cut.
    opts.clip.planes.push(ClipPlane {
        point_mm: [0.0; 3],
        normal: [0.0, 1.0, 0.0],
    });
    let img = surface_render(&scene, &rays, &opts).unwrap();
    let mut on_cap = 0;
    for r in 0..96 {
        for c in 0..96 {
            let (o, _) = rays.ray(r as f64, c as f64);
            let rho = (o[0] * o[0] + o[2] * o[2]).sqrt();
            let d = img.depth(r, c);
            if rho < 19.0 {
                assert!((d - 100.0).abs() < 1e-3, "({r}, {c}) cap depth {d}");
                on_cap += 1;
            } else if rho > 21.0 {
                assert!(d.is_nan(), "({r}, {c}) beyond the sphere shows {d}");
            }
        }
    }
    let r_px = (hits(&img) as f64 / std::f64::consts::PI).sqrt();
    assert!((r_px - 20.0 / rays.pixel).abs() < 0.01 * 20.0 / rays.pixel);
    assert!(on_cap > 700, "{on_cap} pixels on the cap");
}

#[test]
fn a_perspective_camera_sees_a_sphere_as_a_disc_of_the_tangent_cone() {
    let vol = ball(64, 1.0, 20.0);
    let scene = Scene::new(&vol).unwrap();
    let cam = Camera {
        projection: Projection::Perspective,
        distance_mm: Some(80.0),
        fov_deg: Some(40.0),
        ..Camera::default()
    };
    let rays = cam
        .rays(&vol.frame, vol.data.dim(), 128, 128, 4096)
        .unwrap();
    let img = surface_render(&scene, &rays, &ssd(0.0)).unwrap();
    // Tangent cone half-angle asin(R/D); on the image plane the disc has radius tan of it.
    let want = (20.0f64 / 80.0).asin().tan() / rays.pixel;
    let r_px = (hits(&img) as f64 / std::f64::consts::PI).sqrt();
    assert!((r_px - want).abs() < 0.01 * want, "{r_px} vs {want}");
}
