//! Attribute matching of DICOM queries (PS3.4 C.2.2.2), pure: no I/O, no DICOM crate. Shared by C-FIND and,
//! later, QIDO-RS: a front door turns its query into `(tag, value)` keys, [`Key::parse`] makes each a typed
//! [`Matcher`], and [`Matcher::matches`] decides against an attribute value of the index.
//!
//! Supported kinds: universal (empty value, or `*` alone), single value (exact; trailing spaces ignored),
//! wildcard (`*` any run, `?` one character; not for UI, DA, TM, DT), list of UIDs (backslash-separated,
//! UI only), range (`A-B`, `A-`, `-B` for DA, TM and DT). Values are case-sensitive except PN, which matches
//! case-insensitively (as Orthanc does by default). An entity whose value is absent or empty matches only a
//! universal key. Sequence matching is not supported.

/// Query/Retrieve level (0008,0052).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Level {
    Patient,
    Study,
    Series,
    Image,
}

impl Level {
    /// The level named by a Query/Retrieve Level value (`PATIENT`, `STUDY`, `SERIES`, `IMAGE`).
    pub fn parse(s: &str) -> Option<Level> {
        match s.trim() {
            "PATIENT" => Some(Level::Patient),
            "STUDY" => Some(Level::Study),
            "SERIES" => Some(Level::Series),
            "IMAGE" => Some(Level::Image),
            _ => None,
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Level::Patient => "PATIENT",
            Level::Study => "STUDY",
            Level::Series => "SERIES",
            Level::Image => "IMAGE",
        }
    }
}

/// Value representations that matter to matching.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Vr {
    /// Unique identifier: single value or a list, never wildcards.
    Ui,
    Da,
    Tm,
    Dt,
    /// Person name: case-insensitive.
    Pn,
    /// Any other string (LO, SH, CS, IS, …).
    Text,
}

/// The attributes the index holds and answers, by level.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Attr {
    PatientId,
    PatientName,
    PatientBirthDate,
    PatientSex,
    NumberOfPatientRelatedStudies,
    StudyInstanceUid,
    StudyDate,
    StudyTime,
    AccessionNumber,
    StudyDescription,
    ReferringPhysicianName,
    StudyId,
    ModalitiesInStudy,
    NumberOfStudyRelatedSeries,
    NumberOfStudyRelatedInstances,
    SeriesInstanceUid,
    Modality,
    SeriesNumber,
    SeriesDescription,
    BodyPartExamined,
    NumberOfSeriesRelatedInstances,
    SopClassUid,
    SopInstanceUid,
    InstanceNumber,
}

/// Every attribute, in tag order.
pub const ATTRS: &[Attr] = &[
    Attr::SopClassUid,
    Attr::SopInstanceUid,
    Attr::StudyDate,
    Attr::StudyTime,
    Attr::AccessionNumber,
    Attr::Modality,
    Attr::ModalitiesInStudy,
    Attr::ReferringPhysicianName,
    Attr::StudyDescription,
    Attr::SeriesDescription,
    Attr::PatientName,
    Attr::PatientId,
    Attr::PatientBirthDate,
    Attr::PatientSex,
    Attr::BodyPartExamined,
    Attr::StudyInstanceUid,
    Attr::SeriesInstanceUid,
    Attr::StudyId,
    Attr::SeriesNumber,
    Attr::InstanceNumber,
    Attr::NumberOfPatientRelatedStudies,
    Attr::NumberOfStudyRelatedSeries,
    Attr::NumberOfStudyRelatedInstances,
    Attr::NumberOfSeriesRelatedInstances,
];

impl Attr {
    /// The attribute's tag as `(group << 16) | element`.
    pub fn tag(self) -> u32 {
        match self {
            Attr::SopClassUid => 0x0008_0016,
            Attr::SopInstanceUid => 0x0008_0018,
            Attr::StudyDate => 0x0008_0020,
            Attr::StudyTime => 0x0008_0030,
            Attr::AccessionNumber => 0x0008_0050,
            Attr::Modality => 0x0008_0060,
            Attr::ModalitiesInStudy => 0x0008_0061,
            Attr::ReferringPhysicianName => 0x0008_0090,
            Attr::StudyDescription => 0x0008_1030,
            Attr::SeriesDescription => 0x0008_103E,
            Attr::PatientName => 0x0010_0010,
            Attr::PatientId => 0x0010_0020,
            Attr::PatientBirthDate => 0x0010_0030,
            Attr::PatientSex => 0x0010_0040,
            Attr::BodyPartExamined => 0x0018_0015,
            Attr::StudyInstanceUid => 0x0020_000D,
            Attr::SeriesInstanceUid => 0x0020_000E,
            Attr::StudyId => 0x0020_0010,
            Attr::SeriesNumber => 0x0020_0011,
            Attr::InstanceNumber => 0x0020_0013,
            Attr::NumberOfPatientRelatedStudies => 0x0020_1200,
            Attr::NumberOfStudyRelatedSeries => 0x0020_1206,
            Attr::NumberOfStudyRelatedInstances => 0x0020_1208,
            Attr::NumberOfSeriesRelatedInstances => 0x0020_1209,
        }
    }

