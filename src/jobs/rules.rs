//! Automatic processing rules: when a complete series matching [`SeriesMatch`] arrives, run a volume job
//! (a named protocol or an explicit template of steps and products) and send its DICOM results to
//! destinations (configured DIMSE peers or DICOMweb origins). Model, validation, matching and the shipped
//! protocols; the rules are stored by `repo` and fired by the application.
//!
//! Patterns (`modality`, `body_part`, `series_description`) are DICOM-style wildcards: `*` any run of
//! characters, `?` one character, compared without regard to case.

use serde::{Deserialize, Serialize};
use serde_json::json;
use sha2::{Digest, Sha256};

use super::model::SeriesRecord;
use super::model::{MAX_ITEMS, ProductSpec, Step};
use crate::storage::npy::hex;
use crate::volume::WindowPreset;

/// Longest rule name and pattern (characters).
pub const MAX_NAME: usize = 64;
/// Most destinations of one rule.
pub const MAX_DESTINATIONS: usize = 16;

/// An inclusive range; either end may be left open.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Range {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max: Option<f64>,
}

impl Range {
    fn contains(&self, v: f64) -> bool {
        self.min.is_none_or(|m| v >= m) && self.max.is_none_or(|m| v <= m)
    }
    fn problem(&self, what: &str) -> Option<String> {
        let finite = |v: Option<f64>| v.is_none_or(f64::is_finite);
        if !finite(self.min) || !finite(self.max) {
            return Some(format!("`{what}` bounds must be finite numbers"));
        }
        match (self.min, self.max) {
            (Some(a), Some(b)) if a > b => Some(format!("`{what}`: min {a} is above max {b}")),
            _ => None,
        }
    }
}

/// What an arriving series must be for a rule to fire. Every given condition must hold; an empty match
/// takes every series.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SeriesMatch {
    /// Modality (0008,0060) pattern, e.g. `CT`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub modality: Option<String>,
    /// Body Part Examined (0018,0015) pattern, e.g. `*SPINE*`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub body_part: Option<String>,
    /// Series Description (0008,103E) pattern.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub series_description: Option<String>,
    /// Values Image Type (0008,0008) must all contain, e.g. `["ORIGINAL", "AXIAL"]`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub image_type: Vec<String>,
    /// Slice Thickness (0018,0050) in mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slice_thickness_mm: Option<Range>,
    /// Number of instances in the series.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instances: Option<Range>,
    /// Calling AE titles that sent the series (a series uploaded over HTTP has none, so it never
    /// matches a rule that names them).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub calling_ae: Vec<String>,
}

/// A shipped protocol, usable by name in a rule and listed by `GET /v1/protocols` (the viewer's presets).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Protocol {
    /// Sagittal and coronal 3 mm average slabs every 3 mm (derived CT series) and a coronal bone MIP.
    Spine,
    /// A bone iso-surface (300 HU, largest piece, smoothed; Encapsulated STL) and a 36-frame rotating MIP.
    BoneStl,
    /// A coronal MinIP (airways) and axial 10 mm MIP slabs every 10 mm (nodules, vessels), lung window.
    Lung,
}

impl Protocol {
    /// Every shipped protocol, in the order clients list them.
    pub const ALL: [Protocol; 3] = [Protocol::Spine, Protocol::BoneStl, Protocol::Lung];

