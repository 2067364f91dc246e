//! `multipart/related` bodies (RFC 2046 §5.1, RFC 2387) as DICOMweb carries DICOM instances in them: a push
//! parser fed chunk by chunk that emits the parts' headers and data as they arrive, holding no more than a
//! chunk and one delimiter, so memory stays flat in the body size; and the parameters of a `Content-Type`.
//! Pure: no I/O and no DICOM crate.

/// Why a multipart body cannot be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MultipartError {
    #[error(
        "the boundary is empty, longer than {MAX_BOUNDARY} characters or has characters RFC 2046 forbids"
    )]
    BadBoundary,
    #[error("the body has no part delimited by its boundary")]
    NoDelimiter,
    #[error("the headers of a part exceed {0} bytes")]
    HeadersTooLong(usize),
    #[error("a header line of a part is malformed")]
    BadHeader,
    #[error("the body ends before its closing delimiter")]
    Truncated,
}

/// One part's headers, names in lower case, values trimmed.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PartHeaders(pub Vec<(String, String)>);

impl PartHeaders {
    pub fn get(&self, name: &str) -> Option<&str> {
        self.0
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }
}

/// What a chunk of the body revealed, in order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Event {
    /// A part starts.
    Part(PartHeaders),
    /// Bytes of the current part.
    Data(Vec<u8>),
    /// The current part ended.
    PartEnd,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    Preamble,
    AfterDelimiter,
    Headers,
    Body,
    Done,
}

/// A streaming parser of one multipart body.
#[derive(Debug)]
pub struct Parser {
    /// `CRLF--boundary`.
    delimiter: Vec<u8>,
    buf: Vec<u8>,
    state: State,
    max_header_bytes: usize,
}

/// Longest boundary accepted. RFC 2046 §5.1.1 says 70, but Orthanc's DICOMweb client sends 73 characters.
pub const MAX_BOUNDARY: usize = 200;

/// Whether `b` is a valid boundary (RFC 2046 §5.1.1: `bchars`, not ending in a space; up to [`MAX_BOUNDARY`]
/// characters rather than 70, to accept what real clients send).
pub fn valid_boundary(b: &str) -> bool {
    !b.is_empty()
        && b.len() <= MAX_BOUNDARY
        && !b.ends_with(' ')
        && b.bytes()
            .all(|c| c.is_ascii_alphanumeric() || b"'()+_,-./:=? ".contains(&c))
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    if needle.is_empty() || hay.len() < needle.len() {
        return None;
    }
    let first = needle[0];
    (0..=hay.len() - needle.len()).find(|&i| hay[i] == first && &hay[i..i + needle.len()] == needle)
}

impl Parser {
    /// A parser of a body delimited by `boundary`; part headers longer than `max_header_bytes` are refused.
    pub fn new(boundary: &str, max_header_bytes: usize) -> Result<Parser, MultipartError> {
        if !valid_boundary(boundary) {
            return Err(MultipartError::BadBoundary);
        }
        let mut delimiter = b"\r\n--".to_vec();
        delimiter.extend_from_slice(boundary.as_bytes());
        Ok(Parser {
            delimiter,
            // The first delimiter may open the body without a preceding line break.
            buf: b"\r\n".to_vec(),
            state: State::Preamble,
            max_header_bytes,
        })
    }

    /// Whether the closing delimiter was read.
    pub fn done(&self) -> bool {
        self.state == State::Done
    }

