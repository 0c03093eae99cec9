//! A 2 GiB sparse agent log, scrubbed the way the runner scrubs every rollout's stdout and stderr: the memory it
//! takes and the disk the scrubbed copy takes stay within the kept bytes whatever the log's size, the secrets are
//! gone (at the start, across a read chunk's edge, across the kept head's end, in the omitted middle, across the
//! kept tail's start), and the true size and the omitted bytes' SHA-256 are recorded. Alone in its test binary, so
//! that the process's peak memory is this test's.
use std::io::{Seek, SeekFrom, Write};
use std::os::unix::fs::MetadataExt;

use libero_sandbox::logs::{Limits, scrub_log};
use sha2::{Digest, Sha256};

const GIB: u64 = 1 << 30;
const KEY: &str = "test-api-key-0123456789abcdef";
const TOKEN: &str = "mcp-bearer-token-ZYXWVUTSRQ";
const RESULT: &str = "{\"type\":\"result\",\"usage\":{\"input_tokens\":120,\"output_tokens\":50}}\n";

fn head_end_line() -> String {
    format!("sk-proj-abcdefghijklmnopqrstuvwxyz {KEY}\n")
}

fn status_kib(field: &str) -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    let line = status.lines().find(|l| l.starts_with(field)).unwrap_or_else(|| panic!("{field} in /proc/self/status"));
    line.split_whitespace().nth(1).unwrap().parse().unwrap()
}

fn write_at(f: &mut std::fs::File, at: u64, bytes: &[u8]) {
    f.seek(SeekFrom::Start(at)).unwrap();
    f.write_all(bytes).unwrap();
}

