//! The documentation's links hold: every relative link in `README.md` and `docs/*.md` (and in the other markdown
//! files they are the map to: `tasks/README.md`) names a file or folder that exists, and a link with a `#fragment`
//! into a markdown file names one of its headings (GitHub's anchors: lower case, punctuation dropped, spaces as
//! `-`, repeats numbered) or an explicit `<a id=…>`/`<a name=…>`. Links with a scheme (`https:`, `mailto:`) are not
//! checked; code spans and fenced code blocks are not links.
use std::collections::BTreeMap;
use std::path::{Component, Path, PathBuf};

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..").canonicalize().expect("repository root")
}

/// The documents checked: the README, every markdown file of `docs/`, and `tasks/README.md`.
fn documents(root: &Path) -> Vec<PathBuf> {
    let mut out = vec![root.join("README.md"), root.join("tasks/README.md")];
    let mut docs: Vec<PathBuf> = std::fs::read_dir(root.join("docs"))
        .expect("docs/")
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    docs.sort();
    out.extend(docs);
    out
}

/// The lines of a markdown text outside fenced code blocks, with their numbers, inline code spans blanked.
fn prose_lines(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut fence: Option<String> = None;
    for (n, line) in text.lines().enumerate() {
        let trimmed = line.trim_start();
        let marker: String = trimmed.chars().take_while(|c| *c == '`' || *c == '~').collect();
        if marker.len() >= 3 {
            match &fence {
                None => {
                    fence = Some(marker);
                    continue;
                }
                Some(open) if marker.starts_with(open.as_str()) && trimmed.trim_end() == marker => {
                    fence = None;
                    continue;
                }
                _ => {}
            }
        }
        if fence.is_some() {
            continue;
        }
        out.push((n + 1, blank_code_spans(line)));
    }
    out
}

/// `line` with the content of every inline code span replaced by spaces (a span opened by n backticks closes at
/// the next run of exactly n).
fn blank_code_spans(line: &str) -> String {
    let chars: Vec<char> = line.chars().collect();
    let mut out = String::with_capacity(line.len());
    let mut i = 0;
    while i < chars.len() {
        if chars[i] == '`' {
            let run = chars[i..].iter().take_while(|c| **c == '`').count();
            // Find the closing run of the same length.
            let mut j = i + run;
            let mut close = None;
            while j < chars.len() {
                if chars[j] == '`' {
                    let r = chars[j..].iter().take_while(|c| **c == '`').count();
                    if r == run {
                        close = Some(j);
                        break;
                    }
                    j += r;
                } else {
                    j += 1;
                }
            }
            match close {
                Some(j) => {
                    out.extend(std::iter::repeat_n(' ', j + run - i));
                    i = j + run;
                }
                None => {
                    out.extend(&chars[i..i + run]);
                    i += run;
                }
            }
        } else {
            out.push(chars[i]);
            i += 1;
        }
    }
    out
}

/// The targets of the inline links `[text](target)` and reference definitions `[label]: target` of a line.
fn link_targets(line: &str) -> Vec<String> {
    let mut out = Vec::new();
    let bytes = line.as_bytes();
    let mut i = 0;
    while let Some(at) = line[i..].find("](") {
        let start = i + at + 2;
        let mut depth = 0;
        let mut end = None;
        for (k, b) in bytes[start..].iter().enumerate() {
            match b {
                b'(' => depth += 1,
                b')' if depth == 0 => {
                    end = Some(start + k);
                    break;
                }
                b')' => depth -= 1,
                _ => {}
            }
        }
        let Some(end) = end else { break };
        let target = line[start..end].trim();
        // `[text](target "title")`
        let target = target.split_once(" \"").map_or(target, |(t, _)| t);
        out.push(target.trim_matches(['<', '>']).to_string());
        i = end;
    }
    let trimmed = line.trim_start();
    if trimmed.starts_with('[')
        && let Some((label, rest)) = trimmed.split_once("]:")
        && !label.contains(']')
    {
        if let Some(target) = rest.split_whitespace().next() {
            out.push(target.to_string());
        }
    }
    out
}

/// GitHub's anchor of a heading text.
fn slug(heading: &str) -> String {
    // Links in a heading count by their text.
    let mut text = String::new();
    let mut rest = heading;
    while let Some(open) = rest.find('[') {
        match rest[open..].find("](").and_then(|close| rest[open + close..].find(')').map(|end| (close, close + end))) {
            Some((close, end)) => {
                text.push_str(&rest[..open]);
                text.push_str(&rest[open + 1..open + close]);
                rest = &rest[open + end + 1..];
            }
            None => break,
        }
    }
    text.push_str(rest);
    text.trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c),
            _ => None,
        })
        .collect()
}

