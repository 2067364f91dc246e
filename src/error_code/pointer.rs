//! JSON Pointers (RFC 6901) naming the fields of a refused request body.

/// The JSON Pointer of `segments` under `base` (a pointer itself), each segment escaped (`~` → `~0`,
/// `/` → `~1`).
pub fn json_pointer<'a>(base: &str, segments: impl IntoIterator<Item = &'a str>) -> String {
    let mut out = base.to_string();
    for s in segments {
        out.push('/');
        out.push_str(&s.replace('~', "~0").replace('/', "~1"));
    }
    out
}

/// The JSON Pointer of a field path as the validators name fields (`detector.nu`, `centre_mm[0]`,
/// `angles.degrees[3]`) under `base`.
pub fn field_pointer(base: &str, path: &str) -> String {
    let mut segments = Vec::new();
    for part in path.split('.').filter(|p| !p.is_empty()) {
        let mut rest = part;
        if let Some(open) = rest.find('[') {
            segments.push(&rest[..open]);
            rest = &rest[open..];
            while let Some(tail) = rest.strip_prefix('[') {
                let Some(close) = tail.find(']') else { break };
                segments.push(&tail[..close]);
                rest = &tail[close + 1..];
            }
        } else {
            segments.push(rest);
        }
    }
    json_pointer(base, segments.into_iter().filter(|s| !s.is_empty()))
}
