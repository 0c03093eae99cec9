//! The agent's logs after a rollout, scrubbed and bounded. The harness's stdout and stderr are redirected to files
//! in the rollout directory, so their content and size are the agent's: a log may be gigabytes long, sparse (a seek
//! far past its end costs the agent nothing), one line without a newline, or not UTF-8. [`scrub_log`] reads it
//! once through a fixed-size buffer and puts a new file in its place (written beside it, then renamed over it, so
//! a hole is never expanded on disk) that holds:
//!
//! - the first [`Limits::head`] bytes (8 MiB) and the last [`Limits::tail`] bytes (8 MiB) of the log, with the
//!   secrets replaced by `<redacted>` (the whole log when it is no longer than both together);
//! - between them, when bytes were left out, one JSON line `{"libero_agent_log_omitted": {…}}` with the omitted
//!   byte range, the log's true size and the SHA-256 of the omitted bytes as the agent wrote them, as the episode's
//!   `actions.jsonl` records an oversized field (`size_bytes`, `sha256`). The hash covers at most the first
//!   [`Limits::max_hashed`] (4 GiB) of the omitted bytes (`sha256_bytes` says how many), so a sparse log of a
//!   terabyte costs seconds, not hours.
//!
//! Secrets are matched on raw bytes, chunk by chunk ([`Limits::chunk`], 1 MiB): each chunk is scanned with the
//! start of the next in view (the longest secret's length), so a secret that a chunk edge or the head's end cuts is
//! still replaced whole, and the kept tail is scanned from 64 KiB before it, so a secret that begins in the omitted
//! part and ends in the tail is replaced too. What is scrubbed: every secret given (the API key, the episode's MCP
//! bearer token), and `sk-…` and `Bearer …` followed by 6 or more of `[A-Za-z0-9._-]` (the whole run).
//!
//! Memory is the chunk, the lookahead and the kept tail (before it is written); disk is the kept bytes.
use std::ffi::{CStr, CString};
use std::io::{Read, Seek, SeekFrom, Write};
use std::os::fd::{AsFd, BorrowedFd};
use std::path::Path;

use rustix::fs::{FileType, Mode, OFlags};
use serde::Serialize;
use sha2::{Digest, Sha256};

/// What a secret is replaced with.
pub const REDACTED: &str = "<redacted>";
/// Prefixes of tokens scrubbed wherever they appear (the rest of the token is replaced).
const PREFIXES: [&[u8]; 2] = [b"sk-", b"Bearer "];
/// A prefix is followed by at least this many token characters for the run to count as a secret.
const MIN_TOKEN_CHARS: usize = 6;
/// Shorter secrets are not matched (they would redact ordinary words).
const MIN_SECRET_LEN: usize = 6;
/// How far before the kept tail the scan starts, at least.
const TAIL_LOOKBEHIND: u64 = 64 << 10;

/// How much of a log is kept and how it is read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Bytes kept from the start of the log.
    pub head: u64,
    /// Bytes kept from the end of the log.
    pub tail: u64,
    /// Bytes read at a time.
    pub chunk: usize,
    /// Omitted bytes hashed at most.
    pub max_hashed: u64,
}

impl Limits {
    /// 8 MiB from the start, 8 MiB from the end, 1 MiB reads, 4 GiB hashed.
    pub const DEFAULT: Self = Self { head: 8 << 20, tail: 8 << 20, chunk: 1 << 20, max_hashed: 4 << 30 };
}

/// What became of one log (recorded in the rollout's `harness_manifest.json` under `logs`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct LogRecord {
    /// The log's size as the agent's process left it, holes included.
    pub size_bytes: u64,
    /// The size of the scrubbed copy now in its place.
    pub kept_bytes: u64,
    /// Secrets replaced in the kept bytes.
    pub redactions: u64,
    /// The bytes left out, when the log was longer than the head and the tail together.
    pub omitted: Option<Omitted>,
}

/// The part of a log left out of its scrubbed copy.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Omitted {
    /// First omitted byte (offset in the original log).
    pub from: u64,
    /// One past the last omitted byte.
    pub to: u64,
    /// SHA-256 (hex) of the omitted bytes as written, over the first `sha256_bytes` of them.
    pub sha256: String,
    /// How many omitted bytes the hash covers (all of them unless more than [`Limits::max_hashed`]).
    pub sha256_bytes: u64,
}

fn is_token_byte(b: u8) -> bool {
    b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.')
}