/// Every anchor a markdown file offers: its headings' slugs (repeats numbered `-1`, `-2`, …) and explicit ids.
fn anchors(file: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(file).unwrap_or_else(|e| panic!("read {}: {e}", file.display()));
    let mut out = Vec::new();
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    let mut fence = false;
    for line in text.lines() {
        let trimmed = line.trim_start();
        if trimmed.starts_with("```") || trimmed.starts_with("~~~") {
            fence = !fence;
            continue;
        }
        if fence {
            continue;
        }
        let hashes = trimmed.chars().take_while(|c| *c == '#').count();
        if (1..=6).contains(&hashes) && trimmed[hashes..].starts_with(' ') {
            let base = slug(trimmed[hashes..].trim().trim_end_matches('#'));
            let n = seen.entry(base.clone()).or_insert(0);
            out.push(if *n == 0 { base.clone() } else { format!("{base}-{n}") });
            *n += 1;
        }
        for attr in ["id=\"", "name=\""] {
            for (at, _) in line.match_indices(attr) {
                if line[..at].contains("<a ") {
                    let value: String = line[at + attr.len()..].chars().take_while(|c| *c != '"').collect();
                    out.push(value);
                }
            }
        }
    }
    out
}

/// `path` with `.` and `..` resolved lexically.
fn normalize(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::CurDir => {}
            other => out.push(other),
        }
    }
    out
}

fn has_scheme(target: &str) -> bool {
    let scheme: String = target.chars().take_while(|c| c.is_ascii_alphanumeric() || matches!(c, '+' | '-' | '.')).collect();
    !scheme.is_empty() && target[scheme.len()..].starts_with(':')
}

/// What is wrong with one link of `doc`, if anything.
fn check(root: &Path, doc: &Path, target: &str) -> Option<String> {
    if target.is_empty() {
        return Some("empty link target".into());
    }
    if has_scheme(target) {
        return None;
    }
    let (path_part, fragment) = match target.split_once('#') {
        Some((p, f)) => (p, Some(f)),
        None => (target, None),
    };
    let path_part = path_part.split('?').next().unwrap();
    let file = if path_part.is_empty() {
        doc.to_path_buf()
    } else if let Some(abs) = path_part.strip_prefix('/') {
        root.join(abs)
    } else {
        normalize(&doc.parent().unwrap().join(path_part))
    };
    if !file.starts_with(root) {
        return Some(format!("{target}: leaves the repository"));
    }
    if !file.exists() {
        return Some(format!("{target}: {} does not exist", file.strip_prefix(root).unwrap_or(&file).display()));
    }
    let fragment = fragment.filter(|f| !f.is_empty())?;
    if file.extension().is_none_or(|e| e != "md") {
        return None; // `file.rs#L10`: line anchors are GitHub's, not checked here
    }
    let offered = anchors(&file);
    (!offered.iter().any(|a| a == fragment)).then(|| {
        let shown = file.strip_prefix(root).unwrap_or(&file).display().to_string();
        let near: Vec<&String> = offered.iter().filter(|a| a.contains(fragment) || fragment.contains(a.as_str())).take(3).collect();
        format!("{target}: {shown} has no heading with anchor #{fragment}{}", if near.is_empty() { String::new() } else { format!(" (similar: {near:?})") })
    })
}

#[test]
fn every_relative_link_of_the_documentation_points_at_something_that_exists() {
    let root = repo_root();
    let docs = documents(&root);
    assert!(docs.len() >= 10, "expected README.md, tasks/README.md and docs/*.md, found {docs:?}");
    let mut broken = Vec::new();
    let mut checked = 0;
    for doc in &docs {
        let text = std::fs::read_to_string(doc).unwrap_or_else(|e| panic!("read {}: {e}", doc.display()));
        for (line, prose) in prose_lines(&text) {
            for target in link_targets(&prose) {
                checked += 1;
                if let Some(why) = check(&root, doc, &target) {
                    broken.push(format!("{}:{line}: {why}", doc.strip_prefix(&root).unwrap().display()));
                }
            }
        }
    }
    assert!(checked >= 50, "found only {checked} links: is the link parser broken?");
    assert!(broken.is_empty(), "broken links in the documentation:\n{}", broken.join("\n"));
}

#[test]
fn the_link_checker_reads_links_and_anchors_like_github() {
    assert_eq!(slug("Deployment: N GPU machines, one PostgreSQL, one bucket"), "deployment-n-gpu-machines-one-postgresql-one-bucket");
    assert_eq!(slug("The agent boundary (threat model)"), "the-agent-boundary-threat-model");
    assert_eq!(slug("What `make serve` and `make test` fetch"), "what-make-serve-and-make-test-fetch");
    assert_eq!(slug("Performance beyond one machine's CPU: a GPU host"), "performance-beyond-one-machines-cpu-a-gpu-host");
    assert_eq!(slug("[Layout](x.md) of crates"), "layout-of-crates");
    assert_eq!(
        link_targets("see [a](docs/a.md#x), [b](b.md \"title\") and [c](https://example.com)"),
        ["docs/a.md#x", "b.md", "https://example.com"]
    );
    assert_eq!(link_targets("[ref]: ../tasks/README.md"), ["../tasks/README.md"]);
    assert_eq!(link_targets(&blank_code_spans("`[not](a link)` but [this](one.md)")), ["one.md"]);
    let fenced = prose_lines("text\n```sh\n[no](link)\n```\n[yes](x)\n");
    assert_eq!(fenced.iter().map(|(n, _)| *n).collect::<Vec<_>>(), [1, 5]);
    assert!(has_scheme("https://x") && has_scheme("mailto:a@b") && !has_scheme("docs/a.md") && !has_scheme("a.md#x:y"));
}
