//! Queries over the instance index, pure (no I/O): the rows read from the database are grouped at the
//! query's level (patient, study, series or image), each group's attributes are taken from its newest
//! instance (ModalitiesInStudy and the counts from all of them), and the groups every key matches are
//! answered. What C-FIND answers and C-MOVE sends, and what QIDO-RS will answer.

use std::collections::{BTreeSet, HashMap, HashSet};

use super::matching::{Attr, BadKey, Key, Level, Matcher};
use crate::jobs::model::{IndexScope, IndexedInstance, StoredInstance};

/// A query: its level and its matching keys (universal keys included: they are returned).
#[derive(Debug, Clone, PartialEq)]
pub struct Query {
    pub level: Level,
    pub keys: Vec<Key>,
}

/// One matching entity: the values of its attributes (absent ones are not listed) and its instances.
#[derive(Debug, Clone, PartialEq)]
pub struct Found {
    pub values: HashMap<Attr, String>,
    pub instances: Vec<StoredInstance>,
}

impl Found {
    pub fn value(&self, attr: Attr) -> Option<&str> {
        self.values.get(&attr).map(String::as_str)
    }
}

impl Query {
    /// A query at `level` from `(tag, value)` keys; tags the index does not hold are left out (a front door
    /// echoes them empty).
    pub fn new(level: Level, keys: &[(u32, String)]) -> Result<Query, BadKey> {
        let keys = keys
            .iter()
            .filter_map(|(tag, v)| Attr::from_tag(*tag).map(|a| Key::parse(a, v)))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Query { level, keys })
    }

    /// The database read this query needs at most: single-valued study and series UIDs narrow it.
    pub fn scope(&self) -> IndexScope {
        let single = |attr| {
            self.keys.iter().find_map(|k| match &k.matcher {
                Matcher::Single(v) if k.attr == attr => Some(v.clone()),
                _ => None,
            })
        };
        IndexScope {
            study_uid: single(Attr::StudyInstanceUid),
            series_uid: single(Attr::SeriesInstanceUid),
        }
    }
}

/// The value of an attribute of one instance (counts and ModalitiesInStudy are per group: `None`).
pub fn instance_value(i: &IndexedInstance, attr: Attr) -> Option<String> {
    let s = |v: &Option<String>| v.clone();
    match attr {
        Attr::PatientId => s(&i.patient_id),
        Attr::PatientName => s(&i.patient_name),
        Attr::PatientBirthDate => s(&i.patient_birth_date),
        Attr::PatientSex => s(&i.patient_sex),
        Attr::StudyInstanceUid => Some(i.study_uid.clone()),
        Attr::StudyDate => s(&i.study_date),
        Attr::StudyTime => s(&i.study_time),
        Attr::AccessionNumber => s(&i.accession_number),
        Attr::StudyDescription => s(&i.study_description),
        Attr::ReferringPhysicianName => s(&i.referring_physician),
        Attr::StudyId => s(&i.study_id),
        Attr::SeriesInstanceUid => Some(i.series_uid.clone()),
        Attr::Modality => s(&i.modality),
        Attr::SeriesNumber => i.series_number.map(|n| n.to_string()),
        Attr::SeriesDescription => s(&i.series_description),
        Attr::BodyPartExamined => s(&i.body_part),
        Attr::SopClassUid => Some(i.sop_class_uid.clone()),
        Attr::SopInstanceUid => Some(i.sop_instance_uid.clone()),
        Attr::InstanceNumber => i.instance_number.map(|n| n.to_string()),
        Attr::ModalitiesInStudy
        | Attr::NumberOfPatientRelatedStudies
        | Attr::NumberOfStudyRelatedSeries
        | Attr::NumberOfStudyRelatedInstances
        | Attr::NumberOfSeriesRelatedInstances => None,
    }
}

fn group_key(i: &IndexedInstance, level: Level) -> String {
    match level {
        Level::Patient => i.patient_id.clone().unwrap_or_default(),
        Level::Study => i.study_uid.clone(),
        Level::Series => i.series_uid.clone(),
        Level::Image => i.sop_instance_uid.clone(),
    }
}

