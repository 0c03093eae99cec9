//! JSON and file-writing conventions of the original runtime: keys sorted, `indent=2` files with a
//! trailing newline, compact lines for logs, ISO-8601 UTC timestamps, atomic replace-by-rename.
use std::fs::{self, File, OpenOptions};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use serde_json::{Map, Value};
use sha2::{Digest, Sha256};

/// `value` with every object's keys in sorted order (whatever map backend serde_json was built with).
pub fn sorted(value: &Value) -> Value {
    match value {
        Value::Object(map) => {
            let mut keys: Vec<&String> = map.keys().collect();
            keys.sort();
            let mut out = Map::new();
            for k in keys {
                out.insert(k.clone(), sorted(&map[k]));
            }
            Value::Object(out)
        }
        Value::Array(items) => Value::Array(items.iter().map(sorted).collect()),
        other => other.clone(),
    }
}

/// Python's `json.dumps(v, indent=2, sort_keys=True)` layout (without the trailing newline).
pub fn pretty_sorted(value: &Value) -> String {
    serde_json::to_string_pretty(&sorted(value)).unwrap_or_else(|_| "null".to_owned())
}

/// One compact line with sorted keys (no newline).
pub fn compact_sorted(value: &Value) -> String {
    serde_json::to_string(&sorted(value)).unwrap_or_else(|_| "null".to_owned())
}

/// Lower-case hex of `bytes`.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// SHA-256 of `bytes` in lower-case hex (the digests of records and manifests).
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

/// Writes `bytes` to `path` durably and atomically: temp file in the same directory, fsync, rename,
/// fsync of the directory. Readers see the old file or the new one, never a prefix. The temp file has a
/// name no other writer (thread or process) uses and is created exclusively, so two writers never share it.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let (tmp, mut f) = create_temp(dir, &name)?;
    let written = f.write_all(bytes).and_then(|()| f.sync_all()).and_then(|()| fs::rename(&tmp, path));
    if written.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    written?;
    sync_dir(dir)
}

/// A new file `.<name>.tmp-<pid>-<random>` in `dir`, created with `O_EXCL`.
fn create_temp(dir: &Path, name: &str) -> std::io::Result<(PathBuf, File)> {
    let prefix = format!(".{name}.tmp-{}-", std::process::id());
    let mut last = None;
    for _ in 0..4 {
        let tmp = dir.join(random_name(&prefix)?);
        match OpenOptions::new().write(true).create_new(true).open(&tmp) {
            Ok(f) => return Ok((tmp, f)),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => last = Some(e),
            Err(e) => return Err(e),
        }
    }
    Err(last.unwrap_or_else(|| std::io::Error::other("no free temporary name")))
}

/// Opens a JSON-lines file for appending (creating it) and returns it with its number of lines. A last line
/// torn by a crash (no final newline) is ended first, so the next line starts on a line of its own; it
/// counts as a line.
pub fn open_jsonl_for_append(path: &Path) -> std::io::Result<(File, u64)> {
    let mut file = OpenOptions::new().create(true).read(true).append(true).open(path)?;
    let (mut lines, mut last_byte) = (0u64, None);
    let mut buf = vec![0u8; 64 * 1024];
    loop {
        let n = file.read(&mut buf)?;
        if n == 0 {
            break;
        }
        lines += buf[..n].iter().filter(|&&b| b == b'\n').count() as u64;
        last_byte = Some(buf[n - 1]);
    }
    if last_byte.is_some_and(|b| b != b'\n') {
        file.write_all(b"\n")?;
        file.sync_data()?;
        lines += 1;
    }
    Ok((file, lines))
}

/// `pretty_sorted(value)` + newline, written atomically.
pub fn write_json_file(path: &Path, value: &Value) -> std::io::Result<()> {
    let mut text = pretty_sorted(value);
    text.push('\n');
    write_atomic(path, text.as_bytes())
}

/// fsync of a directory, so renames and new entries in it survive a crash.
pub fn sync_dir(dir: &Path) -> std::io::Result<()> {
    File::open(dir)?.sync_all()
}

/// Current time as ISO-8601 UTC with microseconds, e.g. `2026-11-21T17:03:04.123456+00:00`
/// (Python's `datetime.now(timezone.utc).isoformat()`).
pub fn utc_now_iso() -> String {
    iso_from_system_time(SystemTime::now())
}

