//! The JSON description of a phantom: a named table or a user list, plus the scale in millimetres.
//!
//! `{"table": "modified_shepp_logan", "scale_mm": 128}`,
//! `{"ellipses": [{"value": 0.02, "a": 0.5, "b": 0.3, "x0": 0.1, "phi_deg": 30}], "scale_mm": 100}` or
//! `{"ellipsoids": [{"value": 0.02, "a": 0.5, "b": 0.3, "c": 0.4}], "scale_mm": 100}`. Exactly one of
//! `table`, `ellipses`, `ellipsoids`; omitted centres and angles are 0; unknown fields are refused.

use serde::{Deserialize, Serialize};

use super::{Ellipse, Ellipsoid, Phantom2, Phantom3, Table2, Table3};
use crate::recon::error::ReconError;

/// Names of the built-in tables. `shepp_logan` and `modified_shepp_logan` exist in 2D and 3D;
/// `yu_ye_wang` only in 3D.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TableName {
    SheppLogan,
    ModifiedSheppLogan,
    YuYeWang,
}

/// A phantom as a client describes it; [`PhantomSpec::phantom2`] and [`PhantomSpec::phantom3`] turn it
/// into a validated phantom for a 2D or a 3D geometry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhantomSpec {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub table: Option<TableName>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ellipses: Option<Vec<Ellipse>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ellipsoids: Option<Vec<Ellipsoid>>,
    /// Millimetres per phantom unit: half the side of the field of view the phantom's [−1, 1] spans.
    pub scale_mm: f64,
}

impl PhantomSpec {
    fn check_one_source(&self) -> Result<(), ReconError> {
        let given = [
            self.table.is_some(),
            self.ellipses.is_some(),
            self.ellipsoids.is_some(),
        ];
        match given.iter().filter(|&&g| g).count() {
            1 => Ok(()),
            n => Err(ReconError::param(
                "phantom",
                format!("give exactly one of `table`, `ellipses`, `ellipsoids` (got {n})"),
            )),
        }
    }

    /// The validated 2D phantom: a 2D table or `ellipses`.
    pub fn phantom2(&self) -> Result<Phantom2, ReconError> {
        self.check_one_source()?;
        let ellipses = match (&self.table, &self.ellipses) {
            (Some(TableName::SheppLogan), _) => Table2::SheppLogan.ellipses(),
            (Some(TableName::ModifiedSheppLogan), _) => Table2::ModifiedSheppLogan.ellipses(),
            (Some(TableName::YuYeWang), _) => {
                return Err(ReconError::param(
                    "table",
                    "`yu_ye_wang` is a 3D table; a 2D geometry needs `shepp_logan`, \
                     `modified_shepp_logan` or `ellipses`",
                ));
            }
            (None, Some(list)) => list.clone(),
            (None, None) => {
                return Err(ReconError::param(
                    "ellipsoids",
                    "a 2D geometry needs `table` or `ellipses`, not `ellipsoids`",
                ));
            }
        };
        Phantom2::new(ellipses, self.scale_mm)
    }

    /// The validated 3D phantom: a 3D table or `ellipsoids`.
    pub fn phantom3(&self) -> Result<Phantom3, ReconError> {
        self.check_one_source()?;
        let ellipsoids = match (&self.table, &self.ellipsoids) {
            (Some(TableName::SheppLogan), _) => Table3::SheppLogan.ellipsoids(),
            (Some(TableName::ModifiedSheppLogan), _) => Table3::ModifiedSheppLogan.ellipsoids(),
            (Some(TableName::YuYeWang), _) => Table3::YuYeWang.ellipsoids(),
            (None, Some(list)) => list.clone(),
            (None, None) => {
                return Err(ReconError::param(
                    "ellipses",
                    "a 3D geometry needs `table` or `ellipsoids`, not `ellipses`",
                ));
            }
        };
        Phantom3::new(ellipsoids, self.scale_mm)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> PhantomSpec {
        serde_json::from_str(text).unwrap()
    }

    #[test]
    fn a_named_table_builds_in_two_and_three_dimensions() {
        let s = parse(r#"{"table": "modified_shepp_logan", "scale_mm": 128}"#);
        let p2 = s.phantom2().unwrap();
        assert_eq!(p2, Phantom2::from_table(Table2::ModifiedSheppLogan, 128.0));
        let p3 = s.phantom3().unwrap();
        assert_eq!(p3, Phantom3::from_table(Table3::ModifiedSheppLogan, 128.0));
        let yyw = parse(r#"{"table": "yu_ye_wang", "scale_mm": 1}"#);
        assert_eq!(yyw.phantom3().unwrap().ellipsoids[8].z0, 0.625);
        assert!(yyw.phantom2().is_err());
    }

    #[test]
    fn user_lists_take_defaults_for_centres_and_angles() {
        let s = parse(r#"{"ellipses": [{"value": 0.02, "a": 0.5, "b": 0.3}], "scale_mm": 10}"#);
        let p = s.phantom2().unwrap();
        assert_eq!(p.ellipses[0].x0, 0.0);
        assert_eq!(p.ellipses[0].phi_deg, 0.0);
        assert!(s.phantom3().is_err());
        let s = parse(
            r#"{"ellipsoids": [{"value": 1, "a": 0.5, "b": 0.3, "c": 0.2, "theta_deg": 5}],
                "scale_mm": 10}"#,
        );
        assert_eq!(s.phantom3().unwrap().ellipsoids[0].theta_deg, 5.0);
        assert!(s.phantom2().is_err());
    }

    #[test]
    fn unknown_fields_and_ambiguous_or_invalid_specs_are_refused() {
        let unknown = r#"{"table": "shepp_logan", "scale_mm": 1, "fov": 2}"#;
        assert!(serde_json::from_str::<PhantomSpec>(unknown).is_err());
        let in_ellipse = r#"{"ellipses": [{"value": 1, "a": 1, "b": 1, "c": 1}], "scale_mm": 1}"#;
        assert!(serde_json::from_str::<PhantomSpec>(in_ellipse).is_err());
        assert!(serde_json::from_str::<PhantomSpec>(r#"{"table": "kak", "scale_mm": 1}"#).is_err());
        let both = parse(r#"{"table": "shepp_logan", "ellipses": [], "scale_mm": 1}"#);
        assert!(matches!(
            both.phantom2(),
            Err(ReconError::InvalidParameter {
                name: "phantom",
                ..
            })
        ));
        let none = parse(r#"{"scale_mm": 1}"#);
        assert!(none.phantom3().is_err());
        let flat = parse(r#"{"ellipses": [{"value": 1, "a": 0, "b": 1}], "scale_mm": 1}"#);
        let Err(ReconError::InvalidParameter { name, reason }) = flat.phantom2() else {
            panic!("a zero semi-axis must be refused")
        };
        assert_eq!(name, "ellipses");
        assert!(reason.contains("ellipse 0: `a`"), "{reason}");
        let scale = parse(r#"{"table": "shepp_logan", "scale_mm": -1}"#);
        assert!(matches!(
            scale.phantom3(),
            Err(ReconError::InvalidParameter {
                name: "scale_mm",
                ..
            })
        ));
        let nan = Phantom3::new(
            vec![Ellipsoid {
                value: 1.0,
                a: 1.0,
                b: f64::NAN,
                c: 1.0,
                x0: 0.0,
                y0: 0.0,
                z0: 0.0,
                phi_deg: 0.0,
                theta_deg: 0.0,
                psi_deg: 0.0,
            }],
            1.0,
        );
        assert!(nan.is_err());
    }
}
