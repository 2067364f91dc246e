//! The products of a volume job on the marker patient, and what each must show: where every marker lies on
//! screen, the screen sides and the placement of every frame.

use serde_json::{Value, json};

use super::geometry::{
    Planar, Turning, V3, axpy, close, dot, oblique, radiological, rendered, sides, sub, unit, v3,
};
use super::images::{Grey, Plane, assert_marker, blob};
use super::phantom::{MARKERS, N, O, S, lps};
use ctrecon::volume::Frame;

/// What a product is, as far as the checks need to know.
#[derive(Debug, Clone)]
pub enum Expect {
    /// A projection along a display axis (the lattice of the canonical volume).
    Projection(&'static str),
    /// A planar MPR: its centre and screen axes, pixel size, `(spacing, extent)` of a series, whether it is
    /// a slab, and the markers that lie on (within one sample of, or within the slab of) one of its frames.
    Mpr {
        centre: V3,
        right: V3,
        down: V3,
        pixel: f64,
        series: Option<(f64, f64)>,
        slab: bool,
        markers: Vec<usize>,
    },
    /// A curved MPR along `points` (rows `down`, `height` of them centred on the curve); `vertices` names the
    /// point of each marker.
    Curved {
        points: Vec<V3>,
        height: usize,
        pixel: f64,
        vertices: Vec<(usize, usize)>,
    },
    /// A rotating projection of `frames` frames.
    Rotating { frames: usize },
    /// A rendering of `size` pixels from the front, or `frames` of them turning about the superior axis, in
    /// which the markers above `level` HU are lit and the others not.
    Render {
        size: [usize; 2],
        level: f32,
        frames: usize,
    },
}

/// A product request and what it must show.
pub struct Product {
    pub spec: Value,
    pub expect: Expect,
}

/// A radiological MPR (`axis`) with the default pixel, the x spacing.
fn mpr(
    spec: Value,
    centre: V3,
    axis: &str,
    series: Option<(f64, f64)>,
    slab: bool,
    markers: Vec<usize>,
) -> Product {
    let (right, down) = radiological(axis);
    Product {
        spec,
        expect: Expect::Mpr {
            centre,
            right,
            down,
            pixel: S[0],
            series,
            slab,
            markers,
        },
    }
}

/// Every product kind of a volume job, on the marker patient.
pub fn products() -> Vec<Product> {
    let m: Vec<V3> = MARKERS.iter().map(|(c, _)| lps(*c)).collect();
    // Series planes through this lattice point fall on every marker (the default pixel is the x spacing).
    let c = lps([8, 6, 5]);
    let slab = |kind: &str| json!({"thickness_mm": 3.0, "kind": kind});
    let mut out: Vec<Product> = ["axial", "coronal", "sagittal"]
        .iter()
        .map(|&axis| Product {
            spec: json!({"type": "projection", "axis": axis, "kind": "mip"}),
            expect: Expect::Projection(axis),
        })
        .collect();
    // One coronal plane through the first marker (and the face of the second's cube, 1 mm behind).
    let through = [c[0], m[0][1], c[2]];
    out.push(mpr(
        json!({"type": "mpr", "plane": "coronal", "centre_mm": through}),
        through,
        "coronal",
        None,
        false,
        vec![0, 1],
    ));
    out.push(mpr(
        json!({"type": "mpr", "plane": "axial", "centre_mm": c, "spacing_mm": 2.0, "extent_mm": 8.0}),
        c,
        "axial",
        Some((2.0, 8.0)),
        false,
        vec![0, 1, 2],
    ));
    out.push(mpr(
        json!({"type": "mpr", "plane": "coronal", "centre_mm": c, "spacing_mm": 1.0, "extent_mm": 6.0}),
        c,
        "coronal",
        Some((1.0, 6.0)),
        false,
        vec![0, 1, 2],
    ));
    out.push(mpr(
        json!({"type": "mpr", "plane": "sagittal", "centre_mm": c, "spacing_mm": 0.8, "extent_mm": 6.4}),
        c,
        "sagittal",
        Some((0.8, 6.4)),
        false,
        vec![0, 1, 2],
    ));
    for (axis, spacing, extent) in [("coronal", 3.0, 6.0), ("sagittal", 2.4, 4.8)] {
        for kind in ["average", "mip"] {
            out.push(mpr(
                json!({"type": "mpr", "plane": axis, "centre_mm": c, "slab": slab(kind),
                       "spacing_mm": spacing, "extent_mm": extent}),
                c,
                axis,
                Some((spacing, extent)),
                true,
                vec![0, 1, 2],
            ));
        }
    }
    // An oblique plane through the brightest marker, centred 2 mm left and 1.5 mm up of it on screen: the
    // marker's centre falls on pixel (12, 11).
    let normal = [1.0, 2.0, 2.0];
    let (right, down) = oblique(normal);
    let centre = axpy(axpy(m[2], 2.0, right), 1.5, down);
    out.push(Product {
        spec: json!({"type": "mpr", "normal": normal, "centre_mm": centre, "size": [31, 31], "pixel_mm": 0.5}),
        expect: Expect::Mpr {
            centre,
            right,
            down,
            pixel: 0.5,
            series: None,
            slab: false,
            markers: vec![2],
        },
    });
    // A curve through the markers along lattice lines, every vertex a whole number of millimetres along it.
    let mut points = vec![axpy(m[0], -3.0, [1.0, 0.0, 0.0])];
    for (axis, d) in [
        (0, 3.0),
        (0, 4.0),
        (1, 7.0),
        (2, 6.0),
        (0, 4.0),
        (1, -6.0),
        (2, 2.0),
        (2, 4.0),
    ] {
        let mut p = *points.last().unwrap();
        p[axis] += d;
        points.push(p);
    }
    for (i, want) in [(1, m[0]), (4, m[2]), (7, m[1])] {
        assert!(
            close(points[i], want, 1e-9),
            "curve vertex {i}: {:?}",
            points[i]
        );
    }
    out.push(Product {
        spec: json!({"type": "curved", "points_mm": points, "height": 9, "pixel_mm": 1.0}),
        expect: Expect::Curved {
            points,
            height: 9,
            pixel: 1.0,
            vertices: vec![(0, 1), (2, 4), (1, 7)],
        },
    });
    out.push(Product {
        spec: json!({"type": "rotating", "frames": 4}),
        expect: Expect::Rotating { frames: 4 },
    });
    // Renderings: the markers above 450 HU opaque and white, the rest transparent; the volume rendering
    // also turning about the superior axis.
    let p = |value: f64, opacity: f64| json!({"value": value, "color": [1.0, 1.0, 1.0], "opacity": opacity});
    for frames in [1, 4] {
        out.push(Product {
            spec: json!({"type": "volume_render", "size": [64, 64], "camera": {"view": "anterior"},
                         "shading": {"ambient": 1.0, "diffuse": 0.0, "specular": 0.0, "shininess": 1.0},
                         "transfer_function": {"points": [p(-1100.0, 0.0), p(450.0, 0.0), p(460.0, 1.0), p(1000.0, 1.0)]},
                         "frames": frames}),
            expect: Expect::Render {
                size: [64, 64],
                level: 450.0,
                frames,
            },
        });
    }
    out.push(Product {
        spec: json!({"type": "surface_render", "size": [64, 64], "camera": {"view": "anterior"},
                     "surfaces": [{"iso": 450.0}]}),
        expect: Expect::Render {
            size: [64, 64],
            level: 450.0,
            frames: 1,
        },
    });
    out
}

/// The patient box of the canonical volume.
pub fn patient_box() -> (Frame, (usize, usize, usize)) {
    (
        Frame {
            spacing_mm: S,
            origin_mm: O,
            direction: Frame::AXIS_ALIGNED,
        },
        (N[2], N[1], N[0]),
    )
}

/// Where a marker at lattice index `c` is seen in each projection: axial `[y][x]`, coronal `[z↓][x]`,
/// sagittal `[z↓][y]`.
pub fn screen(axis: &str, c: [usize; 3]) -> (usize, usize) {
    match axis {
        "axial" => (c[1], c[0]),
        "coronal" => (N[2] - 1 - c[2], c[0]),
        _ => (N[2] - 1 - c[2], c[1]),
    }
}

/// The patient axis (0 x, 1 y, 2 z) a display axis steps along.
pub fn fixed_axis(axis: &str) -> usize {
    match axis {
        "axial" => 2,
        "coronal" => 1,
        _ => 0,
    }
}

/// Patient position of the first (top-left) pixel of display image `index` along `axis` (fractional for
/// the middle plane of a projection): the right, anterior, superior corner as the display shows it.
pub fn display_first_pixel(axis: &str, index: f64) -> V3 {
    let top = O[2] + (N[2] - 1) as f64 * S[2];
    let mut p = [O[0], O[1], top];
    let a = fixed_axis(axis);
    p[a] = O[a] + index * S[a];
    p
}

/// The curve's length up to each point.
fn arcs(points: &[V3]) -> Vec<f64> {
    let mut s = vec![0.0];
    for w in points.windows(2) {
        let d = sub(w[1], w[0]);
        s.push(s.last().unwrap() + dot(d, d).sqrt());
    }
    s
}

impl Expect {
    /// The planar geometry of an MPR, its size read from the product (`[frames, rows, columns]`).
    pub fn planar(&self, product: &Value) -> Option<Planar> {
        let Expect::Mpr {
            centre,
            right,
            down,
            pixel,
            series,
            ..
        } = self
        else {
            return None;
        };
        let shape = &product["shape"];
        let n = |a: usize| shape[a].as_u64().unwrap() as usize;
        let (spacing, frames) = match series {
            Some((sp, ext)) => (*sp, (2.0 * ext / sp + 1e-9).floor() as usize + 1),
            None => (0.0, 1),
        };
        Some(Planar {
            centre: *centre,
            right: *right,
            down: *down,
            pixel: *pixel,
            size: [n(2), n(1)],
            frames,
            spacing,
        })
    }