pub fn iso_from_system_time(t: SystemTime) -> String {
    let d = t.duration_since(UNIX_EPOCH).unwrap_or_default();
    let secs = d.as_secs() as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    let (y, m, day) = civil_from_days(days);
    format!(
        "{y:04}-{m:02}-{day:02}T{:02}:{:02}:{:02}.{:06}+00:00",
        rem / 3600,
        (rem % 3600) / 60,
        rem % 60,
        d.subsec_micros()
    )
}

/// Howard Hinnant's days-from-epoch → (year, month, day) in the proleptic Gregorian calendar.
fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let y = yoe + era * 400;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    (if m <= 2 { y + 1 } else { y }, m, d)
}

/// Python's `format(x, "g")` for the values budgets take (integers print without a fraction).
pub fn format_g(x: f64) -> String {
    if x.is_finite() && x.fract() == 0.0 && x.abs() < 1e6 {
        format!("{}", x as i64)
    } else {
        format!("{x}")
    }
}

/// `prefix` and 32 random hex digits: a name nobody can guess or pre-create.
pub fn random_name(prefix: &str) -> std::io::Result<String> {
    let mut bytes = [0u8; 16];
    let mut filled = 0;
    while filled < bytes.len() {
        filled += rustix::rand::getrandom(&mut bytes[filled..], rustix::rand::GetRandomFlags::empty())?;
    }
    Ok(format!("{prefix}{}", hex(&bytes)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn pretty_sorted_matches_python_sort_keys_indent_2() {
        let v = serde_json::json!({"b": 1, "a": {"d": [1.0, 2], "c": null}});
        assert_eq!(
            pretty_sorted(&v),
            "{\n  \"a\": {\n    \"c\": null,\n    \"d\": [\n      1.0,\n      2\n    ]\n  },\n  \"b\": 1\n}"
        );
        assert_eq!(compact_sorted(&v), r#"{"a":{"c":null,"d":[1.0,2]},"b":1}"#);
    }

    #[test]
    fn iso_timestamps_are_utc_calendar_dates() {
        let t = UNIX_EPOCH + Duration::from_micros(1_700_000_000_123_456);
        assert_eq!(iso_from_system_time(t), "2023-11-14T22:13:20.123456+00:00");
        assert_eq!(iso_from_system_time(UNIX_EPOCH + Duration::from_secs(951_782_400)), "2000-02-29T00:00:00.000000+00:00");
    }

    #[test]
    fn jsonl_open_ends_a_torn_line_and_counts_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("log.jsonl");
        // Torn inside a UTF-8 sequence: line counting must not need valid text.
        std::fs::write(&path, b"{\"a\":1}\n{\"b\":\xc3").unwrap();
        let (mut f, lines) = open_jsonl_for_append(&path).unwrap();
        assert_eq!(lines, 2, "the torn line counts");
        f.write_all(b"{\"c\":3}\n").unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert!(bytes.ends_with(b"\xc3\n{\"c\":3}\n"), "{:?}", String::from_utf8_lossy(&bytes));
        let (_, lines) = open_jsonl_for_append(&path).unwrap();
        assert_eq!(lines, 3, "an intact file gains nothing");
        let (_, empty) = open_jsonl_for_append(&dir.path().join("new.jsonl")).unwrap();
        assert_eq!(empty, 0);
    }

    #[test]
    fn atomic_writes_from_many_threads_never_share_a_temp_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("result.json");
        let writers: Vec<_> = (0..8u8)
            .map(|t| {
                let path = path.clone();
                std::thread::spawn(move || {
                    for _ in 0..20 {
                        write_atomic(&path, &[t; 4096]).unwrap();
                    }
                })
            })
            .collect();
        for w in writers {
            w.join().unwrap();
        }
        let bytes = std::fs::read(&path).unwrap();
        assert!(bytes.len() == 4096 && bytes.iter().all(|&b| b == bytes[0]), "one writer's whole content");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names, ["result.json"], "no temporary file left");
    }

    #[test]
    fn format_g_prints_budgets_like_python() {
        assert_eq!(format_g(1800.0), "1800");
        assert_eq!(format_g(0.5), "0.5");
        assert_eq!(format_g(90.25), "90.25");
    }
}