/// The values of a group: attributes at or above `level` from its newest instance, and the derived ones.
fn group_values(level: Level, members: &[StoredInstance]) -> HashMap<Attr, String> {
    let mut values = HashMap::new();
    // Each attribute from the newest instance that has it (a derived result may lack, say, StudyDate).
    for a in super::matching::ATTRS {
        if a.level() <= level
            && let Some(v) = members
                .iter()
                .find_map(|m| instance_value(&m.instance, *a).filter(|v| !v.is_empty()))
        {
            values.insert(*a, v);
        }
    }
    let distinct = |f: &dyn Fn(&IndexedInstance) -> Option<String>| {
        members
            .iter()
            .filter_map(|m| f(&m.instance))
            .collect::<BTreeSet<_>>()
    };
    match level {
        Level::Patient => {
            let studies = distinct(&|i| Some(i.study_uid.clone())).len();
            values.insert(Attr::NumberOfPatientRelatedStudies, studies.to_string());
        }
        Level::Study => {
            let modalities: Vec<String> = distinct(&|i| i.modality.clone()).into_iter().collect();
            if !modalities.is_empty() {
                values.insert(Attr::ModalitiesInStudy, modalities.join("\\"));
            }
            let series = distinct(&|i| Some(i.series_uid.clone())).len();
            values.insert(Attr::NumberOfStudyRelatedSeries, series.to_string());
            values.insert(
                Attr::NumberOfStudyRelatedInstances,
                members.len().to_string(),
            );
        }
        Level::Series => {
            values.insert(
                Attr::NumberOfSeriesRelatedInstances,
                members.len().to_string(),
            );
        }
        Level::Image => {}
    }
    values
}

/// Whether a group's values satisfy `key` (keys below the query level are not matched).
fn satisfies(key: &Key, level: Level, values: &HashMap<Attr, String>) -> bool {
    if key.attr.level() > level || key.matcher == Matcher::Universal {
        return true;
    }
    let value = values.get(&key.attr).map(String::as_str);
    if key.attr == Attr::ModalitiesInStudy {
        // Multi-valued on both sides: any requested modality among any of the study's.
        let wanted: Vec<Key> = match &key.matcher {
            Matcher::Single(v) | Matcher::Wildcard(v) => v
                .split('\\')
                .filter_map(|m| Key::parse(Attr::ModalitiesInStudy, m).ok())
                .collect(),
            _ => vec![key.clone()],
        };
        let have: Vec<&str> = value.map(|v| v.split('\\').collect()).unwrap_or_default();
        return wanted
            .iter()
            .any(|w| have.iter().any(|h| w.matches(Some(h))));
    }
    key.matches(value)
}

fn sort_key(level: Level, f: &Found) -> (String, i64, String) {
    let num = |a| {
        f.value(a)
            .and_then(|v| v.trim().parse::<i64>().ok())
            .unwrap_or(i64::MAX)
    };
    let text = |a| f.value(a).unwrap_or_default().to_string();
    match level {
        Level::Patient => (text(Attr::PatientId), 0, String::new()),
        Level::Study => (text(Attr::StudyDate), 0, text(Attr::StudyInstanceUid)),
        Level::Series => (
            text(Attr::StudyInstanceUid),
            num(Attr::SeriesNumber),
            text(Attr::SeriesInstanceUid),
        ),
        Level::Image => (
            text(Attr::SeriesInstanceUid),
            num(Attr::InstanceNumber),
            text(Attr::SopInstanceUid),
        ),
    }
}

