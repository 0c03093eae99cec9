//! Lines of a stream the agent writes (a CLI's stdout or stderr), split as bytes arrive. A line is held only up
//! to a bound: one longer is reported as overlong with its length and never held whole, whatever the agent
//! prints (one line of gigabytes, no newline at all).

/// One line, without its newline.
#[derive(Debug, PartialEq, Eq)]
pub enum Line<'a> {
    Complete(&'a [u8]),
    /// Longer than the bound: only its length is known.
    Overlong(u64),
}

/// Splits bytes into [`Line`]s, holding at most `max` bytes of the line under way.
#[derive(Debug)]
pub struct LineSplitter {
    max: usize,
    line: Vec<u8>,
    /// Bytes of the line under way once it outgrew `max`.
    overlong: Option<u64>,
}

impl LineSplitter {
    pub fn new(max: usize) -> Self {
        Self { max, line: Vec::new(), overlong: None }
    }

    /// The next bytes of the stream; `on_line` gets every line they complete.
    pub fn push(&mut self, mut bytes: &[u8], mut on_line: impl FnMut(Line<'_>)) {
        while let Some(i) = bytes.iter().position(|&b| b == b'\n') {
            if self.line.is_empty() && self.overlong.is_none() && i <= self.max {
                on_line(Line::Complete(&bytes[..i]));
            } else {
                self.append(&bytes[..i]);
                self.end(&mut on_line);
            }
            bytes = &bytes[i + 1..];
        }
        self.append(bytes);
    }

    /// The line under way ends here (the stream ended, or bytes of it were skipped).
    pub fn end(&mut self, mut on_line: impl FnMut(Line<'_>)) {
        match self.overlong.take() {
            Some(n) => on_line(Line::Overlong(n)),
            None if !self.line.is_empty() => on_line(Line::Complete(&self.line)),
            None => {}
        }
        self.line.clear();
        if self.line.capacity() > self.max.min(64 << 10) {
            self.line = Vec::new();
        }
    }

    fn append(&mut self, bytes: &[u8]) {
        if let Some(n) = self.overlong.as_mut() {
            *n += bytes.len() as u64;
            return;
        }
        if self.line.len() + bytes.len() > self.max {
            self.overlong = Some((self.line.len() + bytes.len()) as u64);
            self.line = Vec::new();
            return;
        }
        self.line.extend_from_slice(bytes);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn split(max: usize, chunks: &[&[u8]]) -> Vec<String> {
        let mut s = LineSplitter::new(max);
        let mut out = Vec::new();
        let mut take = |l: Line<'_>| {
            out.push(match l {
                Line::Complete(b) => String::from_utf8_lossy(b).into_owned(),
                Line::Overlong(n) => format!("<{n} bytes>"),
            })
        };
        for c in chunks {
            s.push(c, &mut take);
        }
        s.end(&mut take);
        out
    }

    #[test]
    fn lines_split_across_chunks_and_overlong_ones_are_only_counted() {
        assert_eq!(split(10, &[b"ab", b"c\nde\n\nf"]), ["abc", "de", "", "f"]);
        assert_eq!(split(4, &[b"12345678\nok\n", b"abc", b"defg", b"h\nend"]), ["<8 bytes>", "ok", "<8 bytes>", "end"]);
        assert_eq!(split(4, &[b"1234"]), ["1234"], "a line of exactly the bound is kept");
    }
}