    /// Feed the next chunk; returns what it completed.
    pub fn feed(&mut self, chunk: &[u8]) -> Result<Vec<Event>, MultipartError> {
        let mut out = Vec::new();
        if self.state == State::Done {
            return Ok(out); // the epilogue is ignored
        }
        self.buf.extend_from_slice(chunk);
        loop {
            match self.state {
                State::Preamble => match find(&self.buf, &self.delimiter) {
                    Some(i) => {
                        self.buf.drain(..i + self.delimiter.len());
                        self.state = State::AfterDelimiter;
                    }
                    None => {
                        let keep = self.delimiter.len() - 1;
                        let cut = self.buf.len().saturating_sub(keep);
                        self.buf.drain(..cut);
                        return Ok(out);
                    }
                },
                State::AfterDelimiter => {
                    // `--` closes the body; otherwise optional padding, then CRLF.
                    if self.buf.len() < 2 {
                        return Ok(out);
                    }
                    if self.buf.starts_with(b"--") {
                        self.state = State::Done;
                        self.buf.clear();
                        return Ok(out);
                    }
                    match find(&self.buf, b"\r\n") {
                        Some(i) if self.buf[..i].iter().all(|c| *c == b' ' || *c == b'\t') => {
                            self.buf.drain(..i + 2);
                            self.state = State::Headers;
                        }
                        Some(_) => return Err(MultipartError::BadHeader),
                        None if self.buf.len() > 256 => return Err(MultipartError::BadHeader),
                        None => return Ok(out),
                    }
                }
                State::Headers => {
                    let end = if self.buf.starts_with(b"\r\n") {
                        Some((0, 2))
                    } else {
                        find(&self.buf, b"\r\n\r\n").map(|i| (i, i + 4))
                    };
                    let Some((end, skip)) = end else {
                        if self.buf.len() > self.max_header_bytes {
                            return Err(MultipartError::HeadersTooLong(self.max_header_bytes));
                        }
                        return Ok(out);
                    };
                    if end > self.max_header_bytes {
                        return Err(MultipartError::HeadersTooLong(self.max_header_bytes));
                    }
                    let headers = parse_headers(&self.buf[..end])?;
                    self.buf.drain(..skip);
                    out.push(Event::Part(headers));
                    self.state = State::Body;
                }
                State::Body => match find(&self.buf, &self.delimiter) {
                    Some(i) => {
                        if i > 0 {
                            out.push(Event::Data(self.buf[..i].to_vec()));
                        }
                        out.push(Event::PartEnd);
                        self.buf.drain(..i + self.delimiter.len());
                        self.state = State::AfterDelimiter;
                    }
                    None => {
                        let keep = self.delimiter.len() - 1;
                        let cut = self.buf.len().saturating_sub(keep);
                        if cut > 0 {
                            out.push(Event::Data(self.buf[..cut].to_vec()));
                            self.buf.drain(..cut);
                        }
                        return Ok(out);
                    }
                },
                State::Done => return Ok(out),
            }
        }
    }

    /// The body ended: refused unless its closing delimiter was read.
    pub fn finish(&self) -> Result<(), MultipartError> {
        match self.state {
            State::Done => Ok(()),
            State::Preamble => Err(MultipartError::NoDelimiter),
            _ => Err(MultipartError::Truncated),
        }
    }
}

fn parse_headers(block: &[u8]) -> Result<PartHeaders, MultipartError> {
    let text = std::str::from_utf8(block).map_err(|_| MultipartError::BadHeader)?;
    let mut out = Vec::new();
    for line in text.split("\r\n").filter(|l| !l.is_empty()) {
        let (name, value) = line.split_once(':').ok_or(MultipartError::BadHeader)?;
        let name = name.trim();
        if name.is_empty() || !name.bytes().all(|c| c.is_ascii_graphic()) {
            return Err(MultipartError::BadHeader);
        }
        out.push((name.to_ascii_lowercase(), value.trim().to_string()));
    }
    Ok(PartHeaders(out))
}