    /// The attribute's keyword (PS3.6), as QIDO-RS names it.
    pub fn keyword(self) -> &'static str {
        match self {
            Attr::SopClassUid => "SOPClassUID",
            Attr::SopInstanceUid => "SOPInstanceUID",
            Attr::StudyDate => "StudyDate",
            Attr::StudyTime => "StudyTime",
            Attr::AccessionNumber => "AccessionNumber",
            Attr::Modality => "Modality",
            Attr::ModalitiesInStudy => "ModalitiesInStudy",
            Attr::ReferringPhysicianName => "ReferringPhysicianName",
            Attr::StudyDescription => "StudyDescription",
            Attr::SeriesDescription => "SeriesDescription",
            Attr::PatientName => "PatientName",
            Attr::PatientId => "PatientID",
            Attr::PatientBirthDate => "PatientBirthDate",
            Attr::PatientSex => "PatientSex",
            Attr::BodyPartExamined => "BodyPartExamined",
            Attr::StudyInstanceUid => "StudyInstanceUID",
            Attr::SeriesInstanceUid => "SeriesInstanceUID",
            Attr::StudyId => "StudyID",
            Attr::SeriesNumber => "SeriesNumber",
            Attr::InstanceNumber => "InstanceNumber",
            Attr::NumberOfPatientRelatedStudies => "NumberOfPatientRelatedStudies",
            Attr::NumberOfStudyRelatedSeries => "NumberOfStudyRelatedSeries",
            Attr::NumberOfStudyRelatedInstances => "NumberOfStudyRelatedInstances",
            Attr::NumberOfSeriesRelatedInstances => "NumberOfSeriesRelatedInstances",
        }
    }

    /// The attribute named by a keyword or by eight hexadecimal digits (`0020000D`).
    pub fn from_name(name: &str) -> Option<Attr> {
        if name.len() == 8
            && let Ok(tag) = u32::from_str_radix(name, 16)
        {
            return Attr::from_tag(tag);
        }
        ATTRS.iter().copied().find(|a| a.keyword() == name)
    }

    /// The attribute's value representation (PS3.6), as the DICOM JSON model names it.
    pub fn vr_name(self) -> &'static str {
        match self {
            Attr::SopClassUid
            | Attr::SopInstanceUid
            | Attr::StudyInstanceUid
            | Attr::SeriesInstanceUid => "UI",
            Attr::StudyDate | Attr::PatientBirthDate => "DA",
            Attr::StudyTime => "TM",
            Attr::PatientName | Attr::ReferringPhysicianName => "PN",
            Attr::AccessionNumber | Attr::StudyId => "SH",
            Attr::Modality
            | Attr::ModalitiesInStudy
            | Attr::PatientSex
            | Attr::BodyPartExamined => "CS",
            Attr::PatientId | Attr::StudyDescription | Attr::SeriesDescription => "LO",
            Attr::SeriesNumber
            | Attr::InstanceNumber
            | Attr::NumberOfPatientRelatedStudies
            | Attr::NumberOfStudyRelatedSeries
            | Attr::NumberOfStudyRelatedInstances
            | Attr::NumberOfSeriesRelatedInstances => "IS",
        }
    }

    pub fn from_tag(tag: u32) -> Option<Attr> {
        ATTRS.iter().copied().find(|a| a.tag() == tag)
    }

    pub fn vr(self) -> Vr {
        match self {
            Attr::SopClassUid
            | Attr::SopInstanceUid
            | Attr::StudyInstanceUid
            | Attr::SeriesInstanceUid => Vr::Ui,
            Attr::StudyDate | Attr::PatientBirthDate => Vr::Da,
            Attr::StudyTime => Vr::Tm,
            Attr::PatientName | Attr::ReferringPhysicianName => Vr::Pn,
            _ => Vr::Text,
        }
    }

    /// The level the attribute belongs to.
    pub fn level(self) -> Level {
        match self {
            Attr::PatientId
            | Attr::PatientName
            | Attr::PatientBirthDate
            | Attr::PatientSex
            | Attr::NumberOfPatientRelatedStudies => Level::Patient,
            Attr::StudyInstanceUid
            | Attr::StudyDate
            | Attr::StudyTime
            | Attr::AccessionNumber
            | Attr::StudyDescription
            | Attr::ReferringPhysicianName
            | Attr::StudyId
            | Attr::ModalitiesInStudy
            | Attr::NumberOfStudyRelatedSeries
            | Attr::NumberOfStudyRelatedInstances => Level::Study,
            Attr::SeriesInstanceUid
            | Attr::Modality
            | Attr::SeriesNumber
            | Attr::SeriesDescription
            | Attr::BodyPartExamined
            | Attr::NumberOfSeriesRelatedInstances => Level::Series,
            Attr::SopClassUid | Attr::SopInstanceUid | Attr::InstanceNumber => Level::Image,
        }
    }

    /// The unique key of a level.
    pub fn unique_key(level: Level) -> Attr {
        match level {
            Level::Patient => Attr::PatientId,
            Level::Study => Attr::StudyInstanceUid,
            Level::Series => Attr::SeriesInstanceUid,
            Level::Image => Attr::SopInstanceUid,
        }
    }

    /// Counts computed by the index (they are returned, never matched).
    pub fn is_count(self) -> bool {
        matches!(
            self,
            Attr::NumberOfPatientRelatedStudies
                | Attr::NumberOfStudyRelatedSeries
                | Attr::NumberOfStudyRelatedInstances
                | Attr::NumberOfSeriesRelatedInstances
        )
    }
}

