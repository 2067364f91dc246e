//! Iso-values against the range of a volume job's volume. A surface whose iso-value lies above every sample is
//! empty, so a mesh at it, or a shaded-surface product all of whose surfaces are, shows nothing: refused at
//! submission (422 `iso_out_of_range`) where the maximum is known (a stored series or result, bounded after
//! steps by [`super::imaging::plan`]). A shaded-surface product with some surfaces that cannot appear (a
//! protocol's bone surface on a volume without bone) still shows the others: each missing surface is a job
//! warning with the same code, as is every surface that cannot appear where only the data know the maximum (a
//! series pulled from a PACS, smoothing that lowered the ridge). Samples equal to the iso-value are inside, so
//! an iso-value at the maximum still shows them.

use super::model::{Notice, VolumeUnits};
use super::model::{ProductSpec, VolumeJobRequest};
use super::model::{ValueUnits, to_volume_units};
use crate::error_code::{ErrorCode, Problem};

/// Why an iso-value is refused or warned about: "`what` iso is above every value of the volume (at most max):
/// the surface would be empty".
pub fn above_every_value(
    what: &str,
    iso: impl std::fmt::Display,
    max: impl std::fmt::Display,
) -> String {
    format!(
        "`{what}` {iso} is above every value of the volume (at most {max}): the surface would be empty"
    )
}

/// A shaded surface above `max` (volume units): (product index, surface index, message).
fn surfaces_above(
    req: &VolumeJobRequest,
    max: f32,
    units: VolumeUnits,
    mu_water: f64,
) -> Vec<(usize, usize, String)> {
    let mut out = Vec::new();
    for (i, p) in req.products.iter().enumerate() {
        let ProductSpec::SurfaceRender(s) = p else {
            continue;
        };
        for (j, sf) in s.surfaces.iter().enumerate() {
            let iso = to_volume_units(sf.iso, s.units, units, mu_water) as f32;
            if iso > max {
                // The maximum in the units the request used.
                let shown = match (s.units, units) {
                    (ValueUnits::Hu, VolumeUnits::MuPerMm) => {
                        format!("{:.1} HU", 1000.0 * (f64::from(max) / mu_water - 1.0))
                    }
                    (_, VolumeUnits::Hu) => format!("{max} HU"),
                    (ValueUnits::Native, VolumeUnits::MuPerMm) => format!("{max} /mm"),
                };
                out.push((
                    i,
                    j,
                    format!(
                        "products[{i}]: {}",
                        above_every_value(&format!("surfaces[{j}].iso"), sf.iso, shown)
                    ),
                ));
            }
        }
    }
    out
}

/// Refuse a volume job with a `surface_render` product every surface of which lies above `max`, the bound on
/// the volume's values after its steps (`None`: not known before the job runs): the picture would be empty.
/// The pointer names the product's first surface. HU iso-values on a μ volume convert through `mu_water`.
pub fn refuse_surfaces_above(
    req: &VolumeJobRequest,
    max: Option<f32>,
    units: VolumeUnits,
    mu_water: f64,
) -> Result<(), Problem> {
    let Some(max) = max else { return Ok(()) };
    let above = surfaces_above(req, max, units, mu_water);
    for (i, p) in req.products.iter().enumerate() {
        let ProductSpec::SurfaceRender(s) = p else {
            continue;
        };
        let here: Vec<&(usize, usize, String)> = above.iter().filter(|a| a.0 == i).collect();
        if let Some(first) = here.first()
            && here.len() == s.surfaces.len()
        {
            return Err(Problem::new(ErrorCode::IsoOutOfRange, first.2.clone())
                .at(format!("/products/{i}/surfaces/{}/iso", first.1)));
        }
    }
    Ok(())
}

/// Warnings (`iso_out_of_range`) for every `surface_render` iso-value above `max`, the largest value of the
/// volume the products are made from.
pub fn warn_surfaces_above(
    req: &VolumeJobRequest,
    max: f32,
    units: VolumeUnits,
    mu_water: f64,
) -> Vec<Notice> {
    surfaces_above(req, max, units, mu_water)
        .into_iter()
        .map(|(_, _, message)| Notice {
            code: ErrorCode::IsoOutOfRange.code().to_string(),
            message: message.replace("would be empty", "does not appear in the picture"),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(surfaces: serde_json::Value, units: &str) -> VolumeJobRequest {
        serde_json::from_value(serde_json::json!({
            "kind": "volume",
            "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5",
            "products": [{"type": "mpr"},
                         {"type": "surface_render", "surfaces": surfaces, "units": units}]
        }))
        .unwrap()
    }

    #[test]
    fn a_shaded_surface_product_above_the_maximum_is_refused_with_its_pointer_and_a_partial_one_is_kept()
     {
        let req = request(serde_json::json!([{"iso": 1100}, {"iso": 1200}]), "hu");
        let e = refuse_surfaces_above(&req, Some(1000.0), VolumeUnits::Hu, 0.02).unwrap_err();
        assert_eq!(e.code, ErrorCode::IsoOutOfRange);
        assert_eq!(e.errors[0].pointer, "/products/1/surfaces/0/iso");
        assert!(e.detail.contains("at most 1000 HU"), "{}", e.detail);
        // Skin still shows when the bone surface cannot: kept, and warned about when it runs.
        let partial = request(serde_json::json!([{"iso": 300}, {"iso": 1200}]), "hu");
        assert!(refuse_surfaces_above(&partial, Some(1000.0), VolumeUnits::Hu, 0.02).is_ok());
        let w = warn_surfaces_above(&partial, 1000.0, VolumeUnits::Hu, 0.02);
        assert_eq!(w.len(), 1);
        assert!(w[0].message.contains("surfaces[1].iso"), "{}", w[0].message);
        let at = request(serde_json::json!([{"iso": 1000}]), "hu");
        assert!(refuse_surfaces_above(&at, Some(1000.0), VolumeUnits::Hu, 0.02).is_ok());
        assert!(refuse_surfaces_above(&req, None, VolumeUnits::Hu, 0.02).is_ok());
    }

    #[test]
    fn hu_iso_values_on_a_mu_volume_compare_through_mu_water() {
        // μ_water 0.02 /mm: a maximum of 0.04 /mm is 1000 HU.
        let req = request(serde_json::json!([{"iso": 999}]), "hu");
        assert!(refuse_surfaces_above(&req, Some(0.04), VolumeUnits::MuPerMm, 0.02).is_ok());
        let req = request(serde_json::json!([{"iso": 1010}]), "hu");
        let e = refuse_surfaces_above(&req, Some(0.04), VolumeUnits::MuPerMm, 0.02).unwrap_err();
        assert!(e.detail.contains("at most 1000.0 HU"), "{}", e.detail);
        let native = request(serde_json::json!([{"iso": 0.05}]), "native");
        let w = warn_surfaces_above(&native, 0.04, VolumeUnits::MuPerMm, 0.02);
        assert_eq!(w.len(), 1);
        assert_eq!(w[0].code, "iso_out_of_range");
        assert!(
            w[0].message.contains("(at most 0.04 /mm)"),
            "{}",
            w[0].message
        );
        assert!(w[0].message.contains("does not appear"), "{}", w[0].message);
    }
}
