//! DICOMweb (PS3.18) over the instance index: QIDO-RS queries parsed into the same [`Query`] C-FIND runs and
//! answered in the DICOM JSON model, and the stored instances WADO-RS retrieves (a study, a series or one
//! instance). STOW-RS is in [`super::stow`].
//!
//! Query parameters: matching keys by keyword or tag (`PatientID=…`, `0020000D=…`) of the attributes the
//! index holds, at or above the query's level; `limit`, `offset`, `includefield` (keywords or tags,
//! comma-separated or repeated, or `all`), `fuzzymatching=false`. Anything else is refused, as is
//! `fuzzymatching=true` (not supported). Answers carry the attributes of the query's level (PS3.18 Table
//! 6.7.1-2), those of the levels above when the path does not fix them, the matched keys, what
//! `includefield` asks for, Specific Character Set `ISO_IR 192` (UTF-8) and a RetrieveURL.

use serde_json::{Map, Value, json};

use super::error::refused;
use super::matching::{ATTRS, Attr, Level};
use super::query::{Found, Query};
use super::{App, AppResult};
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::model::StoredInstance;

/// Where a QIDO-RS query was sent: its level and the UIDs its path fixes.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct QidoPath {
    pub study: Option<String>,
    pub series: Option<String>,
}

/// Which attributes an answer carries beyond the defaults.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Include {
    Defaults(Vec<Attr>),
    All,
}

/// A parsed QIDO-RS request.
#[derive(Debug, Clone, PartialEq)]
pub struct Qido {
    pub level: Level,
    pub path: QidoPath,
    pub query: Query,
    pub include: Include,
    pub limit: Option<usize>,
    pub offset: usize,
}

fn bad(detail: impl Into<String>) -> Problem {
    Problem::new(ErrorCode::InvalidQuery, detail)
}

/// Parse the query parameters `params` (decoded) of a QIDO-RS request at `level` on `path`.
pub fn parse_qido(
    level: Level,
    path: QidoPath,
    params: &[(String, String)],
) -> Result<Qido, Problem> {
    for uid in [&path.study, &path.series].into_iter().flatten() {
        if !crate::dicom::is_valid_uid(uid) {
            return Err(Problem::new(
                ErrorCode::InvalidId,
                format!("{uid:?} is not a UID"),
            ));
        }
    }
    let mut keys: Vec<(u32, String)> = Vec::new();
    let mut include = Include::Defaults(Vec::new());
    let (mut limit, mut offset) = (None, 0usize);
    for (name, value) in params {
        match name.as_str() {
            "limit" => {
                let n: usize = value
                    .parse()
                    .map_err(|_| bad(format!("limit {value:?} is not a count")))?;
                limit = Some(n);
            }
            "offset" => {
                offset = value
                    .parse()
                    .map_err(|_| bad(format!("offset {value:?} is not a count")))?;
            }
            "fuzzymatching" => match value.as_str() {
                "false" => {}
                "true" => {
                    return Err(bad(
                        "fuzzymatching=true is not supported: names match exactly, case-insensitively",
                    ));
                }
                _ => return Err(bad("fuzzymatching is true or false")),
            },
            "includefield" => {
                for f in value.split(',').map(str::trim).filter(|f| !f.is_empty()) {
                    if f == "all" {
                        include = Include::All;
                        continue;
                    }
                    let attr = Attr::from_name(f);
                    let is_tag = f.len() == 8 && f.bytes().all(|b| b.is_ascii_hexdigit());
                    match (attr, &mut include) {
                        (Some(a), Include::Defaults(list)) => list.push(a),
                        (Some(_), Include::All) => {}
                        // A tag ctrecon does not index: nothing to include.
                        (None, _) if is_tag => {}
                        (None, _) => {
                            return Err(bad(format!(
                                "includefield {f:?} is neither a tag nor a keyword ctrecon answers"
                            )));
                        }
                    }
                }
            }
            other => {
                let attr = Attr::from_name(other).ok_or_else(|| {
                    bad(format!(
                        "{other:?} is not a parameter or an attribute ctrecon matches on"
                    ))
                })?;
                if attr.level() > level {
                    return Err(bad(format!(
                        "{} is not an attribute of the {} level",
                        attr.keyword(),
                        level.as_str().to_lowercase()
                    )));
                }
                if attr.is_count() {
                    return Err(bad(format!("{} cannot be matched", attr.keyword())));
                }
                keys.push((attr.tag(), value.clone()));
            }
        }
    }
    let fixed = [
        (Attr::StudyInstanceUid, &path.study),
        (Attr::SeriesInstanceUid, &path.series),
    ];
    for (attr, uid) in fixed {
        if let Some(uid) = uid {
            keys.retain(|(t, _)| *t != attr.tag());
            keys.push((attr.tag(), uid.clone()));
        }
    }
    let query = Query::new(level, &keys).map_err(|e| bad(e.0))?;
    Ok(Qido {
        level,
        path,
        query,
        include,
        limit,
        offset,
    })
}