/// Answer `query` over `rows` (newest first, as the index reads them). An instance indexed twice (the same
/// SOP Instance UID received again) counts once, as its newest copy.
pub fn run(rows: Vec<StoredInstance>, query: &Query) -> Vec<Found> {
    let mut seen = HashSet::new();
    let mut groups: Vec<(String, Vec<StoredInstance>)> = Vec::new();
    let mut index: HashMap<String, usize> = HashMap::new();
    for r in rows {
        if !seen.insert(r.instance.sop_instance_uid.clone()) {
            continue;
        }
        let k = group_key(&r.instance, query.level);
        match index.get(&k) {
            Some(&g) => groups[g].1.push(r),
            None => {
                index.insert(k.clone(), groups.len());
                groups.push((k, vec![r]));
            }
        }
    }
    let mut found: Vec<Found> = groups
        .into_iter()
        .filter_map(|(_, members)| {
            let values = group_values(query.level, &members);
            query
                .keys
                .iter()
                .all(|k| satisfies(k, query.level, &values))
                .then_some(Found {
                    values,
                    instances: members,
                })
        })
        .collect();
    found.sort_by_cached_key(|f| sort_key(query.level, f));
    found
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::{InstanceId, InstanceOwner, UploadId};

    fn row(study: &str, series: &str, sop: &str, modality: &str, n: i64) -> StoredInstance {
        StoredInstance {
            id: InstanceId::generate(),
            owner: InstanceOwner::Upload(UploadId::generate()),
            series_id: None,
            created_us: 0,
            instance: IndexedInstance {
                sop_class_uid: "1.2.840.10008.5.1.4.1.1.2".into(),
                sop_instance_uid: sop.into(),
                study_uid: study.into(),
                series_uid: series.into(),
                patient_id: Some("P1".into()),
                patient_name: Some("DOE^JANE".into()),
                study_date: Some(
                    if study == "1.1" {
                        "20200315"
                    } else {
                        "20210101"
                    }
                    .into(),
                ),
                modality: Some(modality.into()),
                series_number: Some(if series.ends_with('2') { 2 } else { 1 }),
                instance_number: Some(n),
                bytes: 10,
                ..IndexedInstance::default()
            },
            sha256: None,
        }
    }

    fn rows() -> Vec<StoredInstance> {
        vec![
            row("1.1", "1.1.2", "1.1.2.1", "OT", 1),
            row("1.1", "1.1.1", "1.1.1.2", "CT", 2),
            row("1.1", "1.1.1", "1.1.1.1", "CT", 1),
            row("2.1", "2.1.1", "2.1.1.1", "CT", 1),
            // An instance received again: counted once.
            row("2.1", "2.1.1", "2.1.1.1", "CT", 1),
        ]
    }

    fn q(level: Level, keys: &[(Attr, &str)]) -> Query {
        let keys: Vec<(u32, String)> = keys.iter().map(|(a, v)| (a.tag(), v.to_string())).collect();
        Query::new(level, &keys).unwrap()
    }

    #[test]
    fn studies_group_their_series_and_instances_and_derive_modalities() {
        let found = run(rows(), &q(Level::Study, &[(Attr::ModalitiesInStudy, "")]));
        assert_eq!(found.len(), 2);
        let s = &found[0];
        assert_eq!(s.value(Attr::StudyInstanceUid), Some("1.1"));
        assert_eq!(s.value(Attr::ModalitiesInStudy), Some("CT\\OT"));
        assert_eq!(s.value(Attr::NumberOfStudyRelatedSeries), Some("2"));
        assert_eq!(s.value(Attr::NumberOfStudyRelatedInstances), Some("3"));
        assert_eq!(
            found[1].value(Attr::NumberOfStudyRelatedInstances),
            Some("1")
        );
        assert_eq!(found[1].instances.len(), 1);
    }

    #[test]
    fn keys_filter_at_their_level_and_modalities_match_any_member() {
        let ot = run(
            rows(),
            &q(Level::Study, &[(Attr::ModalitiesInStudy, "MR\\OT")]),
        );
        assert_eq!(ot.len(), 1);
        assert_eq!(ot[0].value(Attr::StudyInstanceUid), Some("1.1"));
        let dated = run(rows(), &q(Level::Study, &[(Attr::StudyDate, "20210101-")]));
        assert_eq!(dated.len(), 1);
        assert_eq!(dated[0].value(Attr::StudyInstanceUid), Some("2.1"));
        let series = run(
            rows(),
            &q(
                Level::Series,
                &[(Attr::StudyInstanceUid, "1.1"), (Attr::Modality, "C*")],
            ),
        );
        assert_eq!(series.len(), 1);
        assert_eq!(series[0].value(Attr::SeriesInstanceUid), Some("1.1.1"));
        assert_eq!(
            series[0].value(Attr::NumberOfSeriesRelatedInstances),
            Some("2")
        );
        let images = run(
            rows(),
            &q(Level::Image, &[(Attr::SeriesInstanceUid, "1.1.1")]),
        );
        let uids: Vec<_> = images
            .iter()
            .map(|f| f.value(Attr::SopInstanceUid).unwrap())
            .collect();
        assert_eq!(
            uids,
            vec!["1.1.1.1", "1.1.1.2"],
            "ordered by instance number"
        );
        assert_eq!(images[0].value(Attr::InstanceNumber), Some("1"));
        let patients = run(rows(), &q(Level::Patient, &[(Attr::PatientName, "doe*")]));
        assert_eq!(patients.len(), 1);
        assert_eq!(
            patients[0].value(Attr::NumberOfPatientRelatedStudies),
            Some("2")
        );
    }

    #[test]
    fn single_uids_narrow_the_database_read() {
        let query = q(
            Level::Image,
            &[
                (Attr::StudyInstanceUid, "1.1"),
                (Attr::SeriesInstanceUid, "1.1.1\\1.1.2"),
            ],
        );
        assert_eq!(
            query.scope(),
            IndexScope {
                study_uid: Some("1.1".into()),
                series_uid: None
            }
        );
    }
}