/// A media type and its parameters: `type/subtype` in lower case, parameter names in lower case, quoted
/// values unquoted. `None` when there is no `type/subtype`.
pub fn media_type(value: &str) -> Option<(String, Vec<(String, String)>)> {
    let mut rest = value;
    let end = rest.find(';').unwrap_or(rest.len());
    let essence = rest[..end].trim().to_ascii_lowercase();
    if !essence.contains('/') || essence.starts_with('/') || essence.ends_with('/') {
        return None;
    }
    rest = &rest[end..];
    let mut params = Vec::new();
    while let Some(r) = rest.strip_prefix(';') {
        let r = r.trim_start();
        let eq = r.find('=')?;
        let name = r[..eq].trim().to_ascii_lowercase();
        let after = &r[eq + 1..];
        let (v, next) = if let Some(q) = after.strip_prefix('"') {
            let mut v = String::new();
            let mut chars = q.char_indices();
            let mut close = None;
            while let Some((i, c)) = chars.next() {
                match c {
                    '\\' => {
                        if let Some((_, e)) = chars.next() {
                            v.push(e);
                        }
                    }
                    '"' => {
                        close = Some(i);
                        break;
                    }
                    c => v.push(c),
                }
            }
            let close = close?;
            let tail = &q[close + 1..];
            (v, &tail[tail.find(';').unwrap_or(tail.len())..])
        } else {
            let e = after.find(';').unwrap_or(after.len());
            (after[..e].trim().to_string(), &after[e..])
        };
        params.push((name, v));
        rest = next.trim_start();
    }
    Some((essence, params))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn body(boundary: &str, parts: &[(&str, &[u8])]) -> Vec<u8> {
        let mut b = b"preamble to ignore\r\n".to_vec();
        for (ct, data) in parts {
            b.extend_from_slice(format!("--{boundary}\r\nContent-Type: {ct}\r\n\r\n").as_bytes());
            b.extend_from_slice(data);
            b.extend_from_slice(b"\r\n");
        }
        b.extend_from_slice(format!("--{boundary}--\r\nepilogue").as_bytes());
        b
    }

    /// Parse `bytes` fed in chunks of `n`: (content type, data) per part.
    fn parse(
        boundary: &str,
        bytes: &[u8],
        n: usize,
    ) -> Result<Vec<(String, Vec<u8>)>, MultipartError> {
        let mut p = Parser::new(boundary, 1024)?;
        let mut parts: Vec<(String, Vec<u8>)> = Vec::new();
        let mut open = false;
        for chunk in bytes.chunks(n) {
            for e in p.feed(chunk)? {
                match e {
                    Event::Part(h) => {
                        assert!(!open);
                        open = true;
                        parts.push((h.get("content-type").unwrap_or("").into(), Vec::new()));
                    }
                    Event::Data(d) => parts.last_mut().unwrap().1.extend_from_slice(&d),
                    Event::PartEnd => open = false,
                }
            }
        }
        p.finish()?;
        Ok(parts)
    }

    #[test]
    fn parts_come_back_whole_whatever_the_chunking() {
        // Data that holds CRLF, dashes and a near-boundary.
        let a: Vec<u8> = (0..3000u32).map(|i| (i * 7 % 256) as u8).collect();
        let b = b"\r\n--bound\r\n--boundar not quite".to_vec();
        let bytes = body(
            "boundary",
            &[("application/dicom", &a), ("application/dicom", &b)],
        );
        for n in [1, 2, 3, 7, 64, 1000, bytes.len()] {
            let parts = parse("boundary", &bytes, n).unwrap();
            assert_eq!(parts.len(), 2, "chunks of {n}");
            assert_eq!(parts[0], ("application/dicom".to_string(), a.clone()));
            assert_eq!(parts[1].1, b);
        }
    }

    #[test]
    fn a_body_starting_with_its_delimiter_and_an_empty_part_are_read() {
        let bytes = b"--xy\r\n\r\n\r\n--xy\r\nA: 1\r\n\r\nabc\r\n--xy--".to_vec();
        let parts = parse("xy", &bytes, 5).unwrap();
        assert_eq!(parts.len(), 2);
        assert!(parts[0].1.is_empty());
        assert_eq!(parts[1].1, b"abc");
    }

    #[test]
    fn wrong_boundaries_truncation_and_long_headers_are_refused() {
        let bytes = body("right", &[("application/dicom", b"x")]);
        assert_eq!(parse("wrong", &bytes, 10), Err(MultipartError::NoDelimiter));
        assert_eq!(
            parse("right", &bytes[..bytes.len() - 20], 10),
            Err(MultipartError::Truncated)
        );
        assert!(Parser::new("", 10).is_err());
        assert!(Parser::new(&"a".repeat(201), 10).is_err());
        assert!(
            Parser::new(&"a".repeat(73), 10).is_ok(),
            "Orthanc's boundaries are 73 characters"
        );
        assert!(Parser::new("a\"b", 10).is_err());
        let long = format!("--b\r\nX: {}\r\n\r\nx\r\n--b--", "y".repeat(2000));
        assert_eq!(
            parse("b", long.as_bytes(), 100),
            Err(MultipartError::HeadersTooLong(1024))
        );
        assert_eq!(
            parse("b", b"--b\r\nno colon\r\n\r\nx\r\n--b--", 4),
            Err(MultipartError::BadHeader)
        );
    }

    #[test]
    fn the_parser_holds_no_more_than_a_chunk_and_a_delimiter() {
        let mut p = Parser::new("boundary", 1024).unwrap();
        p.feed(b"--boundary\r\n\r\n").unwrap();
        for _ in 0..100 {
            p.feed(&[7u8; 4096]).unwrap();
            assert!(p.buf.len() < 4096 + 16);
        }
    }

    #[test]
    fn media_types_and_parameters_are_parsed() {
        let (t, p) = media_type(
            r#"Multipart/Related; type="application/dicom"; boundary=abc-123 ; x="a\"b;c""#,
        )
        .unwrap();
        assert_eq!(t, "multipart/related");
        assert_eq!(
            p,
            vec![
                ("type".into(), "application/dicom".into()),
                ("boundary".into(), "abc-123".into()),
                ("x".into(), "a\"b;c".into()),
            ]
        );
        assert_eq!(
            media_type("application/dicom").unwrap().0,
            "application/dicom"
        );
        assert!(media_type("nonsense").is_none());
        assert!(media_type("a/b; noequals").is_none());
    }
}