/// How one key matches (PS3.4 C.2.2.2).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Matcher {
    Universal,
    Single(String),
    Wildcard(String),
    UidList(Vec<String>),
    /// Inclusive bounds, normalised for comparison as text; `None` is open.
    Range(Option<String>, Option<String>),
}

/// A key the query cannot be run with.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct BadKey(pub String);

/// One matching key of a query.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Key {
    pub attr: Attr,
    pub matcher: Matcher,
}

fn normalise_date(s: &str) -> Option<String> {
    let d: String = s.chars().filter(|c| *c != '.').collect();
    (d.len() == 8 && d.bytes().all(|b| b.is_ascii_digit())).then_some(d)
}

/// A time as `HHMMSS.FFFFFF`, missing components filled with `fill`.
fn normalise_time(s: &str, fill: char) -> Option<String> {
    let s: String = s.chars().filter(|c| *c != ':').collect();
    let (hms, frac) = match s.split_once('.') {
        Some((a, b)) => (a.to_string(), b.to_string()),
        None => (s.clone(), String::new()),
    };
    let ok = |t: &str, max: usize| t.len() <= max && t.bytes().all(|b| b.is_ascii_digit());
    if hms.is_empty() || hms.len() % 2 == 1 || !ok(&hms, 6) || !ok(&frac, 6) {
        return None;
    }
    let pad = |t: &str, n: usize| {
        let mut t = t.to_string();
        while t.len() < n {
            t.push(fill);
        }
        t
    };
    Some(format!("{}.{}", pad(&hms, 6), pad(&frac, 6)))
}

/// A date-time as `YYYYMMDDHHMMSS.FFFFFF` (a UTC offset is ignored), missing components filled with `fill`.
fn normalise_datetime(s: &str, fill: char) -> Option<String> {
    let s = s.split(['+', '-']).next().unwrap_or_default();
    if !s.is_ascii() || s.len() < 4 || !s.bytes().take(4).all(|b| b.is_ascii_digit()) {
        return None;
    }
    let (date, time) = s.split_at(s.len().min(8));
    if !date.bytes().all(|b| b.is_ascii_digit()) || date.len() % 2 == 1 {
        return None;
    }
    let mut d = date.to_string();
    while d.len() < 8 {
        d.push(fill);
    }
    let t = if time.is_empty() {
        format!("{0}{0}{0}{0}{0}{0}.{0}{0}{0}{0}{0}{0}", fill)
    } else {
        normalise_time(time, fill)?
    };
    Some(d + &t)
}

/// The comparable form of a value of `vr` (dates, times, date-times), or `None` when it is malformed.
fn comparable(vr: Vr, s: &str, upper: bool) -> Option<String> {
    let fill = if upper { '9' } else { '0' };
    match vr {
        Vr::Da => normalise_date(s),
        Vr::Tm => normalise_time(s, fill),
        Vr::Dt => normalise_datetime(s, fill),
        _ => None,
    }
}

