//! The INI-like metadata of vendor scans (`.xtekct`, SkyScan `.log`): `[Section]` headers and `key=value`
//! lines, parsed from `&str`. Lookups are typed and fail with the file and the key; every value taken is
//! recorded as [`Provenance`].

use std::path::{Path, PathBuf};

use super::{Provenance, ScanError};

/// A parsed metadata file: its sections in order, each with its `key=value` pairs (keys and values
/// trimmed; a key repeated within a section keeps its first value).
#[derive(Debug, Clone)]
pub struct Ini {
    pub file: PathBuf,
    sections: Vec<(String, Vec<(String, String)>)>,
    /// The values looked up so far, with their origin.
    pub taken: Vec<Provenance>,
}

impl Ini {
    /// Parse `text` (the contents of `file`). Lines without `=` outside comments are ignored; lines before
    /// the first header belong to the section named "".
    pub fn parse(file: &Path, text: &str) -> Ini {
        let mut sections: Vec<(String, Vec<(String, String)>)> = vec![(String::new(), Vec::new())];
        for line in text.lines() {
            let line = line.trim().trim_start_matches('\u{feff}');
            if line.is_empty() || line.starts_with(';') || line.starts_with('#') {
                continue;
            }
            if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
                sections.push((name.trim().to_string(), Vec::new()));
                continue;
            }
            if let Some((k, v)) = line.split_once('=')
                && let Some((_, pairs)) = sections.last_mut()
            {
                let k = k.trim();
                if !pairs.iter().any(|(key, _)| key == k) {
                    pairs.push((k.to_string(), v.trim().to_string()));
                }
            }
        }
        Ini {
            file: file.to_path_buf(),
            sections,
            taken: Vec::new(),
        }
    }

    /// Whether the file has a section of this name.
    pub fn has_section(&self, section: &str) -> bool {
        self.sections.iter().any(|(s, _)| s == section)
    }

    fn raw(&self, section: &str, key: &str) -> Option<&str> {
        self.sections
            .iter()
            .filter(|(s, _)| s == section)
            .flat_map(|(_, pairs)| pairs.iter())
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }

    fn origin(&self, section: &str, key: &str) -> String {
        let name = self.file.file_name().map_or_else(
            || self.file.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        format!("{name} [{section}] {key}")
    }

    /// The text of `key` in `section`, recorded as taken; `None` when absent.
    pub fn text(&mut self, section: &str, key: &str) -> Option<String> {
        let v = self.raw(section, key)?.to_string();
        self.taken.push(Provenance {
            key: key.to_string(),
            value: v.clone(),
            origin: self.origin(section, key),
        });
        Some(v)
    }

    /// A finite number, `None` when the key is absent; an error naming the file and key when it is not a
    /// finite number.
    pub fn number(&mut self, section: &str, key: &str) -> Result<Option<f64>, ScanError> {
        let Some(v) = self.text(section, key) else {
            return Ok(None);
        };
        match v.parse::<f64>() {
            Ok(x) if x.is_finite() => Ok(Some(x)),
            _ => Err(ScanError::invalid(
                &self.file,
                key,
                &v,
                "not a finite number",
            )),
        }
    }

    /// A required finite number.
    pub fn required(&mut self, section: &str, key: &str) -> Result<f64, ScanError> {
        self.number(section, key)?.ok_or_else(|| self.missing(key))
    }

    /// A required positive number (distances, pixel sizes).
    pub fn positive(&mut self, section: &str, key: &str) -> Result<f64, ScanError> {
        let x = self.required(section, key)?;
        if x > 0.0 {
            Ok(x)
        } else {
            Err(ScanError::invalid(
                &self.file,
                key,
                &x.to_string(),
                "must be positive",
            ))
        }
    }

    /// A required count in `1..=max`.
    pub fn count(&mut self, section: &str, key: &str, max: usize) -> Result<usize, ScanError> {
        let v = self.text(section, key).ok_or_else(|| self.missing(key))?;
        match v.parse::<usize>() {
            Ok(n) if (1..=max).contains(&n) => Ok(n),
            Ok(n) => Err(ScanError::invalid(
                &self.file,
                key,
                &v,
                format!("must be between 1 and {max}, got {n}"),
            )),
            Err(_) => Err(ScanError::invalid(
                &self.file,
                key,
                &v,
                "not a whole number",
            )),
        }
    }

    pub fn missing(&self, key: &str) -> ScanError {
        ScanError::Missing {
            file: self.file.clone(),
            key: key.to_string(),
        }
    }
}
