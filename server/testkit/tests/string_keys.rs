//! JSON read by string key only where the JSON is foreign (docs/ARCHITECTURE.md, "Rules"). A `v["key"]` or
//! `v.get("key")` on a `serde_json::Value` is a field name the compiler cannot check: rename the field where the
//! record is written and the reader silently gets `null`. The project's own records, API replies and documents
//! are typed (`libero_records`'s records, `EpisodeView`, `HarnessManifest`, `ExpertSweepRow`, …), so their
//! readers and writers cannot drift apart. What stays dynamic is JSON that comes from outside and must be read
//! leniently or reported on precisely: tool arguments an agent sends, model-API and harness output, user files
//! under validation, MJCF attribute maps. [`FOREIGN`] names each such file, what it reads and how many reads it
//! has (exactly: a file that gets typed lowers its figure here, a new read in it raises it on purpose).
//! Unit-test modules (`#[cfg(test)] mod …` to the end of the file) and `tests/` folders are not counted.
use std::collections::BTreeMap;

mod source_tree;
use source_tree::{rust_files, server_dir};

/// Files whose string-key reads are of foreign JSON: (path below `server/`, reads, what the JSON is).
const FOREIGN: &[(&str, usize, &str)] = &[
    ("app/src/bench_sim.rs", 1, "the output of the LIBERO Python peer it measures against"),
    ("app/src/cmd_mcp_stdio.rs", 3, "JSON-RPC messages relayed between a stdio harness and the server"),
    ("app/src/cmd_sim.rs", 1, "an action file a user passes on the command line (each action's error reported)"),
    ("episode/src/actor.rs", 1, "the actions an agent sends in `osc_sequence`'s arguments"),
    ("episode/src/call.rs", 3, "an agent's MCP tool arguments, checked key by key with the protocol's messages"),
    ("episode/src/demo/mod.rs", 1, "an action row of a bundle under validation"),
    ("episode/src/demo/project.rs", 15, "the agent-visible bundle under validation (exact key sets, each wrong value named)"),
    ("episode/src/demo/record.rs", 1, "a stored replay-check list the typed view cannot read, kept and written back as it was"),
    ("episode/src/demo/validate.rs", 49, "a demonstration bundle under validation, possibly not ours (exact key sets, each wrong value named)"),
    ("records/src/action_event.rs", 1, "the actions an agent sent, as logged"),
    ("records/src/expert_sweep.rs", 1, "an older row's ill-typed `error`, kept in the record's unnamed keys"),
    ("records/src/result.rs", 1, "an ill-typed `infrastructure_error`, kept in the record's unnamed keys"),
    ("runner/src/cli_checks.rs", 8, "the harness CLIs' own output (`codex mcp get --json`, …)"),
    ("runner/src/transcript.rs", 44, "the harnesses' transcripts (six CLIs' event formats)"),
    ("runner/src/usage.rs", 5, "the harnesses' usage logs"),
    ("sandbox/src/netgate/usage.rs", 3, "model-API responses (token counts of each provider's format)"),
    ("server/src/client.rs", 3, "MCP's JSON-RPC envelope (`result`, `id`, the tools' names)"),
    ("server/src/mcp_gate.rs", 8, "JSON-RPC messages from agents, read before any reaches rmcp"),
    ("sim/src/compose/mjxml.rs", 12, "attribute maps of the LIBERO assets' MJCF (XML, not JSON)"),
    ("sim/src/compose/mod.rs", 13, "attribute maps of the LIBERO assets' MJCF (XML, not JSON)"),
    ("sim/src/compose/xml.rs", 4, "attribute maps of the LIBERO assets' MJCF (XML, not JSON)"),
];

/// Reads by string key in `source` outside comments and its unit-test module: `["key"]` and `.get("key")` with a
/// lower-case key.
fn string_key_reads(source: &str) -> usize {
    let mut count = 0;
    let mut lines = source.lines().peekable();
    while let Some(line) = lines.next() {
        let trimmed = line.trim_start();
        if trimmed.starts_with("#[cfg(test)]") && lines.peek().is_some_and(|next| next.trim_start().starts_with("mod ")) {
            break;
        }
        if trimmed.starts_with("//") {
            continue;
        }
        count += occurrences(line, "[\"", "\"]") + occurrences(line, ".get(\"", "\")");
    }
    count
}

/// How often `line` reads `open` + a key (`[a-z0-9_]+`) + `close`. An index (`["k"]`) counts only after a value
/// (an identifier, `)` or `]`: not a slice literal such as `&["a"]` or `vec!["a"]`) and not when it is assigned to
/// (`v["k"] = …`, a write of a document being built).
fn occurrences(line: &str, open: &str, close: &str) -> usize {
    let bytes = line.as_bytes();
    let mut n = 0;
    let mut from = 0;
    while let Some(found) = line[from..].find(open) {
        let at = from + found;
        from = at + open.len();
        let after = &line[from..];
        let key_len = after.bytes().take_while(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || *b == b'_').count();
        if key_len == 0 || !after[key_len..].starts_with(close) {
            continue;
        }
        if open.starts_with('[') {
            let before = at.checked_sub(1).map(|i| bytes[i]);
            let indexes_a_value = before.is_some_and(|b| b.is_ascii_alphanumeric() || matches!(b, b'_' | b')' | b']'));
            let rest = after[key_len + close.len()..].trim_start();
            let assigned = rest.starts_with('=') && !rest.starts_with("==");
            if !indexes_a_value || assigned {
                continue;
            }
        }
        n += 1;
    }
    n
}

#[test]
fn json_is_read_by_string_key_only_where_it_is_foreign() {
    let server = server_dir();
    let mut found: BTreeMap<String, usize> = BTreeMap::new();
    for krate in std::fs::read_dir(&server).unwrap().flatten() {
        let src = krate.path().join("src");
        if !src.is_dir() {
            continue;
        }
        let mut files = Vec::new();
        rust_files(&src, &mut files);
        for file in files {
            let n = string_key_reads(&std::fs::read_to_string(&file).unwrap());
            if n > 0 {
                found.insert(file.strip_prefix(&server).unwrap().to_string_lossy().replace('\\', "/"), n);
            }
        }
    }
    let mut wrong = Vec::new();
    for (path, n) in &found {
        match FOREIGN.iter().find(|(p, _, _)| p == path) {
            None => wrong.push(format!("{path}: {n} string-key reads of JSON this project writes: read it through its type")),
            Some((_, allowed, _)) if allowed != n => {
                wrong.push(format!("{path}: {n} string-key reads, FOREIGN says {allowed}: update the figure if the new reads are of foreign JSON"))
            }
            Some(_) => {}
        }
    }
    for (path, allowed, _) in FOREIGN {
        if !found.contains_key(*path) {
            wrong.push(format!("{path}: no string-key reads left (FOREIGN says {allowed}): drop it from FOREIGN"));
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

#[test]
fn the_counter_sees_index_and_get_reads_but_not_comments_or_test_modules() {
    let source = "let a = v[\"name\"].as_str();\nlet b = v.get(\"id\");\nlet c = f()[\"k\"] == x[\"k2\"];\n\
                  // v[\"doc\"]\nlet d = m[\"Key\"]; let e = v[0]; let s = &[\"slice\"]; let t = vec![\"a\"];\n\
                  doc[\"written\"] = json!(1);\n#[cfg(test)]\nmod tests {\n    fn f() { v[\"x\"]; }\n}\n";
    assert_eq!(string_key_reads(source), 4);
}