    /// Screen right and down of frame `k` of `frames`.
    pub fn axes(&self, k: usize, frames: usize) -> (V3, V3) {
        match self {
            Expect::Projection(axis) => radiological(axis),
            Expect::Mpr { right, down, .. } => (*right, *down),
            Expect::Curved { points, .. } => {
                let along = sub(*points.last().unwrap(), points[0]);
                (unit(along), [0.0, 0.0, -1.0])
            }
            Expect::Rotating { .. } | Expect::Render { .. } => (
                Turning::right(360.0 * k as f64 / frames as f64),
                [0.0, 0.0, -1.0],
            ),
        }
    }

    /// The screen sides of frame `k` of `frames`, as JSON.
    pub fn sides(&self, k: usize, frames: usize) -> Value {
        let (r, d) = self.axes(k, frames);
        sides(r, d)
    }

    /// Check a product's JSON: shape, screen sides and placement.
    pub fn check_json(&self, p: &Value, what: &str) {
        let frames = p["shape"][0].as_u64().unwrap() as usize;
        assert_eq!(p["orientation"], self.sides(0, frames), "{what}: {p}");
        match self {
            Expect::Projection(axis) => {
                let plane = &p["plane"];
                let (r, d) = radiological(axis);
                let a = fixed_axis(axis);
                let first = display_first_pixel(axis, (N[a] - 1) as f64 / 2.0);
                let pixel = match *axis {
                    "axial" => [S[1], S[0]],
                    "coronal" => [S[2], S[0]],
                    _ => [S[2], S[1]],
                };
                let ok = close(v3(&plane["first_pixel_mm"]), first, 1e-6)
                    && close(v3(&plane["row_direction"]), r, 1e-9)
                    && close(v3(&plane["column_direction"]), d, 1e-9)
                    && (0..2)
                        .all(|a| (plane["pixel_mm"][a].as_f64().unwrap() - pixel[a]).abs() < 1e-9);
                assert!(ok, "{what}: {plane}");
            }
            Expect::Mpr { series, .. } => {
                let planar = self.planar(p).unwrap();
                assert_eq!(frames, planar.frames, "{what}: {p}");
                planar.assert_plane(&p["plane"], 0, what);
                match series {
                    Some((sp, _)) => {
                        assert_eq!(p["frame_spacing_mm"].as_f64(), Some(*sp), "{what}")
                    }
                    None => assert!(p.get("frame_spacing_mm").is_none(), "{what}: {p}"),
                }
            }
            Expect::Curved {
                points,
                height,
                pixel,
                ..
            } => {
                let length = arcs(points).last().copied().unwrap();
                let cols = (length / pixel + 1e-9).floor() as u64 + 1;
                assert_eq!(p["shape"], json!([1, height, cols]), "{what}");
            }
            Expect::Rotating { frames: n } => {
                assert_eq!(frames, *n, "{what}");
                let px = &p["pixel_mm"];
                assert!(
                    (0..2).all(|a| (px[a].as_f64().unwrap() - S[0]).abs() < 1e-9),
                    "{what}: {p}"
                );
            }
            Expect::Render {
                size, frames: n, ..
            } => {
                assert_eq!(p["shape"], json!([n, size[1], size[0]]), "{what}");
            }
        }
    }