/// The attributes of `level` a QIDO-RS answer carries by default.
fn defaults(level: Level) -> &'static [Attr] {
    match level {
        Level::Patient => &[Attr::PatientName, Attr::PatientId],
        Level::Study => &[
            Attr::StudyDate,
            Attr::StudyTime,
            Attr::AccessionNumber,
            Attr::ModalitiesInStudy,
            Attr::ReferringPhysicianName,
            Attr::StudyDescription,
            Attr::PatientName,
            Attr::PatientId,
            Attr::PatientBirthDate,
            Attr::PatientSex,
            Attr::StudyInstanceUid,
            Attr::StudyId,
            Attr::NumberOfStudyRelatedSeries,
            Attr::NumberOfStudyRelatedInstances,
        ],
        Level::Series => &[
            Attr::Modality,
            Attr::SeriesDescription,
            Attr::SeriesInstanceUid,
            Attr::SeriesNumber,
            Attr::BodyPartExamined,
            Attr::NumberOfSeriesRelatedInstances,
            Attr::StudyInstanceUid,
        ],
        Level::Image => &[
            Attr::SopClassUid,
            Attr::SopInstanceUid,
            Attr::InstanceNumber,
            Attr::StudyInstanceUid,
            Attr::SeriesInstanceUid,
        ],
    }
}

impl Qido {
    /// The attributes of each answer.
    fn attributes(&self) -> Vec<Attr> {
        if self.include == Include::All {
            return ATTRS
                .iter()
                .copied()
                .filter(|a| a.level() <= self.level && *a != Attr::NumberOfPatientRelatedStudies)
                .collect();
        }
        let mut out: Vec<Attr> = defaults(self.level).to_vec();
        if self.level >= Level::Series && self.path.study.is_none() {
            out.extend_from_slice(defaults(Level::Study));
        }
        if self.level == Level::Image && self.path.series.is_none() {
            out.extend_from_slice(defaults(Level::Series));
        }
        out.extend(self.query.keys.iter().map(|k| k.attr));
        if let Include::Defaults(more) = &self.include {
            out.extend(more.iter().copied().filter(|a| a.level() <= self.level));
        }
        // Counts and ModalitiesInStudy are computed at their own level only.
        out.retain(|a| !(a.is_count() || *a == Attr::ModalitiesInStudy) || a.level() == self.level);
        out
    }
}

/// The path of a study, series or instance under `/dicom-web` (UIDs are digits and dots).
pub fn resource_path(study: &str, series: Option<&str>, instance: Option<&str>) -> String {
    let mut p = format!("/dicom-web/studies/{study}");
    if let Some(s) = series {
        p.push_str(&format!("/series/{s}"));
        if let Some(i) = instance {
            p.push_str(&format!("/instances/{i}"));
        }
    }
    p
}

/// The JSON model of one attribute value.
fn attr_json(attr: Attr, value: &str) -> Value {
    let vr = attr.vr_name();
    let values: Vec<Value> = match vr {
        "IS" => value
            .split('\\')
            .map(|v| {
                v.trim()
                    .parse::<i64>()
                    .map(|n| json!(n))
                    .unwrap_or(Value::Null)
            })
            .collect(),
        "PN" => vec![json!({ "Alphabetic": value })],
        _ => value.split('\\').map(|v| json!(v.trim())).collect(),
    };
    json!({ "vr": vr, "Value": values })
}

/// One QIDO-RS answer: the attributes of `found`, with its RetrieveURL under `base` (`http://host:port`).
pub fn found_json(q: &Qido, found: &Found, base: &str) -> Value {
    let mut m = Map::new();
    m.insert(
        "00080005".into(),
        json!({"vr": "CS", "Value": ["ISO_IR 192"]}),
    );
    for a in q.attributes() {
        let key = format!("{:08X}", a.tag());
        let v = match found.value(a) {
            Some(v) => attr_json(a, v),
            None => json!({ "vr": a.vr_name() }),
        };
        m.insert(key, v);
    }
    let study = found.value(Attr::StudyInstanceUid).unwrap_or_default();
    let url = match q.level {
        Level::Patient | Level::Study => resource_path(study, None, None),
        Level::Series => resource_path(study, found.value(Attr::SeriesInstanceUid), None),
        Level::Image => resource_path(
            study,
            found.value(Attr::SeriesInstanceUid),
            found.value(Attr::SopInstanceUid),
        ),
    };
    m.insert(
        "00081190".into(),
        json!({"vr": "UR", "Value": [format!("{base}{url}")]}),
    );
    Value::Object(m)
}

impl App {
    /// Answer a QIDO-RS query: the matches after `offset`, at most `limit` of them.
    pub async fn qido(&self, q: &Qido) -> AppResult<Vec<Found>> {
        let found = self.find_instances(&q.query).await?;
        Ok(found
            .into_iter()
            .skip(q.offset)
            .take(q.limit.unwrap_or(usize::MAX))
            .collect())
    }