#[test]
fn a_sparse_two_gib_log_is_scrubbed_in_bounded_memory_and_disk() {
    let limits = Limits::DEFAULT;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("claude_code_stdout.jsonl");
    let size = 2 * GIB;
    {
        let mut f = std::fs::File::create(&path).unwrap();
        f.set_len(size).unwrap();
        // At the start, a usage line and the API key.
        write_at(&mut f, 0, format!("{{\"type\":\"assistant\",\"message\":{{\"usage\":{{\"input_tokens\":7,\"output_tokens\":3}}}}}}\nkey {KEY} here\n").as_bytes());
        // Exactly across the first read chunk's edge: the bearer token, and a Bearer header after it.
        let chunk = limits.chunk as u64;
        write_at(&mut f, chunk - 10, format!("{TOKEN} Authorization: Bearer abcdefghijklmnop\n").as_bytes());
        // Across the kept head's end.
        write_at(&mut f, limits.head - 5, head_end_line().as_bytes());
        // Past the cap, in the omitted middle.
        write_at(&mut f, GIB, format!("{KEY} {TOKEN}\n").as_bytes());
        // Across the kept tail's start, and in the tail with the result line.
        write_at(&mut f, size - limits.tail - 7, format!("{KEY}\n").as_bytes());
        let end = format!("Bearer {TOKEN}\n{RESULT}");
        write_at(&mut f, size - end.len() as u64, end.as_bytes());
        f.sync_all().unwrap();
    }
    let meta = std::fs::metadata(&path).unwrap();
    assert_eq!(meta.len(), size);
    assert!(meta.blocks() * 512 < 64 << 20, "the log is sparse ({} blocks)", meta.blocks());

    // Peak resident memory from here on (writing 5 to clear_refs resets VmHWM).
    std::fs::write("/proc/self/clear_refs", "5").unwrap();
    let rss_before = status_kib("VmRSS:");
    // What the runner's usage scanner is fed: the raw (unscrubbed) bytes as read, `None` for a stretch left unread.
    let (mut raw_tail, mut raw_bytes, mut gaps) = (Vec::new(), 0u64, 0);
    let rec = scrub_log(&path, &[KEY, TOKEN], &limits, |b| match b {
        Some(b) => {
            raw_bytes += b.len() as u64;
            raw_tail.extend_from_slice(b);
            let excess = raw_tail.len().saturating_sub(4096);
            raw_tail.drain(..excess);
        }
        None => gaps += 1,
    })
    .unwrap();
    let peak = status_kib("VmHWM:");
    let growth_mib = peak.saturating_sub(rss_before) / 1024;
    assert!(growth_mib < 64, "resident memory grew by {growth_mib} MiB (VmRSS {rss_before} KiB before, VmHWM {peak} KiB)");

    let out = std::fs::read(&path).unwrap();
    let meta = std::fs::symlink_metadata(&path).unwrap();
    assert!(meta.file_type().is_file());
    let cap = limits.head + limits.tail + 4096;
    assert!(meta.len() <= cap, "the scrubbed copy is {} bytes", meta.len());
    assert!(meta.blocks() * 512 <= cap + (1 << 20), "the scrubbed copy takes {} blocks", meta.blocks());
    assert_eq!(rec.kept_bytes, meta.len());
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "no temporary file left");

    let text = String::from_utf8_lossy(&out);
    for secret in [KEY, TOKEN, "abcdefghijklmnop", "sk-proj-abc"] {
        assert!(!text.contains(secret), "{secret} is still in the log");
    }
    assert!(text.starts_with("{\"type\":\"assistant\""), "the head is kept");
    assert!(text.contains("key <redacted> here") && text.contains("<redacted> Authorization: Bearer <redacted>"));
    assert!(text.contains("sk-<redacted>"), "the key across the head's end");
    assert!(text.ends_with(&format!("Bearer <redacted>\n{RESULT}")), "the tail is kept");
    // The key at the start, the token and the Bearer value across the chunk edge, the sk- key across the head's
    // end, the key across the tail's start, the Bearer token at the end.
    assert_eq!(rec.redactions, 6, "{rec:?}");

    // The true size, and the omitted bytes' hash, computed here independently (zeros and the middle secret).
    assert_eq!(rec.size_bytes, size);
    let omitted = rec.omitted.clone().expect("the middle is omitted");
    assert_eq!((omitted.from, omitted.to), (limits.head, size - limits.tail));
    assert_eq!(omitted.sha256_bytes, omitted.to - omitted.from);
    let middle = format!("{KEY} {TOKEN}\n");
    let mut h = Sha256::new();
    let zeros = vec![0u8; 1 << 20];
    let feed_zeros = |h: &mut Sha256, mut n: u64| {
        while n > 0 {
            let k = n.min(zeros.len() as u64);
            h.update(&zeros[..k as usize]);
            n -= k;
        }
    };
    let head_end = head_end_line();
    let head_end_rest = &head_end.as_bytes()[5..];
    h.update(head_end_rest);
    feed_zeros(&mut h, GIB - limits.head - head_end_rest.len() as u64);
    h.update(middle.as_bytes());
    feed_zeros(&mut h, size - limits.tail - 7 - GIB - middle.len() as u64);
    h.update(&KEY.as_bytes()[..7]);
    let expected: String = h.finalize().iter().map(|b| format!("{b:02x}")).collect();
    assert_eq!(omitted.sha256, expected);
    let marker = text.lines().find(|l| l.starts_with("{\"libero_agent_log_omitted\"")).expect("the omission is marked in the log");
    let marker: serde_json::Value = serde_json::from_str(marker).unwrap();
    assert_eq!(marker["libero_agent_log_omitted"]["size_bytes"], size);
    assert_eq!(marker["libero_agent_log_omitted"]["sha256"], expected);

    // The raw stream the runner reads usage from: the middle is hashed whole (under `max_hashed`), so every byte
    // passes in order, unscrubbed, with the result line at its end.
    assert_eq!((raw_bytes, gaps), (size, 0));
    assert!(raw_tail.ends_with(RESULT.as_bytes()), "the raw stream ends with the result line");
}