    /// Check where a grey product shows each marker.
    pub fn check_grey(&self, p: &Value, img: &Grey, what: &str) {
        match self {
            Expect::Projection(axis) => {
                for (c, v) in MARKERS {
                    let (r, col) = screen(axis, c);
                    assert_eq!(img.at(0, r, col), v, "{what}: marker {c:?}");
                    assert_marker(img.frame(0), (r as f64, col as f64), 0.0, 0.5, what);
                }
            }
            Expect::Mpr { slab, markers, .. } => {
                let planar = self.planar(p).unwrap();
                assert_eq!(
                    (img.frames, img.rows, img.cols),
                    (planar.frames, planar.size[1], planar.size[0]),
                    "{what}"
                );
                // A thin plane shows a marker whose cube (one sample either side of its centre) it cuts at
                // full value; a slab the markers within it.
                let reach = if *slab {
                    planar.spacing / 2.0 + 1e-6
                } else {
                    1.0 + 1e-6
                };
                let mut checked = Vec::new();
                for (m, (c, v)) in MARKERS.iter().enumerate() {
                    let p = lps(*c);
                    let (k, d) = planar.frame_of(p);
                    if d > reach {
                        assert!(
                            !markers.contains(&m),
                            "{what}: marker {m} is {d} mm from the nearest frame"
                        );
                        continue;
                    }
                    let want = planar.pixel_of(p, k);
                    let what = format!("{what}: marker {m} in frame {k}");
                    assert_marker(img.frame(k), want, v / 8.0, 0.5, &what);
                    // A marker's centre on a pixel of a thin plane: that pixel has its value.
                    let whole = |x: f64| (x - x.round()).abs() < 1e-6;
                    if !*slab && d < 1e-6 && whole(want.0) && whole(want.1) {
                        let got = img.at(k, want.0.round() as usize, want.1.round() as usize);
                        assert!((got - v).abs() < 1e-2, "{what}: {got} at {want:?}");
                    }
                    checked.push(m);
                }
                assert_eq!(&checked, markers, "{what}: markers seen");
            }
            Expect::Curved {
                points,
                height,
                pixel,
                vertices,
            } => {
                let s = arcs(points);
                let row = (height - 1) / 2;
                for &(m, i) in vertices {
                    let col = (s[i] / pixel).round() as usize;
                    let v = MARKERS[m].1;
                    assert!(
                        (img.at(0, row, col) - v).abs() < 1e-2,
                        "{what}: marker {m} at column {col}: {}",
                        img.at(0, row, col)
                    );
                }
            }
            Expect::Rotating { frames } => {
                let (frame, dim) = patient_box();
                let (centre, _) = super::geometry::bounds(&frame, dim);
                let turning = Turning {
                    centre,
                    pixel: p["pixel_mm"][0].as_f64().unwrap(),
                    rows: img.rows,
                    cols: img.cols,
                };
                for k in 0..*frames {
                    let angle = 360.0 * k as f64 / *frames as f64;
                    for (m, (c, v)) in MARKERS.iter().enumerate() {
                        let want = turning.pixel_of(lps(*c), angle);
                        assert_marker(
                            img.frame(k),
                            want,
                            v / 8.0,
                            0.5,
                            &format!("{what}: marker {m} at {angle}°"),
                        );
                    }
                }
            }
            Expect::Render { .. } => panic!("{what}: a rendering is not grey"),
        }
    }

    /// Where frame `k` of a rendering (its brightness) of a volume (`frame`, `dim`) shows each marker (at `at`,
    /// LPS) above its level; the centroids.
    pub fn check_render(
        &self,
        img: Plane<'_>,
        k: usize,
        (frame, dim): (&Frame, (usize, usize, usize)),
        at: &[V3],
        tol: f64,
        what: &str,
    ) -> Vec<(f64, f64)> {
        let Expect::Render {
            size,
            level,
            frames,
        } = self
        else {
            panic!("{what}: not a rendering")
        };
        assert_eq!((img.rows, img.cols), (size[1], size[0]), "{what}");
        let (right, _) = self.axes(k, *frames);
        let mut out = Vec::new();
        for (m, (_, v)) in MARKERS.iter().enumerate() {
            let want = rendered(frame, dim, *size, right, at[m]);
            if v > level {
                out.push(assert_marker(
                    img,
                    want,
                    30.0,
                    tol,
                    &format!("{what}: marker {m}"),
                ));
            } else {
                assert!(
                    blob(img, want, 3.0, 30.0).is_none(),
                    "{what}: marker {m} of {v} HU is lit"
                );
            }
        }
        out
    }
}