    /// The name rules give (`"protocol": "spine"`).
    pub fn name(self) -> &'static str {
        match self {
            Protocol::Spine => "spine",
            Protocol::BoneStl => "bone_stl",
            Protocol::Lung => "lung",
        }
    }

    /// One line on what the protocol makes, for people choosing one.
    pub fn description(self) -> &'static str {
        match self {
            Protocol::Spine => {
                "Spine: sagittal and coronal 3 mm average slabs every 3 mm, coronal MIP"
            }
            Protocol::BoneStl => "Bone: 300 HU bone surface (STL), 36-frame rotating MIP",
            Protocol::Lung => "Lung: coronal MinIP, axial 10 mm MIP slabs every 10 mm",
        }
    }

    /// The window of its Secondary Capture results when the rule names none.
    pub fn window(self) -> WindowPreset {
        match self {
            Protocol::Spine | Protocol::BoneStl => WindowPreset::Bone,
            Protocol::Lung => WindowPreset::Lung,
        }
    }

    /// The steps and products as `POST /v1/jobs` (`kind: volume`) takes them: `{"steps": [...], "products":
    /// [...]}`. [`Protocol::template`] is this, parsed.
    pub fn body(self) -> serde_json::Value {
        let products = match self {
            Protocol::Spine => json!([
                {"type": "mpr", "plane": "sagittal", "slab": {"thickness_mm": 3.0, "kind": "average"},
                 "spacing_mm": 3.0},
                {"type": "mpr", "plane": "coronal", "slab": {"thickness_mm": 3.0, "kind": "average"},
                 "spacing_mm": 3.0},
                {"type": "projection", "axis": "coronal", "kind": "mip"}
            ]),
            Protocol::BoneStl => json!([
                {"type": "mesh", "iso": 300.0, "largest_component": true, "smoothing": 10,
                 "target_triangles": 200000},
                {"type": "rotating", "frames": 36, "kind": "mip"}
            ]),
            Protocol::Lung => json!([
                {"type": "projection", "axis": "coronal", "kind": "minip"},
                {"type": "mpr", "plane": "axial", "slab": {"thickness_mm": 10.0, "kind": "mip"},
                 "spacing_mm": 10.0}
            ]),
        };
        json!({"steps": [], "products": products})
    }

    /// The protocol's steps and products.
    pub fn template(self) -> JobTemplate {
        serde_json::from_value(self.body()).unwrap_or_default()
    }
}

/// The volume job a rule runs on the matched series: the body of `POST /v1/jobs` without `kind` and
/// `input`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobTemplate {
    #[serde(default)]
    pub steps: Vec<Step>,
    #[serde(default)]
    pub products: Vec<ProductSpec>,
}

fn yes() -> bool {
    true
}

/// `POST /v1/rules` and a rule of the configuration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RuleSpec {
    /// `[a-z0-9_-]`, 1–64 characters; the rule's id.
    pub name: String,
    #[serde(default = "yes")]
    pub enabled: bool,
    #[serde(default, rename = "match")]
    pub matches: SeriesMatch,
    /// A shipped protocol; exactly one of `protocol` and `job`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub protocol: Option<Protocol>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub job: Option<JobTemplate>,
    /// Window of Secondary Capture results (projections, rotating MIPs); default the protocol's (`lung` for
    /// `lung`, `bone` otherwise), and without a protocol each image's own 0.5–99.5 percentile range.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window: Option<WindowPreset>,
    /// Also send the job's whole volume as a derived CT series.
    #[serde(default)]
    pub send_volume: bool,
    /// AE titles of configured peers that receive the DICOM results.
    #[serde(default)]
    pub destinations: Vec<String>,
}

/// Why a rule cannot be used.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RuleProblem {
    /// The name, the template or a range is wrong.
    Invalid(String),
    /// A pattern is not a valid wildcard pattern.
    BadPattern(String),
    /// A destination is not a configured peer.
    UnknownPeer(String),
}

impl RuleSpec {
    /// The steps and products the rule's job runs.
    pub fn template(&self) -> JobTemplate {
        match (&self.job, self.protocol) {
            (Some(t), _) => t.clone(),
            (None, Some(p)) => p.template(),
            (None, None) => JobTemplate::default(),
        }
    }

    /// The Secondary Capture window of the results.
    pub fn result_window(&self) -> Option<WindowPreset> {
        self.window.or(self.protocol.map(Protocol::window))
    }