impl Key {
    /// The matcher of `value` (as the query carried it, padding included) for `attr`.
    pub fn parse(attr: Attr, value: &str) -> Result<Key, BadKey> {
        let v = value.trim_matches(|c: char| c == ' ' || c == '\0');
        let vr = attr.vr();
        let matcher = if v.is_empty() || v == "*" || attr.is_count() {
            Matcher::Universal
        } else {
            match vr {
                Vr::Ui if v.contains('\\') => Matcher::UidList(
                    v.split('\\')
                        .map(|u| u.trim().to_string())
                        .filter(|u| !u.is_empty())
                        .collect(),
                ),
                Vr::Ui => Matcher::Single(v.to_string()),
                Vr::Da | Vr::Tm | Vr::Dt if v.contains('-') && (vr != Vr::Dt || is_range_dt(v)) => {
                    let (lo, hi) = v.split_once('-').unwrap_or((v, ""));
                    let bound = |s: &str, upper| -> Result<Option<String>, BadKey> {
                        if s.trim().is_empty() {
                            return Ok(None);
                        }
                        comparable(vr, s.trim(), upper)
                            .map(Some)
                            .ok_or_else(|| BadKey(format!("{s:?} is not a valid bound of a range")))
                    };
                    let (lo, hi) = (bound(lo, false)?, bound(hi, true)?);
                    if lo.is_none() && hi.is_none() {
                        return Err(BadKey("a range needs at least one bound".into()));
                    }
                    Matcher::Range(lo, hi)
                }
                Vr::Da | Vr::Tm | Vr::Dt => {
                    if comparable(vr, v, false).is_none() {
                        return Err(BadKey(format!("{v:?} is not a valid date or time")));
                    }
                    Matcher::Single(v.to_string())
                }
                _ if v.contains(['*', '?']) => Matcher::Wildcard(v.to_string()),
                _ => Matcher::Single(v.to_string()),
            }
        };
        Ok(Key { attr, matcher })
    }

    /// Whether an entity whose value of this key's attribute is `value` matches.
    pub fn matches(&self, value: Option<&str>) -> bool {
        self.matcher.matches(self.attr.vr(), value)
    }
}

/// A DT value with a `-` is a range unless the `-` starts a UTC offset (`…-0500`, no second date).
fn is_range_dt(v: &str) -> bool {
    let (lo, hi) = v.split_once('-').unwrap_or((v, ""));
    lo.is_empty() || hi.is_empty() || (hi.len() >= 4 && !(lo.len() >= 8 && hi.len() == 4))
}

/// `*` and `?` against `text` (no regex: an explicit backtracking walk, linear in practice).
fn wildcard(pattern: &[char], text: &[char]) -> bool {
    let (mut p, mut t) = (0, 0);
    let (mut star, mut mark) = (None, 0);
    while t < text.len() {
        if p < pattern.len() && (pattern[p] == '?' || pattern[p] == text[t]) {
            p += 1;
            t += 1;
        } else if p < pattern.len() && pattern[p] == '*' {
            star = Some(p);
            mark = t;
            p += 1;
        } else if let Some(s) = star {
            p = s + 1;
            mark += 1;
            t = mark;
        } else {
            return false;
        }
    }
    pattern[p..].iter().all(|c| *c == '*')
}

impl Matcher {
    /// Whether a value of `vr` matches; an absent or empty value matches only [`Matcher::Universal`].
    pub fn matches(&self, vr: Vr, value: Option<&str>) -> bool {
        if *self == Matcher::Universal {
            return true;
        }
        let Some(value) = value
            .map(|v| v.trim_matches(|c: char| c == ' ' || c == '\0'))
            .filter(|v| !v.is_empty())
        else {
            return false;
        };
        let fold = |s: &str| {
            if vr == Vr::Pn {
                s.to_uppercase()
            } else {
                s.to_string()
            }
        };
        match self {
            Matcher::Universal => true,
            Matcher::Single(s) => match vr {
                Vr::Da | Vr::Tm | Vr::Dt => {
                    comparable(vr, s, false).is_some()
                        && comparable(vr, s, false) == comparable(vr, value, false)
                }
                _ => fold(s) == fold(value),
            },
            Matcher::Wildcard(p) => {
                let p: Vec<char> = fold(p).chars().collect();
                let t: Vec<char> = fold(value).chars().collect();
                wildcard(&p, &t)
            }
            Matcher::UidList(list) => list.iter().any(|u| u == value),
            Matcher::Range(lo, hi) => {
                let Some(v) = comparable(vr, value, false) else {
                    return false;
                };
                lo.as_ref().is_none_or(|lo| *lo <= v) && hi.as_ref().is_none_or(|hi| v <= *hi)
            }
        }
    }
}

#[cfg(test)]
mod tests;
