//! JSON and file-writing conventions of the original runtime: keys sorted, `indent=2` files with a
//! trailing newline, compact lines for logs, ISO-8601 UTC timestamps, atomic replace-by-rename.
use std::fs::{self, File, OpenOptions};
use std::io::Write;
use std::path::Path;
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
/// fsync of the directory. Readers see the old file or the new one, never a prefix.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = dir.join(format!(".{name}.tmp-{}", std::process::id()));
    {
        let mut f = OpenOptions::new().write(true).create(true).truncate(true).open(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
    }
    fs::rename(&tmp, path)?;
    sync_dir(dir)
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
    fn format_g_prints_budgets_like_python() {
        assert_eq!(format_g(1800.0), "1800");
        assert_eq!(format_g(0.5), "0.5");
        assert_eq!(format_g(90.25), "90.25");
    }
}