    /// The instances WADO-RS retrieves for a study, a series of it or one instance of that series (the
    /// newest copy of each, in series then instance-number order); refused when there is none.
    pub async fn wado_instances(
        &self,
        study: &str,
        series: Option<&str>,
        instance: Option<&str>,
    ) -> AppResult<Vec<StoredInstance>> {
        let mut keys = vec![(Attr::StudyInstanceUid.tag(), study.to_string())];
        if let Some(s) = series {
            keys.push((Attr::SeriesInstanceUid.tag(), s.to_string()));
        }
        if let Some(i) = instance {
            keys.push((Attr::SopInstanceUid.tag(), i.to_string()));
        }
        let uid_ok = |u: &str| crate::dicom::is_valid_uid(u);
        if !uid_ok(study) || !series.is_none_or(uid_ok) || !instance.is_none_or(uid_ok) {
            return Err(refused(ErrorCode::InvalidId, "a UID is malformed"));
        }
        let query =
            Query::new(Level::Image, &keys).map_err(|e| refused(ErrorCode::InvalidQuery, e.0))?;
        let found = self.find_instances(&query).await?;
        let out: Vec<StoredInstance> = found
            .into_iter()
            .filter_map(|f| f.instances.into_iter().next())
            .collect();
        if out.is_empty() {
            let what = match (series, instance) {
                (_, Some(i)) => format!("instance {i}"),
                (Some(s), None) => format!("series {s}"),
                (None, None) => format!("study {study}"),
            };
            return Err(refused(
                ErrorCode::DicomwebNotFound,
                format!("ctrecon holds no {what} in study {study}"),
            ));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(pairs: &[(&str, &str)]) -> Vec<(String, String)> {
        pairs
            .iter()
            .map(|(a, b)| (a.to_string(), b.to_string()))
            .collect()
    }

    #[test]
    fn parameters_become_keys_limits_and_includes() {
        let q = parse_qido(
            Level::Series,
            QidoPath {
                study: Some("1.2.3".into()),
                series: None,
            },
            &p(&[
                ("Modality", "CT"),
                ("0008103E", "bone*"),
                ("limit", "5"),
                ("offset", "2"),
                ("includefield", "PatientName,00101010"),
                ("fuzzymatching", "false"),
            ]),
        )
        .unwrap();
        assert_eq!((q.limit, q.offset), (Some(5), 2));
        let attrs: Vec<Attr> = q.query.keys.iter().map(|k| k.attr).collect();
        assert_eq!(
            attrs,
            vec![
                Attr::Modality,
                Attr::SeriesDescription,
                Attr::StudyInstanceUid
            ]
        );
        assert_eq!(q.include, Include::Defaults(vec![Attr::PatientName]));
        let a = q.attributes();
        assert!(a.contains(&Attr::PatientName) && a.contains(&Attr::SeriesNumber));
        assert!(
            !a.contains(&Attr::StudyDate),
            "the path fixes the study: its attributes are not repeated"
        );
    }

    #[test]
    fn unknown_parameters_fuzzy_matching_and_keys_below_the_level_are_refused() {
        let none = QidoPath::default();
        for bad in [
            ("PatientAge", "30"),
            ("fuzzymatching", "true"),
            ("limit", "-1"),
            ("includefield", "NoSuchKeyword"),
            ("Modality", "CT"),
            ("StudyDate", "2020-13"),
        ] {
            assert!(
                parse_qido(Level::Study, none.clone(), &p(&[bad])).is_err(),
                "{bad:?} should be refused at the study level"
            );
        }
        let all = parse_qido(Level::Study, none, &p(&[("includefield", "all")])).unwrap();
        assert_eq!(all.include, Include::All);
        assert!(all.attributes().contains(&Attr::PatientBirthDate));
    }

    #[test]
    fn answers_use_the_json_model() {
        let q = parse_qido(Level::Study, QidoPath::default(), &[]).unwrap();
        let mut values = std::collections::HashMap::new();
        values.insert(Attr::StudyInstanceUid, "1.2.3".to_string());
        values.insert(Attr::PatientName, "DOE^JANE".to_string());
        values.insert(Attr::ModalitiesInStudy, "CT\\OT".to_string());
        values.insert(Attr::NumberOfStudyRelatedInstances, "12".to_string());
        let f = Found {
            values,
            instances: vec![],
        };
        let j = found_json(&q, &f, "http://h:1");
        assert_eq!(j["0020000D"], json!({"vr": "UI", "Value": ["1.2.3"]}));
        assert_eq!(
            j["00100010"],
            json!({"vr": "PN", "Value": [{"Alphabetic": "DOE^JANE"}]})
        );
        assert_eq!(j["00080061"]["Value"], json!(["CT", "OT"]));
        assert_eq!(j["00201208"], json!({"vr": "IS", "Value": [12]}));
        assert_eq!(j["00080020"], json!({"vr": "DA"}), "absent: no Value");
        assert_eq!(
            j["00081190"]["Value"][0],
            "http://h:1/dicom-web/studies/1.2.3"
        );
        assert_eq!(j["00080005"]["Value"][0], "ISO_IR 192");
    }
}
