//! The documentation's links and the paths and commands it cites hold.
//!
//! Links: every relative link in `README.md` and `docs/*.md` (and in the other markdown files they are the map to:
//! `tasks/README.md`) names a file or folder that exists, and a link with a `#fragment` into a markdown file names
//! one of its headings (GitHub's anchors: lower case, punctuation dropped, spaces as `-`, repeats numbered) or an
//! explicit `<a id=…>`/`<a name=…>`. Links with a scheme (`https:`, `mailto:`) are not checked; code spans and
//! fenced code blocks are not links.
//!
//! Code: in the code spans and fenced blocks of the same documents, (1) every path that starts at a top-level entry
//! of the repository (`server/app/tests/x.rs`, `tests/dashboard/x.cjs`, `scripts/setup.py`) exists, and a
//! `file.rs::name` names a `fn name` of that file; (2) a shorter Rust or script path (`families/vlabench/expert.rs`)
//! is the end of some file's path; (3) every `libero-agent <command> … --flag` names a command and flags that
//! [docs/cli.md](../../../docs/cli.md) lists (that file is the binary's own `--help`, held by
//! `server/app/tests/cli_reference.rs`). Not checked: URLs, placeholders (`{id}`, `<dir>`, `…`, `*`), paths inside
//! a run, data or workspace folder (they do not start at the repository's top), and the files of other projects that
//! some notes describe ([`ELSEWHERE`]).
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Component, Path, PathBuf};

mod source_tree;
use source_tree::{repo_root, repository_files};

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

/// The lines of a markdown text with their numbers, each marked whether it is inside a fenced code block (the fence
/// lines themselves left out).
fn lines_and_fences(text: &str) -> Vec<(usize, &str, bool)> {
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
        out.push((n + 1, line, fence.is_some()));
    }
    out
}

/// The lines of a markdown text outside fenced code blocks, with their numbers, inline code spans blanked.
fn prose_lines(text: &str) -> Vec<(usize, String)> {
    lines_and_fences(text).into_iter().filter(|(_, _, fenced)| !fenced).map(|(n, line, _)| (n, blank_code_spans(line))).collect()
}

/// The inline code spans of a text: for each, the range of its characters with its backtick fences, and of its content
/// (a span opened by n backticks closes at the next run of exactly n; one without a closing run is not a span).
fn code_span_ranges(chars: &[char]) -> Vec<(std::ops::Range<usize>, std::ops::Range<usize>)> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < chars.len() {
        if chars[i] != '`' {
            i += 1;
            continue;
        }
        let run = chars[i..].iter().take_while(|c| **c == '`').count();
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
                out.push((i..j + run, i + run..j));
                i = j + run;
            }
            None => i += run,
        }
    }
    out
}