    /// Check everything that needs no volume; `is_peer` says whether an AE title is a configured peer.
    pub fn validate(&self, is_peer: impl Fn(&str) -> bool) -> Result<(), RuleProblem> {
        self.validate_at(is_peer).map_err(|(p, _)| p)
    }

    /// [`RuleSpec::validate`], with the JSON Pointer (into the rule's body) of the field a problem is about.
    pub fn validate_at(&self, is_peer: impl Fn(&str) -> bool) -> Result<(), (RuleProblem, String)> {
        let invalid = |m: String, at: &str| Err((RuleProblem::Invalid(m), at.to_string()));
        if self.name.is_empty()
            || self.name.len() > MAX_NAME
            || !self
                .name
                .bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_' || b == b'-')
        {
            return invalid(
                format!(
                    "rule name {:?} must be 1–{MAX_NAME} characters of a–z, 0–9, `_` and `-`",
                    self.name.chars().take(80).collect::<String>()
                ),
                "/name",
            );
        }
        match (&self.protocol, &self.job) {
            (Some(_), Some(_)) => {
                return invalid("give either `protocol` or `job`, not both".into(), "/job");
            }
            (None, None) => {
                return invalid("a rule needs a `protocol` or a `job` template".into(), "");
            }
            _ => {}
        }
        let t = self.template();
        if t.products.is_empty() && !self.send_volume {
            return invalid(
                "the job template makes no product and `send_volume` is false: nothing to send"
                    .into(),
                "/job/products",
            );
        }
        if t.products.len() > MAX_ITEMS || t.steps.len() > MAX_ITEMS {
            let at = if t.steps.len() > MAX_ITEMS {
                "/job/steps"
            } else {
                "/job/products"
            };
            return invalid(
                format!("at most {MAX_ITEMS} steps and {MAX_ITEMS} products"),
                at,
            );
        }
        let m = &self.matches;
        for (what, p) in [
            ("modality", &m.modality),
            ("body_part", &m.body_part),
            ("series_description", &m.series_description),
        ] {
            if let Some(p) = p {
                check_pattern(what, p).map_err(|e| (e, format!("/match/{what}")))?;
            }
        }
        for (k, v) in m.image_type.iter().enumerate() {
            let at = format!("/match/image_type/{k}");
            check_pattern("image_type", v).map_err(|e| (e, at.clone()))?;
            if v.contains(['*', '?']) {
                return Err((
                    RuleProblem::BadPattern(
                        "`image_type` lists exact values, without wildcards".into(),
                    ),
                    at,
                ));
            }
        }
        for (what, r) in [
            ("slice_thickness_mm", &m.slice_thickness_mm),
            ("instances", &m.instances),
        ] {
            if let Some(p) = r.as_ref().and_then(|r| r.problem(what)) {
                return invalid(p, &format!("/match/{what}"));
            }
        }
        if let Some((k, ae)) = m
            .calling_ae
            .iter()
            .enumerate()
            .find(|(_, a)| !crate::config::dicom::is_ae_title(a))
        {
            return invalid(
                format!("calling AE {ae:?} is not a valid AE title"),
                &format!("/match/calling_ae/{k}"),
            );
        }
        if self.destinations.len() > MAX_DESTINATIONS {
            return invalid(
                format!("at most {MAX_DESTINATIONS} destinations"),
                "/destinations",
            );
        }
        if let Some((k, d)) = self
            .destinations
            .iter()
            .enumerate()
            .find(|(_, d)| !is_peer(d))
        {
            return Err((
                RuleProblem::UnknownPeer(format!(
                    "destination {:?} is not a configured DICOM peer (`dicom.peers`) or DICOMweb origin \
                     (`dicom.web_peers`)",
                    d.chars().take(80).collect::<String>()
                )),
                format!("/destinations/{k}"),
            ));
        }
        Ok(())
    }