fn token_run(bytes: &[u8]) -> usize {
    bytes.iter().position(|&b| !is_token_byte(b)).unwrap_or(bytes.len())
}

/// A piece of scrubbed output, for a range of raw bytes.
enum Piece<'b> {
    /// Raw bytes kept as they are.
    Plain(&'b [u8]),
    /// A secret: `prefix` (`sk-`, `Bearer ` or nothing), then [`REDACTED`].
    Redacted(&'static [u8]),
}

/// The streaming matcher. Stateless between tokens except for a redacted `sk-`/`Bearer` run that goes on past
/// the bytes seen so far: the rest of that run is dropped as it arrives.
#[derive(Clone)]
struct Scrubber {
    /// Longest first, so a secret that contains another is replaced whole.
    secrets: Vec<Vec<u8>>,
    /// The bytes a match can start with.
    starts: [bool; 256],
    /// Bytes after a position needed to decide whether a match starts there.
    lookahead: usize,
    /// Inside a redacted run that may continue.
    skipping: bool,
}

impl Scrubber {
    fn new(secrets: &[&str]) -> Self {
        let mut secrets: Vec<Vec<u8>> =
            secrets.iter().filter(|s| s.len() >= MIN_SECRET_LEN).map(|s| s.as_bytes().to_vec()).collect();
        secrets.sort_by(|a, b| b.len().cmp(&a.len()).then_with(|| a.cmp(b)));
        secrets.dedup();
        let mut starts = [false; 256];
        for s in &secrets {
            starts[usize::from(s[0])] = true;
        }
        for p in PREFIXES {
            starts[usize::from(p[0])] = true;
        }
        let longest_prefix = PREFIXES.iter().map(|p| p.len()).max().unwrap_or(0);
        let lookahead = secrets.first().map_or(0, Vec::len).max(longest_prefix + MIN_TOKEN_CHARS);
        Self { secrets, starts, lookahead, skipping: false }
    }

    /// Scans `buf`, calling `emit(start, end, piece)` (offsets in `buf`) for each token whose match could be
    /// decided: all of them when `last` (nothing follows `buf`), else those starting at least
    /// [`Scrubber::lookahead`] bytes before its end. Returns how many bytes of `buf` were consumed.
    fn scan(&mut self, buf: &[u8], last: bool, emit: &mut impl FnMut(usize, usize, Piece<'_>)) -> usize {
        let n = buf.len();
        let mut i = 0;
        while i < n {
            if self.skipping {
                i += token_run(&buf[i..]);
                if i == n {
                    break;
                }
                self.skipping = false;
                continue;
            }
            if !last && n - i < self.lookahead {
                break;
            }
            if self.starts[usize::from(buf[i])] {
                if let Some(s) = self.secrets.iter().find(|s| buf[i..].starts_with(s)) {
                    emit(i, i + s.len(), Piece::Redacted(b""));
                    i += s.len();
                    continue;
                }
                if let Some(p) = PREFIXES.iter().find(|p| buf[i..].starts_with(p)) {
                    let run = token_run(&buf[i + p.len()..]);
                    if run >= MIN_TOKEN_CHARS {
                        emit(i, i + p.len() + run, Piece::Redacted(p));
                        i += p.len() + run;
                        // The run reaches the end of what was read: what follows may continue it.
                        self.skipping = i == n && !last;
                        continue;
                    }
                    // Too short to be a key: the prefix stays, and the run is scanned like anything else.
                    emit(i, i + p.len(), Piece::Plain(&buf[i..i + p.len()]));
                    i += p.len();
                    continue;
                }
            }
            // Plain bytes up to the next one a match could start with (and no further than can be decided).
            let decided = if last { n } else { n + 1 - self.lookahead };
            let mut j = i + 1;
            while j < decided && !self.starts[usize::from(buf[j])] {
                j += 1;
            }
            emit(i, j, Piece::Plain(&buf[i..j]));
            i = j;
        }
        i
    }
}

/// `text` with the secrets (each at least 6 bytes), `sk-…` keys and `Bearer …` tokens replaced by `<redacted>`.
pub fn scrub_text(text: &str, secrets: &[&str]) -> String {
    let mut out = Vec::with_capacity(text.len());
    Scrubber::new(secrets).scan(text.as_bytes(), true, &mut |_, _, piece| match piece {
        Piece::Plain(b) => out.extend_from_slice(b),
        Piece::Redacted(prefix) => {
            out.extend_from_slice(prefix);
            out.extend_from_slice(REDACTED.as_bytes());
        }
    });
    String::from_utf8_lossy(&out).into_owned()
}

/// A range of the log scanned in chunks, whose output is kept only for raw bytes in `keep_from..keep_to` (a
/// redacted secret that overlaps the range is kept whole).
struct Window {
    scrubber: Scrubber,
    buf: Vec<u8>,
    /// Offset in the log of `buf[0]`.
    base: u64,
    keep_from: u64,
    keep_to: u64,
    redactions: u64,
}

impl Window {
    fn new(scrubber: Scrubber, base: u64, keep_from: u64, keep_to: u64) -> Self {
        Self { scrubber, buf: Vec::new(), base, keep_from, keep_to, redactions: 0 }
    }

    /// Adds the log's next bytes and appends what could be decided to `out`.
    fn push(&mut self, data: &[u8], out: &mut Vec<u8>) {
        self.buf.extend_from_slice(data);
        self.run(false, out);
    }

    /// Scans what is left: `last` when the log ends there; otherwise positions without enough lookahead stay
    /// unscanned (they lie past `keep_to`).
    fn finish(&mut self, last: bool, out: &mut Vec<u8>) {
        self.run(last, out);
        self.buf = Vec::new();
    }

    fn run(&mut self, last: bool, out: &mut Vec<u8>) {
        let (base, from, to) = (self.base, self.keep_from, self.keep_to);
        let mut redactions = 0;
        let done = self.scrubber.scan(&self.buf, last, &mut |s, e, piece| {
            let (s, e) = (base + s as u64, base + e as u64);
            match piece {
                Piece::Plain(bytes) => {
                    let (a, b) = (s.max(from), e.min(to));
                    if a < b {
                        out.extend_from_slice(&bytes[(a - s) as usize..(b - s) as usize]);
                    }
                }
                Piece::Redacted(prefix) => {
                    if s < to && e > from {
                        out.extend_from_slice(prefix);
                        out.extend_from_slice(REDACTED.as_bytes());
                        redactions += 1;
                    }
                }
            }
        });
        self.redactions += redactions;
        self.buf.drain(..done);
        self.base += done as u64;
    }
}

const DIR_FLAGS: OFlags = OFlags::RDONLY.union(OFlags::DIRECTORY).union(OFlags::CLOEXEC);

/// Scrubs the log at `path` in place (see the module's documentation) and returns what was kept. `raw` is given
/// the log's bytes in order as they are read (for the token usage), and `None` where a stretch of omitted bytes
/// was not read. The log is opened without following a link; anything but a regular file is refused (and left).
pub fn scrub_log(path: &Path, secrets: &[&str], limits: &Limits, mut raw: impl FnMut(Option<&[u8]>)) -> std::io::Result<LogRecord> {
    let bad = |what: &str| std::io::Error::other(format!("{}: {what}", path.display()));
    let name = path.file_name().ok_or_else(|| bad("no file name"))?;
    let name = CString::new(name.as_encoded_bytes()).map_err(|_| bad("a NUL in the name"))?;
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let dir = rustix::fs::open(parent, DIR_FLAGS, Mode::empty())?;
    let log_fd = rustix::fs::openat(
        dir.as_fd(),
        name.as_c_str(),
        OFlags::RDONLY | OFlags::NOFOLLOW | OFlags::CLOEXEC | OFlags::NONBLOCK | OFlags::NOCTTY,
        Mode::empty(),
    )?;
    let st = rustix::fs::fstat(&log_fd)?;
    if FileType::from_raw_mode(st.st_mode) != FileType::RegularFile {
        return Err(bad("not a regular file"));
    }
    let size = u64::try_from(st.st_size).unwrap_or(0);
    let mut log = std::fs::File::from(log_fd);
    let tmp = CString::new(format!(".{}.scrub-{}", name.to_string_lossy(), libero_records::json::random_name("")?))
        .map_err(|_| bad("a NUL in the name"))?;
    let out_fd = rustix::fs::openat(
        dir.as_fd(),
        tmp.as_c_str(),
        OFlags::WRONLY | OFlags::CREATE | OFlags::EXCL | OFlags::NOFOLLOW | OFlags::CLOEXEC,
        Mode::from_raw_mode(0o600),
    )?;
    let mut out = std::fs::File::from(out_fd);
    let written = copy_scrubbed(&mut log, size, secrets, limits, &mut out, &mut raw).and_then(|r| {
        out.sync_data()?;
        Ok(r)
    });
    match written {
        Ok(record) => {
            if let Err(e) = rustix::fs::renameat(dir.as_fd(), tmp.as_c_str(), dir.as_fd(), name.as_c_str()) {
                remove_quietly(dir.as_fd(), &tmp);
                return Err(e.into());
            }
            Ok(record)
        }
        Err(e) => {
            remove_quietly(dir.as_fd(), &tmp);
            Err(e)
        }
    }
}

fn remove_quietly(dir: BorrowedFd<'_>, name: &CStr) {
    let _ = rustix::fs::unlinkat(dir, name, rustix::fs::AtFlags::empty());
}

/// Reads into `buf` until it is full or the file ends; the bytes read.
fn read_full(f: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match f.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

/// The part of `[pos, pos + len)` inside `[from, to)`, as a range of the chunk.
fn overlap(pos: u64, len: usize, from: u64, to: u64) -> Option<std::ops::Range<usize>> {
    let (a, b) = (pos.max(from), (pos + len as u64).min(to));
    (a < b).then(|| (a - pos) as usize..(b - pos) as usize)
}

/// The scrubbed copy of the first `size` bytes of `log` into `out`.
fn copy_scrubbed(
    log: &mut std::fs::File,
    size: u64,
    secrets: &[&str],
    limits: &Limits,
    out: &mut std::fs::File,
    raw: &mut impl FnMut(Option<&[u8]>),
) -> std::io::Result<LogRecord> {
    let scrubber = Scrubber::new(secrets);
    let lookahead = scrubber.lookahead as u64;
    let mut chunk = vec![0u8; limits.chunk.max(1)];
    let mut pending = Vec::new();
    let mut kept = 0u64;
    let flush = |pending: &mut Vec<u8>, out: &mut std::fs::File, kept: &mut u64| -> std::io::Result<()> {
        out.write_all(pending)?;
        *kept += pending.len() as u64;
        pending.clear();
        Ok(())
    };
    if size <= limits.head.saturating_add(limits.tail) {
        // All of it, scrubbed.
        let mut window = Window::new(scrubber, 0, 0, u64::MAX);
        let mut pos = 0u64;
        while pos < size {
            let want = chunk.len().min((size - pos) as usize);
            let n = read_full(log, &mut chunk[..want])?;
            if n == 0 {
                break; // shrunk meanwhile
            }
            raw(Some(&chunk[..n]));
            window.push(&chunk[..n], &mut pending);
            flush(&mut pending, out, &mut kept)?;
            pos += n as u64;
        }
        window.finish(true, &mut pending);
        flush(&mut pending, out, &mut kept)?;
        return Ok(LogRecord { size_bytes: size, kept_bytes: kept, redactions: window.redactions, omitted: None });
    }
    let head_end = limits.head;
    let tail_start = size - limits.tail;
    let hash_end = tail_start.min(head_end.saturating_add(limits.max_hashed));
    // The head is scanned with its lookahead; the tail from before its start.
    let head_feed_end = head_end.saturating_add(lookahead).min(size);
    let tail_scan = tail_start.saturating_sub(TAIL_LOOKBEHIND.max(2 * lookahead));
    let sequential_end = if hash_end.max(head_feed_end) >= tail_scan { size } else { hash_end.max(head_feed_end) };
    let mut head = Window::new(scrubber.clone(), 0, 0, head_end);
    let mut head_open = true;
    let mut tail = Window::new(scrubber, tail_scan, tail_start, u64::MAX);
    let mut tail_out = Vec::new();
    let mut hasher = Sha256::new();
    let mut pos = 0u64;
    let mut ended_with_newline = true;
    while pos < sequential_end {
        let want = chunk.len().min((sequential_end - pos) as usize);
        let n = read_full(log, &mut chunk[..want])?;
        if n == 0 {
            break;
        }
        let data = &chunk[..n];
        raw(Some(data));
        if head_open {
            if let Some(r) = overlap(pos, n, 0, head_feed_end) {
                head.push(&data[r], &mut pending);
            }
            if pos + n as u64 >= head_feed_end {
                head.finish(head_feed_end >= size, &mut pending);
                head_open = false;
            }
            if let Some(&last) = pending.last() {
                ended_with_newline = last == b'\n';
            }
            flush(&mut pending, out, &mut kept)?;
        }
        if let Some(r) = overlap(pos, n, head_end, hash_end) {
            hasher.update(&data[r]);
        }
        if let Some(r) = overlap(pos, n, tail_scan, size) {
            tail.push(&data[r], &mut tail_out);
        }
        pos += n as u64;
    }
    if head_open {
        // The log shrank under the head's lookahead.
        head.finish(true, &mut pending);
        if let Some(&last) = pending.last() {
            ended_with_newline = last == b'\n';
        }
        flush(&mut pending, out, &mut kept)?;
    }
    let hashed = hash_end.min(pos).saturating_sub(head_end);
    if sequential_end < size {
        // The hash is complete; jump to the tail.
        raw(None);
        log.seek(SeekFrom::Start(tail_scan))?;
        let mut pos = tail_scan;
        while pos < size {
            let want = chunk.len().min((size - pos) as usize);
            let n = read_full(log, &mut chunk[..want])?;
            if n == 0 {
                break;
            }
            raw(Some(&chunk[..n]));
            tail.push(&chunk[..n], &mut tail_out);
            pos += n as u64;
        }
    }
    tail.finish(true, &mut tail_out);
    let omitted = Omitted {
        from: head_end,
        to: tail_start,
        sha256: hasher.finalize().iter().map(|b| format!("{b:02x}")).collect(),
        sha256_bytes: hashed,
    };
    let marker = serde_json::json!({"libero_agent_log_omitted": {
        "from": omitted.from, "to": omitted.to, "omitted_bytes": omitted.to - omitted.from, "size_bytes": size,
        "sha256": omitted.sha256, "sha256_bytes": omitted.sha256_bytes,
    }});
    if !ended_with_newline {
        pending.push(b'\n');
    }
    pending.extend_from_slice(marker.to_string().as_bytes());
    pending.push(b'\n');
    pending.append(&mut tail_out);
    flush(&mut pending, out, &mut kept)?;
    Ok(LogRecord { size_bytes: size, kept_bytes: kept, redactions: head.redactions + tail.redactions, omitted: Some(omitted) })
}

#[cfg(test)]
mod tests {
    use super::*;

    const SMALL: Limits = Limits { head: 64, tail: 64, chunk: 16, max_hashed: 1 << 20 };

    fn scrub_bytes(bytes: &[u8], secrets: &[&str], limits: &Limits) -> (Vec<u8>, LogRecord, Vec<u8>) {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("agent_stdout.jsonl");
        std::fs::write(&p, bytes).unwrap();
        let mut seen = Vec::new();
        let rec = scrub_log(&p, secrets, limits, |b| match b {
            Some(b) => seen.extend_from_slice(b),
            None => seen.extend_from_slice(b"<gap>"),
        })
        .unwrap();
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names.len(), 1, "no temporary file left: {names:?}");
        (std::fs::read(&p).unwrap(), rec, seen)
    }

    #[test]
    fn text_scrubbing_keeps_its_old_behaviour() {
        let t = "key=sk-abcdef123456 auth: Bearer 0123456789abcdef and MYSECRETKEY here; sk-no";
        assert_eq!(scrub_text(t, &["MYSECRETKEY"]), "key=sk-<redacted> auth: Bearer <redacted> and <redacted> here; sk-no");
        assert_eq!(scrub_text("short abc stays", &["abc"]), "short abc stays");
        assert_eq!(scrub_text("Bearer abc sk-x", &[]), "Bearer abc sk-x");
        assert_eq!(scrub_text("xxsk-aaaaaa", &[]), "xxsk-<redacted>");
        // A short run after a prefix is scanned again: a secret starting inside it is still caught.
        assert_eq!(scrub_text("Bearer ab/SECRET/x", &["ab/SECRET"]), "Bearer <redacted>/x");
        assert_eq!(scrub_text("ünï sk-ÄÖÜ MYSECRETKEY", &["MYSECRETKEY"]), "ünï sk-ÄÖÜ <redacted>");
    }

    #[test]
    fn secrets_across_every_chunk_edge_are_caught() {
        let secret = "S3CRET-KEY-0123";
        for at in 0..40 {
            let mut log = vec![b'x'; at];
            log.extend_from_slice(secret.as_bytes());
            log.extend_from_slice(b" and Bearer abcdefghijklmnopqrstuvwxyz0123456789 end");
            let (out, rec, seen) = scrub_bytes(&log, &[secret], &Limits { head: 1 << 20, tail: 1 << 20, ..SMALL });
            let out = String::from_utf8(out).unwrap();
            assert_eq!(out, format!("{}<redacted> and Bearer <redacted> end", "x".repeat(at)));
            assert_eq!((rec.redactions, rec.omitted, rec.size_bytes), (2, None, log.len() as u64));
            assert_eq!(seen, log, "the raw bytes are passed on once each, in order");
        }
    }

    #[test]
    fn a_long_log_keeps_its_head_and_tail_and_hashes_the_rest() {
        let mut log = Vec::new();
        log.extend_from_slice(b"head KEY123456 ");
        log.resize(60, b'a');
        // Across the head's end (64): caught whole.
        log.extend_from_slice(b"KEY123456");
        log.resize(200, b'm');
        log.extend_from_slice(b" KEY123456 "); // omitted
        log.resize(300, b'n');
        // Across the tail's start (310): caught whole.
        log.extend_from_slice(b"Bearer zzzzzzzzzzzz");
        log.resize(364, b'~');
        log.extend_from_slice(b" KEY123456");
        let size = log.len() as u64;
        let tail_start = size - 64;
        assert_eq!(tail_start, 310);
        let (out, rec, seen) = scrub_bytes(&log, &["KEY123456"], &SMALL);
        let out = String::from_utf8(out).unwrap();
        assert!(!out.contains("KEY1") && !out.contains("zzz"), "{out}");
        let omitted = rec.omitted.clone().unwrap();
        assert_eq!((omitted.from, omitted.to, omitted.sha256_bytes), (64, tail_start, tail_start - 64));
        let expected: String = Sha256::digest(&log[64..tail_start as usize]).iter().map(|b| format!("{b:02x}")).collect();
        assert_eq!(omitted.sha256, expected);
        let lines: Vec<&str> = out.lines().collect();
        assert_eq!(lines.len(), 3, "{out}");
        assert_eq!(lines[0], format!("head <redacted> {}<redacted>", "a".repeat(45)));
        let marker: serde_json::Value = serde_json::from_str(lines[1]).unwrap();
        assert_eq!(marker["libero_agent_log_omitted"]["size_bytes"], size);
        assert_eq!(marker["libero_agent_log_omitted"]["sha256"], expected);
        assert!(lines[2].starts_with("Bearer <redacted>~~~~") && lines[2].ends_with(" <redacted>"), "{}", lines[2]);
        assert_eq!(rec.redactions, 4);
        assert_eq!(rec.kept_bytes, out.len() as u64);
        assert_eq!(seen, log, "read once, in order, without a gap");
    }

    #[test]
    fn a_log_beyond_the_hash_limit_is_read_in_two_stretches() {
        let mut log = vec![b'a'; 200_000];
        log.extend_from_slice(b"TAILSECRET99");
        let limits = Limits { head: 100, tail: 100, chunk: 64, max_hashed: 1000 };
        let (out, rec, seen) = scrub_bytes(&log, &["TAILSECRET99"], &limits);
        let o = rec.omitted.unwrap();
        assert_eq!((o.from, o.to, o.sha256_bytes), (100, 199_912, 1000));
        let expected: String = Sha256::digest(&log[100..1100]).iter().map(|b| format!("{b:02x}")).collect();
        assert_eq!(o.sha256, expected);
        assert!(String::from_utf8(out).unwrap().ends_with(&format!("\n{}<redacted>", "a".repeat(88))));
        // Read up to the end of the hashed bytes, then from 64 KiB before the tail.
        let gap = seen.windows(5).position(|w| w == b"<gap>").expect("a gap");
        assert_eq!(gap, 1100);
        assert_eq!(seen.len(), 1100 + 5 + (200_012 - (199_912 - 65_536)));
    }

    #[test]
    fn links_and_fifos_are_refused_untouched() {
        let dir = tempfile::tempdir().unwrap();
        let host = dir.path().join("host.txt");
        std::fs::write(&host, "Bearer abcdefghijkl").unwrap();
        let link = dir.path().join("codex_stdout.jsonl");
        std::os::unix::fs::symlink(&host, &link).unwrap();
        assert!(scrub_log(&link, &[], &Limits::DEFAULT, |_| {}).is_err());
        assert_eq!(std::fs::read_to_string(&host).unwrap(), "Bearer abcdefghijkl");
        assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
        let fifo = dir.path().join("fifo.log");
        assert!(std::process::Command::new("mkfifo").arg(&fifo).status().unwrap().success());
        assert!(scrub_log(&fifo, &[], &Limits::DEFAULT, |_| {}).is_err(), "a FIFO is refused without blocking");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 3, "no temporary file left");
    }
}