/// `line` with the content of every inline code span replaced by spaces.
fn blank_code_spans(line: &str) -> String {
    let mut chars: Vec<char> = line.chars().collect();
    for (whole, _) in code_span_ranges(&chars.clone()) {
        chars[whole].fill(' ');
    }
    chars.into_iter().collect()
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

/// Files of other projects that a document describes by their own paths (the reference Python implementation,
/// robosuite, LIBERO's assets), which happen to start like a folder of this repository: (document, path).
const ELSEWHERE: &[(&str, &str)] = &[
    ("docs/protocol.md", "docs/PROTOCOL.md"),
    ("docs/protocol.md", "scripts/run_benchmark.py"),
    ("docs/protocol.md", "scripts/smoke_install.py"),
    ("docs/libero_port_notes.md", "assets/scenes/"),
    ("docs/libero_port_notes.md", "assets/textures/"),
    ("docs/libero_port_notes.md", "tasks/task.py"),
];

/// The code of a markdown text with the line each piece starts on: every inline code span of its prose (a span may
/// wrap onto the next line of its paragraph) and every line of its fenced blocks (a line ending in `\` joined with
/// the next).
fn code_texts(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut paragraph: Vec<(usize, &str)> = Vec::new();
    let mut continued: Option<(usize, String)> = None;
    let flush = |paragraph: &mut Vec<(usize, &str)>, out: &mut Vec<(usize, String)>| {
        let joined: Vec<char> = paragraph.iter().map(|(_, l)| *l).collect::<Vec<_>>().join("\n").chars().collect();
        for (whole, content) in code_span_ranges(&joined) {
            let line = paragraph[0].0 + joined[..whole.start].iter().filter(|c| **c == '\n').count();
            out.push((line, joined[content].iter().collect::<String>().replace('\n', " ")));
        }
        paragraph.clear();
    };
    for (n, line, fenced) in lines_and_fences(text) {
        let trimmed = line.trim_start();
        if fenced {
            flush(&mut paragraph, &mut out);
            let (start, mut joined) = continued.take().unwrap_or((n, String::new()));
            let piece = if joined.is_empty() { line.trim_end() } else { line.trim() };
            joined.push_str(piece.trim_end_matches('\\'));
            if line.trim_end().ends_with('\\') {
                continued = Some((start, joined + " "));
            } else {
                out.push((start, joined));
            }
            continue;
        }
        // A blank line ends a paragraph; a table row is one of its own.
        if trimmed.is_empty() || trimmed.starts_with('|') {
            flush(&mut paragraph, &mut out);
            if trimmed.starts_with('|') {
                paragraph.push((n, line));
                flush(&mut paragraph, &mut out);
            }
            continue;
        }
        paragraph.push((n, line));
    }
    flush(&mut paragraph, &mut out);
    out
}

/// The words of a piece of code that could be paths: split at spaces and shell or markdown punctuation, trailing
/// sentence punctuation dropped; placeholders and URLs left out.
fn path_words(code: &str) -> Vec<&str> {
    code.split(|c: char| c.is_whitespace() || matches!(c, ',' | ';' | '(' | ')' | '[' | ']' | '"' | '\'' | '=' | '`'))
        .map(|w| w.trim_end_matches(['.', ':']))
        .filter(|w| w.contains('/') && !w.contains("://"))
        .filter(|w| !w.contains(['{', '}', '<', '>', '…', '*', '$', '~', '|', '%', '@']) && !w.contains(".."))
        .collect()
}

/// What is wrong with one path word of `doc` (`top`: the repository's top-level entries, `files`: its files, relative).
fn check_path(root: &Path, doc: &str, word: &str, top: &BTreeSet<String>, files: &[String]) -> Option<String> {
    // `file.rs::item`, `file.rs:12`, `doc.md#anchor`: the file, and the item it names.
    let (file, item) = match word.split_once("::") {
        Some((file, item)) => (file, Some(item)),
        None => (word, None),
    };
    let file = file.split('#').next().unwrap();
    let file = file.split_once(':').map_or(file, |(f, line)| if line.chars().all(|c| c.is_ascii_digit()) { f } else { file });
    if ELSEWHERE.contains(&(doc, file)) {
        return None;
    }
    let first = file.split('/').next().unwrap();
    if top.contains(first) && file.len() > first.len() + 1 {
        let path = root.join(file);
        if !path.exists() {
            let name = file.rsplit('/').find(|s| !s.is_empty()).unwrap_or(file);
            let found: Vec<&String> = files.iter().filter(|f| f.ends_with(&format!("/{name}")) || *f == name).take(3).collect();
            return Some(format!("`{word}`: {file} does not exist{}", if found.is_empty() { String::new() } else { format!(" (files of that name: {found:?})") }));
        }
        let item = item.map(|i| i.split("::").last().unwrap()).filter(|i| !i.is_empty() && file.ends_with(".rs"))?;
        let text = std::fs::read_to_string(&path).unwrap_or_default();
        let defined = text.match_indices(&format!("fn {item}")).any(|(at, _)| {
            !text[at + 3 + item.len()..].starts_with(|c: char| c.is_alphanumeric() || c == '_')
        });
        return (!defined && !text.contains(&format!("mod {item}"))).then(|| format!("`{word}`: {file} has no `fn {item}`"));
    }
    // A shorter path of this project's own code: some file's path must end with it.
    if [".rs", ".cjs"].iter().any(|e| file.ends_with(e)) && !files.iter().any(|f| f.ends_with(&format!("/{file}"))) {
        return Some(format!("`{word}`: no file of the repository ends with {file}"));
    }
    None
}

/// The commands of the binary's reference (docs/cli.md): the command path (`""`, `tasks`, `tasks list`) → its flags
/// (`--tasks`, `-h`).
fn cli_reference(root: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let text = std::fs::read_to_string(root.join("docs/cli.md")).expect("docs/cli.md");
    let mut out: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let mut current: Option<String> = None;
    for line in text.lines() {
        if let Some(heading) = line.strip_prefix("## `libero-agent").and_then(|h| h.strip_suffix('`')) {
            current = Some(heading.trim().to_string());
            out.entry(heading.trim().to_string()).or_default();
            continue;
        }
        let (Some(command), trimmed) = (&current, line.trim_start()) else { continue };
        if !trimmed.starts_with('-') || trimmed.len() == line.len() {
            continue;
        }
        for word in trimmed.split([',', ' ']).take_while(|w| w.starts_with('-') || w.is_empty()).filter(|w| !w.is_empty()) {
            let flag: String = word.chars().take_while(|c| c.is_alphanumeric() || *c == '-').collect();
            if flag.len() > 1 {
                out.get_mut(command).unwrap().insert(flag);
            }
        }
    }
    out
}

/// What is wrong with the `libero-agent` commands in a piece of code: each command must be one of the reference's
/// and each flag one its command takes.
fn check_commands(code: &str, cli: &BTreeMap<String, BTreeSet<String>>) -> Vec<String> {
    // `$(mktemp -d)` is another program's.
    let mut code = code.to_string();
    while let Some(open) = code.find("$(") {
        let close = code[open..].find(')').map_or(code.len(), |c| open + c + 1);
        code.replace_range(open..close, "X");
    }
    let words: Vec<&str> = code.split_whitespace().collect();
    let mut out = Vec::new();
    for (k, word) in words.iter().enumerate() {
        let is_binary = *word == "libero-agent" || word.ends_with("/libero-agent");
        if !is_binary || (k > 0 && matches!(words[k - 1], "-p" | "--package" | "--bin")) {
            continue;
        }
        let mut command = String::new();
        let mut after_flag = false;
        for raw in &words[k + 1..] {
            if matches!(*raw, "|" | "&&" | "||" | ";" | ">" | "2>&1" | "&") {
                break;
            }
            let word = raw.trim_matches(['[', ']', '(', ')', '\'', '"']).trim_end_matches([',', '.', ':', ';']);
            if word.is_empty() {
                continue;
            }
            if word.starts_with('-') {
                let flag = word.split('=').next().unwrap();
                if !flag.contains(['…', '<']) && !cli[&command].contains(flag) {
                    out.push(format!("`libero-agent {command}` has no flag {flag}"));
                }
                after_flag = !word.contains('=');
                continue;
            }
            let deeper = if command.is_empty() { word.to_string() } else { format!("{command} {word}") };
            let has_subcommands = cli.keys().any(|c| c.starts_with(&format!("{command} ")) || (command.is_empty() && !c.is_empty()));
            if cli.contains_key(&deeper) && !after_flag {
                command = deeper;
            } else if word.contains(['<', '…', '{', '*', '|']) || word.chars().all(|c| c.is_ascii_uppercase() || c == '_') {
                // A placeholder (`<cmd>`, `[OPTIONS]`, `BATCH`) or a choice (`tasks list|show`): what follows is not
                // one command.
                if has_subcommands && !after_flag {
                    break;
                }
            } else if has_subcommands && !after_flag && command.split(' ').count() < 2 && !cli.contains_key(&deeper) {
                out.push(format!("`libero-agent {command}` has no command {word}"));
                break;
            }
            after_flag = false;
        }
    }
    out
}

#[test]
fn every_path_and_command_the_documentation_cites_exists() {
    let root = repo_root();
    let files: Vec<String> = repository_files(&root)
        .iter()
        .map(|f| f.strip_prefix(&root).unwrap().to_string_lossy().to_string())
        .collect();
    let top: BTreeSet<String> = files.iter().map(|f| f.split('/').next().unwrap().to_string()).collect();
    let cli = cli_reference(&root);
    assert!(cli.len() >= 20 && cli["run"].contains("--tasks"), "docs/cli.md read as {} commands: is its reader broken?", cli.len());
    let mut wrong = Vec::new();
    let (mut paths, mut commands) = (0, 0);
    let mut used_elsewhere = BTreeSet::new();
    for doc in documents(&root) {
        let shown = doc.strip_prefix(&root).unwrap().to_string_lossy().to_string();
        let text = std::fs::read_to_string(&doc).unwrap_or_else(|e| panic!("read {shown}: {e}"));
        for (line, code) in code_texts(&text) {
            for word in path_words(&code) {
                paths += 1;
                if let Some(e) = ELSEWHERE.iter().find(|(d, p)| *d == shown && word.starts_with(p)) {
                    used_elsewhere.insert(*e);
                }
                if let Some(why) = check_path(&root, &shown, word, &top, &files) {
                    wrong.push(format!("{shown}:{line}: {why}"));
                }
            }
            commands += code.matches("libero-agent ").count();
            for why in check_commands(&code, &cli) {
                wrong.push(format!("{shown}:{line}: {why} (in `{code}`)"));
            }
        }
    }
    assert!(paths >= 300 && commands >= 60, "found only {paths} paths and {commands} commands: is the reader broken?");
    let unused: Vec<_> = ELSEWHERE.iter().filter(|e| !used_elsewhere.contains(e)).collect();
    assert!(unused.is_empty(), "ELSEWHERE lists paths no document cites any more: {unused:?}");
    assert!(wrong.is_empty(), "the documentation cites what does not exist:\n{}", wrong.join("\n"));
}

#[test]
fn the_code_checker_reads_spans_paths_and_commands() {
    // Spans wrap onto the next line of their paragraph; fenced lines are code; a blank line ends a paragraph.
    let texts = code_texts("see `a/b.rs\nc` and `d`\n\n```sh\nx \\\n  --y\nz\n```\n`e");
    assert_eq!(texts, [(1, "a/b.rs c".into()), (2, "d".into()), (5, "x  --y".into()), (7, "z".into())]);
    assert_eq!(path_words("cat server/a.rs, `tests/{id}.rs` <dir>/x.rs https://a/b runs/…/x.json docs/a.md."), ["server/a.rs", "docs/a.md"]);
    let root = repo_root();
    let files: Vec<String> = vec!["server/testkit/tests/doc_links.rs".into(), "server/app/tests/x.rs".into()];
    let top: BTreeSet<String> = ["server", "tests", "docs"].map(String::from).into();
    let check = |word: &str| check_path(&root, "docs/a.md", word, &top, &files);
    assert_eq!(check("server/testkit/tests/doc_links.rs"), None);
    assert_eq!(check("server/testkit/tests/doc_links.rs::the_code_checker_reads_spans_paths_and_commands"), None);
    assert!(check("server/testkit/tests/doc_links.rs::no_such_test").is_some());
    assert!(check("tests/x.rs").unwrap().contains("server/app/tests/x.rs"), "a short path is named with where the file is");
    assert!(check("server/app/tests/gone.rs").is_some());
    assert_eq!(check("app/tests/x.rs"), None);
    assert!(check("families/gone.rs").is_some());
    assert_eq!(check("runs/batch/result.json"), None);
    assert_eq!(check_path(&root, "docs/protocol.md", "scripts/run_benchmark.py", &top, &files), None);
    let cli = cli_reference(&root);
    assert!(check_commands("libero-agent run --experiment main_table --tasks T11 [--dry-run]", &cli).is_empty());
    assert!(check_commands("libero-agent --log-format json serve --addr 127.0.0.1:8080 --data $(mktemp -d)", &cli).is_empty());
    assert!(check_commands("cargo test -p libero-agent --test cli_reference; libero-agent <cmd> --help", &cli).is_empty());
    assert_eq!(check_commands("libero-agent expert --tasks robomemarena --filter x", &cli), ["`libero-agent expert` has no flag --filter"]);
    assert_eq!(check_commands("target/release/libero-agent tasks lst", &cli), ["`libero-agent tasks` has no command lst"]);
    assert_eq!(check_commands("libero-agent frobnicate", &cli), ["`libero-agent ` has no command frobnicate"]);
}