    /// Whether `s` satisfies the rule's match.
    pub fn matches(&self, s: &SeriesFacts) -> bool {
        let m = &self.matches;
        let text = |p: &Option<String>, v: &Option<String>| match p {
            None => true,
            Some(p) => wildcard(p, v.as_deref().unwrap_or("")),
        };
        text(&m.modality, &s.modality)
            && text(&m.body_part, &s.body_part)
            && text(&m.series_description, &s.series_description)
            && m.image_type
                .iter()
                .all(|want| s.image_type.iter().any(|v| v.eq_ignore_ascii_case(want)))
            && m.slice_thickness_mm
                .is_none_or(|r| s.slice_thickness_mm.is_some_and(|t| r.contains(t)))
            && m.instances.is_none_or(|r| r.contains(s.instances as f64))
            && (m.calling_ae.is_empty()
                || s.calling_ae
                    .as_deref()
                    .is_some_and(|ae| m.calling_ae.iter().any(|a| a.trim() == ae.trim())))
    }
}

fn check_pattern(what: &str, p: &str) -> Result<(), RuleProblem> {
    if p.is_empty()
        || p.chars().count() > MAX_NAME
        || p.chars()
            .any(|c| c.is_control() || matches!(c, '\\' | '[' | ']'))
    {
        return Err(RuleProblem::BadPattern(format!(
            "`{what}` pattern {:?} must be 1–{MAX_NAME} characters without control characters, `\\`, `[` \
             or `]` (`*` and `?` are the wildcards)",
            p.chars().take(80).collect::<String>()
        )));
    }
    Ok(())
}

/// DICOM-style wildcard matching (`*`, `?`), ignoring case and surrounding spaces of the value.
pub fn wildcard(pattern: &str, value: &str) -> bool {
    let p: Vec<char> = pattern.to_uppercase().chars().collect();
    let v: Vec<char> = value.trim().to_uppercase().chars().collect();
    // Greedy matching with backtracking to the last star: linear in practice, no recursion.
    let (mut i, mut j) = (0, 0);
    let (mut star, mut mark) = (None, 0);
    while j < v.len() {
        if i < p.len() && (p[i] == '?' || p[i] == v[j]) {
            i += 1;
            j += 1;
        } else if i < p.len() && p[i] == '*' {
            star = Some(i);
            mark = j;
            i += 1;
        } else if let Some(s) = star {
            i = s + 1;
            mark += 1;
            j = mark;
        } else {
            return false;
        }
    }
    p[i..].iter().all(|&c| c == '*')
}

/// Where a rule comes from: the API (`POST /v1/rules`, editable) or the configuration file (`dicom.rules`,
/// read again at every start and read-only in the API).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RuleSource {
    Api,
    Config,
}

impl RuleSource {
    pub fn as_str(self) -> &'static str {
        match self {
            RuleSource::Api => "api",
            RuleSource::Config => "config",
        }
    }
}

/// A stored rule.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredRule {
    pub spec: RuleSpec,
    pub source: RuleSource,
    pub created_us: i64,
    pub updated_us: i64,
}

/// What rules look at in an arriving series.
#[derive(Debug, Clone, PartialEq, Default, Serialize)]
pub struct SeriesFacts {
    pub modality: Option<String>,
    pub body_part: Option<String>,
    pub series_description: Option<String>,
    pub image_type: Vec<String>,
    pub slice_thickness_mm: Option<f64>,
    pub instances: usize,
    /// The AE title that sent it by C-STORE; `None` for an HTTP upload.
    pub calling_ae: Option<String>,
}

/// The content hash of an assembled series: its UID and the SHA-256 of its assembled volume (which
/// changes whenever a slice's pixels, position or rescale change). The same series arriving again has the
/// same hash, so a rule does not run twice on it.
pub fn content_hash(s: &SeriesRecord) -> String {
    hex(&Sha256::digest(
        format!("{}|{}", s.series_uid, s.volume.sha256).as_bytes(),
    ))
}

#[cfg(test)]
mod tests;
