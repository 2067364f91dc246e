//! The header's Python dictionary literal (`{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }`):
//! a cursor that reads exactly the three keys a `.npy` header has, each once, and nothing else.

use super::header::{NpyError, malformed};

/// A cursor over the header's Python dictionary literal.
pub(super) struct Dict<'a> {
    s: &'a [u8],
    i: usize,
}

impl<'a> Dict<'a> {
    pub(super) fn new(text: &'a str) -> Self {
        Self {
            s: text.as_bytes(),
            i: 0,
        }
    }
    fn ws(&mut self) {
        while self.i < self.s.len() && self.s[self.i].is_ascii_whitespace() {
            self.i += 1;
        }
    }
    fn eat(&mut self, c: u8) -> bool {
        self.ws();
        if self.s.get(self.i) == Some(&c) {
            self.i += 1;
            true
        } else {
            false
        }
    }
    fn expect(&mut self, c: u8) -> Result<(), NpyError> {
        if self.eat(c) {
            Ok(())
        } else {
            Err(malformed(format!(
                "expected `{}` at header byte {}",
                c as char, self.i
            )))
        }
    }
    fn string(&mut self) -> Result<String, NpyError> {
        self.ws();
        let q = match self.s.get(self.i) {
            Some(&q @ (b'\'' | b'"')) => q,
            _ => return Err(malformed("expected a quoted string in the header")),
        };
        self.i += 1;
        let start = self.i;
        while self.i < self.s.len() && self.s[self.i] != q {
            self.i += 1;
        }
        if self.i >= self.s.len() {
            return Err(malformed("unterminated string in the header"));
        }
        let out = String::from_utf8_lossy(&self.s[start..self.i]).into_owned();
        self.i += 1;
        Ok(out)
    }
    fn word(&mut self) -> &'a [u8] {
        self.ws();
        let start = self.i;
        while self.i < self.s.len() && self.s[self.i].is_ascii_alphanumeric() {
            self.i += 1;
        }
        &self.s[start..self.i]
    }
    fn shape(&mut self) -> Result<Vec<usize>, NpyError> {
        self.expect(b'(')?;
        let mut dims = Vec::new();
        loop {
            if self.eat(b')') {
                return Ok(dims);
            }
            let w = self.word();
            let n = std::str::from_utf8(w)
                .ok()
                .and_then(|t| t.parse::<usize>().ok())
                .ok_or_else(|| malformed("shape entries must be non-negative integers"))?;
            dims.push(n);
            if dims.len() > 32 {
                return Err(malformed("more than 32 dimensions"));
            }
            if !self.eat(b',') {
                self.expect(b')')?;
                return Ok(dims);
            }
        }
    }
    pub(super) fn parse(mut self) -> Result<(String, bool, Vec<usize>), NpyError> {
        self.expect(b'{')?;
        let (mut descr, mut fortran, mut shape) = (None, None, None);
        loop {
            if self.eat(b'}') {
                break;
            }
            let key = self.string()?;
            self.expect(b':')?;
            match key.as_str() {
                "descr" if descr.is_none() => descr = Some(self.string()?),
                "fortran_order" if fortran.is_none() => {
                    fortran = Some(match self.word() {
                        b"True" => true,
                        b"False" => false,
                        _ => return Err(malformed("fortran_order must be True or False")),
                    })
                }
                "shape" if shape.is_none() => shape = Some(self.shape()?),
                _ => return Err(malformed(format!("unexpected or repeated key `{key}`"))),
            }
            if !self.eat(b',') {
                self.expect(b'}')?;
                break;
            }
        }
        self.ws();
        if self.i != self.s.len() {
            return Err(malformed("trailing characters after the header dictionary"));
        }
        match (descr, fortran, shape) {
            (Some(d), Some(f), Some(s)) => Ok((d, f, s)),
            _ => Err(malformed(
                "the header needs `descr`, `fortran_order` and `shape`",
            )),
        }
    }
}
