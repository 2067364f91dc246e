//! Where a derived 2D image sits in patient space ([`ImagePlane`]) and the names of its screen sides
//! ([`ScreenSides`]), in patient directions (R/L, A/P, H/F) or, for a volume not from a patient, its axes.

use serde::{Deserialize, Serialize};

type V3 = [f64; 3];

/// Where a 2D image sits in patient space, as DICOM's Image Plane module says it: the centre of the first
/// (top-left) pixel, the unit direction along a row (screen right) and down a column (screen down), and the
/// spacing between rows and between columns.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ImagePlane {
    pub first_pixel_mm: V3,
    pub row_direction: V3,
    pub column_direction: V3,
    /// Spacing between rows, then between columns (mm), as DICOM Pixel Spacing.
    pub pixel_mm: [f64; 2],
}

impl ImagePlane {
    /// Patient position of pixel (`row`, `col`).
    pub fn position(&self, row: f64, col: f64) -> V3 {
        std::array::from_fn(|c| {
            self.first_pixel_mm[c]
                + col * self.pixel_mm[1] * self.row_direction[c]
                + row * self.pixel_mm[0] * self.column_direction[c]
        })
    }

    /// The patient directions at the four screen sides.
    pub fn sides(&self) -> ScreenSides {
        let neg = |v: V3| v.map(|c| -c);
        ScreenSides {
            left: direction_label(neg(self.row_direction)),
            right: direction_label(self.row_direction),
            top: direction_label(neg(self.column_direction)),
            bottom: direction_label(self.column_direction),
        }
    }

    /// The screen sides named by the volume's axes (`+x`, `−y` written `-y`, …), for volumes without a
    /// patient (reconstructions).
    pub fn axis_sides(&self) -> ScreenSides {
        let name = |v: V3| {
            let c = (0..3)
                .max_by(|&a, &b| v[a].abs().total_cmp(&v[b].abs()))
                .unwrap_or(0);
            format!(
                "{}{}",
                if v[c] < 0.0 { '-' } else { '+' },
                ['x', 'y', 'z'][c]
            )
        };
        let neg = |v: V3| v.map(|c| -c);
        ScreenSides {
            left: name(neg(self.row_direction)),
            right: name(self.row_direction),
            top: name(neg(self.column_direction)),
            bottom: name(self.column_direction),
        }
    }

    /// Patient directions when the volume comes from a patient, volume axes otherwise.
    pub fn sides_for(&self, patient: bool) -> ScreenSides {
        if patient {
            self.sides()
        } else {
            self.axis_sides()
        }
    }

    /// DICOM Patient Orientation (0020,0020): the directions of the rows and of the columns, with H/F for
    /// head and feet.
    pub fn patient_orientation(&self) -> [String; 2] {
        let head_feet = |s: String| s.replace('S', "H").replace('I', "F");
        [
            head_feet(direction_label(self.row_direction)),
            head_feet(direction_label(self.column_direction)),
        ]
    }
}

/// The patient direction each side of the screen points to: `R`/`L`, `A`/`P`, `S`/`I` (combined, largest
/// component first, for oblique images, e.g. `LP`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ScreenSides {
    pub left: String,
    pub right: String,
    pub top: String,
    pub bottom: String,
}

/// Name of a patient direction (LPS): `L`/`R`, `P`/`A`, `S`/`I`, letters for every component above 0.1 in
/// decreasing size.
pub fn direction_label(v: V3) -> String {
    let mut parts: Vec<(f64, char)> = (0..3)
        .filter(|&c| v[c].abs() > 0.1)
        .map(|c| {
            let letter = match (c, v[c] > 0.0) {
                (0, true) => 'L',
                (0, false) => 'R',
                (1, true) => 'P',
                (1, false) => 'A',
                (_, true) => 'S',
                (_, false) => 'I',
            };
            (v[c].abs(), letter)
        })
        .collect();
    parts.sort_by(|a, b| b.0.total_cmp(&a.0));
    parts.into_iter().map(|(_, l)| l).collect()
}
