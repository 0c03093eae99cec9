//! No import circle inside any crate of the workspace (docs/ARCHITECTURE.md, "Rules"): the modules of every crate
//! under `server/*/src` form a directed graph by the `crate::…`, `super::…` and `self::…` paths their code names (in
//! `use` trees and in expressions; comments are not imports), and that graph has no cycle. A circle means two modules
//! each need the other, so neither can be read, tested or moved alone; the shared items belong in the module lower in
//! the order, or in a small module of their own.
//!
//! Nodes are file modules (`src/a.rs` and `src/a/mod.rs` are `a`, `src/a/b.rs` is `a::b`; inline modules such as
//! `mod tests` belong to their file). A path counts as a reference to the longest file module it starts with. A
//! module's references to its own ancestors (`super::Item` of a `mod.rs`, the crate root's re-exports) are not
//! edges: a parent declares and owns its children, so only references across the tree can close a circle.
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

mod source_tree;
use source_tree::{module_path, rust_files, server_dir};

/// One compilation unit: the library (`src/lib.rs`), the binary (`src/main.rs`) or a `src/bin/*.rs` binary, each
/// with the file modules that belong to it.
struct Unit {
    name: String,
    /// File module path (`a::b`; the root is empty) → file.
    modules: BTreeMap<String, PathBuf>,
}

fn units(crate_dir: &Path) -> Vec<Unit> {
    let src = crate_dir.join("src");
    let crate_name = crate_dir.file_name().unwrap().to_string_lossy().to_string();
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let bin_dir = src.join("bin");
    let mut out = Vec::new();
    let main_modules: BTreeMap<String, PathBuf> = files
        .iter()
        .filter(|f| !f.starts_with(&bin_dir))
        .map(|f| (module_path(&src, f), f.clone()))
        .collect();
    // A crate with both lib.rs and main.rs: main.rs is a root of its own that reaches the library by name.
    let has_lib = src.join("lib.rs").is_file();
    let has_main = src.join("main.rs").is_file();
    if has_lib || has_main {
        let mut modules = main_modules;
        if has_lib && has_main {
            modules.insert(String::new(), src.join("lib.rs"));
        }
        out.push(Unit { name: crate_name.clone(), modules });
    }
    if bin_dir.is_dir() {
        for f in files.iter().filter(|f| f.starts_with(&bin_dir)) {
            let rel = f.strip_prefix(&bin_dir).unwrap();
            // `src/bin/x.rs` is a root; `src/bin/x/main.rs` and the files beside it form the unit `x`.
            let (name, root_dir) = if rel.components().count() == 1 {
                (rel.to_string_lossy().trim_end_matches(".rs").to_string(), None)
            } else {
                let first = rel.iter().next().unwrap().to_string_lossy().to_string();
                (first.clone(), Some(bin_dir.join(first)))
            };
            let unit_name = format!("{crate_name} (bin {name})");
            let module = match &root_dir {
                None => String::new(),
                Some(dir) => module_path(dir, f),
            };
            match out.iter_mut().find(|u| u.name == unit_name) {
                Some(u) => {
                    u.modules.insert(module, f.clone());
                }
                None => out.push(Unit { name: unit_name, modules: BTreeMap::from([(module, f.clone())]) }),
            }
        }
    }
    out
}

/// The text of `line` before a `//` comment that is not inside a string literal.
fn strip_line_comment(line: &str) -> &str {
    let bytes = line.as_bytes();
    let mut in_string = false;
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'\\' if in_string => i += 1,
            b'"' => in_string = !in_string,
            b'/' if !in_string && bytes.get(i + 1) == Some(&b'/') => return &line[..i],
            _ => {}
        }
        i += 1;
    }
    line
}

/// The file's code without comments (line comments and `/* … */` blocks), with the inline-module nesting of every
/// line: the names of the `mod name {` blocks it sits in.
fn code_lines(text: &str) -> Vec<(usize, String, Vec<String>)> {
    let mut out = Vec::new();
    let mut in_block = false;
    let mut depth: i64 = 0;
    let mut inline: Vec<(String, i64)> = Vec::new();
    for (n, raw) in text.lines().enumerate() {
        let mut line = String::new();
        let mut rest = raw;
        loop {
            if in_block {
                match rest.find("*/") {
                    Some(i) => {
                        rest = &rest[i + 2..];
                        in_block = false;
                    }
                    None => break,
                }
            } else {
                let code = strip_line_comment(rest);
                match code.find("/*") {
                    Some(i) => {
                        line.push_str(&code[..i]);
                        rest = &code[i + 2..];
                        in_block = true;
                    }
                    None => {
                        line.push_str(code);
                        break;
                    }
                }
            }
        }
        let trimmed = line.trim_start();
        let declared = trimmed
            .strip_prefix("pub ")
            .or_else(|| trimmed.strip_prefix("pub(crate) "))
            .or_else(|| trimmed.strip_prefix("pub(super) "))
            .unwrap_or(trimmed)
            .strip_prefix("mod ")
            .filter(|r| r.contains('{'))
            .map(|r| r.split(|c: char| !(c.is_alphanumeric() || c == '_')).next().unwrap_or("").to_string());
        let nesting: Vec<String> = inline.iter().map(|(name, _)| name.clone()).collect();
        out.push((n + 1, line.clone(), nesting));
        if let Some(name) = declared {
            inline.push((name, depth));
        }
        for c in line.chars() {
            match c {
                '{' => depth += 1,
                '}' => {
                    depth -= 1;
                    while inline.last().is_some_and(|(_, d)| depth <= *d) {
                        inline.pop();
                    }
                }
                _ => {}
            }
        }
    }
    out
}

/// Every path of a `use` tree: `a::{b, c::{d as e, *}}` gives `a::b`, `a::c::d`, `a::c`.
fn expand_use_tree(tree: &str) -> Vec<String> {
    fn parse(s: &str, prefix: &str, out: &mut Vec<String>) {
        let s = s.trim();
        if let Some(open) = s.find('{') {
            let head = s[..open].trim().trim_end_matches("::");
            let inner = &s[open + 1..s.rfind('}').unwrap_or(s.len())];
            let base = join(prefix, head);
            let mut level = 0;
            let mut start = 0;
            for (i, c) in inner.char_indices() {
                match c {
                    '{' => level += 1,
                    '}' => level -= 1,
                    ',' if level == 0 => {
                        parse(&inner[start..i], &base, out);
                        start = i + 1;
                    }
                    _ => {}
                }
            }
            parse(&inner[start..], &base, out);
        } else {
            let item = s.split(" as ").next().unwrap().trim();
            if item.is_empty() {
                return;
            }
            let item = item.trim_end_matches("::*").trim_end_matches('*');
            out.push(if item == "self" { prefix.to_string() } else { join(prefix, item) });
        }
    }
    fn join(a: &str, b: &str) -> String {
        match (a.is_empty(), b.is_empty()) {
            (true, _) => b.to_string(),
            (_, true) => a.to_string(),
            _ => format!("{a}::{b}"),
        }
    }
    let mut out = Vec::new();
    parse(tree, "", &mut out);
    out
}

/// The paths a file names, each with its line and the inline-module nesting it was named in.
fn named_paths(file: &Path) -> Vec<(usize, String, Vec<String>)> {
    let text = std::fs::read_to_string(file).unwrap_or_else(|e| panic!("read {}: {e}", file.display()));
    let lines = code_lines(&text);
    let mut out = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let (n, line, nesting) = &lines[i];
        let trimmed = line.trim_start();
        let after_vis = ["pub(crate) ", "pub(super) ", "pub "].iter().find_map(|v| trimmed.strip_prefix(v)).unwrap_or(trimmed);
        if let Some(rest) = after_vis.strip_prefix("use ") {
            // A `use` statement, possibly over several lines, up to its `;`.
            let mut stmt = rest.to_string();
            while !stmt.contains(';') && i + 1 < lines.len() {
                i += 1;
                stmt.push(' ');
                stmt.push_str(&lines[i].1);
            }
            let stmt = stmt.split(';').next().unwrap();
            for path in expand_use_tree(stmt) {
                out.push((*n, path, nesting.clone()));
            }
        } else {
            for start in ["crate::", "super::", "self::"] {
                for (at, _) in line.match_indices(start) {
                    let before = line[..at].chars().last();
                    if before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == ':') {
                        continue; // `libero_tasks::crate::…` cannot happen; `foo::self::` is not ours
                    }
                    let path: String =
                        line[at..].chars().take_while(|c| c.is_alphanumeric() || *c == '_' || *c == ':').collect();
                    out.push((*n, path.trim_end_matches(':').to_string(), nesting.clone()));
                }
            }
        }
        i += 1;
    }
    out
}

/// The file module a path refers to, from the file module `from` nested in the inline modules `nesting`; `None` for
/// paths outside the crate (another crate, `std`).
fn resolve(unit: &Unit, from: &str, nesting: &[String], path: &str) -> Option<String> {
    let mut segments: Vec<&str> = path.split("::").filter(|s| !s.is_empty()).collect();
    let mut base: Vec<String> = match segments.first() {
        Some(&"crate") => {
            segments.remove(0);
            Vec::new()
        }
        Some(&"super") | Some(&"self") => {
            let mut here: Vec<String> = from.split("::").filter(|s| !s.is_empty()).map(String::from).collect();
            here.extend(nesting.iter().cloned());
            while let Some(first) = segments.first() {
                match *first {
                    "super" => {
                        here.pop();
                    }
                    "self" => {}
                    _ => break,
                }
                segments.remove(0);
            }
            here
        }
        _ => return None,
    };
    base.extend(segments.iter().map(|s| s.to_string()));
    // The longest prefix that is a file module of this unit.
    while !base.is_empty() {
        let candidate = base.join("::");
        if unit.modules.contains_key(&candidate) {
            return Some(candidate);
        }
        base.pop();
    }
    Some(String::new())
}

fn is_ancestor(ancestor: &str, module: &str) -> bool {
    ancestor.is_empty() || module.starts_with(&format!("{ancestor}::"))
}

/// The import graph of a unit: module → module → the first `file:line` naming it.
fn graph(unit: &Unit, root: &Path) -> BTreeMap<String, BTreeMap<String, String>> {
    let mut edges: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
    for (module, file) in &unit.modules {
        for (line, path, nesting) in named_paths(file) {
            let Some(target) = resolve(unit, module, &nesting, &path) else { continue };
            if &target == module || is_ancestor(&target, module) {
                continue;
            }
            let shown = format!("{}:{line}", file.strip_prefix(root).unwrap_or(file).display());
            edges.entry(module.clone()).or_default().entry(target).or_insert(shown);
        }
    }
    edges
}

/// The strongly connected components of more than one module (Tarjan), each sorted.
fn cycles(edges: &BTreeMap<String, BTreeMap<String, String>>, nodes: &BTreeSet<String>) -> Vec<Vec<String>> {
    struct State<'a> {
        edges: &'a BTreeMap<String, BTreeMap<String, String>>,
        index: BTreeMap<String, usize>,
        low: BTreeMap<String, usize>,
        stack: Vec<String>,
        on_stack: BTreeSet<String>,
        next: usize,
        out: Vec<Vec<String>>,
    }
    fn visit(s: &mut State, v: &str) {
        s.index.insert(v.to_string(), s.next);
        s.low.insert(v.to_string(), s.next);
        s.next += 1;
        s.stack.push(v.to_string());
        s.on_stack.insert(v.to_string());
        let targets: Vec<String> = s.edges.get(v).map(|m| m.keys().cloned().collect()).unwrap_or_default();
        for w in targets {
            if !s.index.contains_key(&w) {
                visit(s, &w);
                let low = s.low[v].min(s.low[&w]);
                s.low.insert(v.to_string(), low);
            } else if s.on_stack.contains(&w) {
                let low = s.low[v].min(s.index[&w]);
                s.low.insert(v.to_string(), low);
            }
        }
        if s.low[v] == s.index[v] {
            let mut component = Vec::new();
            loop {
                let w = s.stack.pop().unwrap();
                s.on_stack.remove(&w);
                let done = w == v;
                component.push(w);
                if done {
                    break;
                }
            }
            if component.len() > 1 {
                component.sort();
                s.out.push(component);
            }
        }
    }
    let mut s = State {
        edges,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on_stack: BTreeSet::new(),
        next: 0,
        out: Vec::new(),
    };
    for v in nodes {
        if !s.index.contains_key(v) {
            visit(&mut s, v);
        }
    }
    s.out
}

/// One circle through the component's first module, with the line that makes each step.
fn describe(component: &[String], edges: &BTreeMap<String, BTreeMap<String, String>>) -> String {
    let members: BTreeSet<&String> = component.iter().collect();
    let start = &component[0];
    // Breadth-first from start back to start inside the component.
    let mut previous: BTreeMap<String, String> = BTreeMap::new();
    let mut queue = std::collections::VecDeque::from([start.clone()]);
    let mut found = None;
    while let Some(v) = queue.pop_front() {
        for w in edges.get(&v).map(|m| m.keys().cloned().collect::<Vec<_>>()).unwrap_or_default() {
            if !members.contains(&w) {
                continue;
            }
            if &w == start {
                found = Some(v.clone());
                break;
            }
            if !previous.contains_key(&w) {
                previous.insert(w.clone(), v.clone());
                queue.push_back(w);
            }
        }
        if found.is_some() {
            break;
        }
    }
    let mut path = vec![start.clone()];
    let mut v = found.expect("a component has a circle");
    while &v != start {
        path.push(v.clone());
        v = previous[&v].clone();
    }
    path.push(start.clone());
    let end = path.len() - 1;
    path[1..end].reverse();
    let shown = |m: &str| if m.is_empty() { "(crate root)".to_string() } else { m.to_string() };
    let mut lines = vec![format!("  {}", path.iter().map(|m| shown(m)).collect::<Vec<_>>().join(" → "))];
    for pair in path.windows(2) {
        lines.push(format!("    {} → {} ({})", shown(&pair[0]), shown(&pair[1]), edges[&pair[0]][&pair[1]]));
    }
    if component.len() > 2 {
        lines.push(format!("    (all modules of this circle: {})", component.join(", ")));
    }
    lines.join("\n")
}

#[test]
fn no_crate_has_an_import_circle_between_its_modules() {
    let server = server_dir();
    let root = server.join("..").canonicalize().unwrap();
    let mut report = Vec::new();
    let mut crates = 0;
    let mut modules = 0;
    let mut entries: Vec<PathBuf> = std::fs::read_dir(&server).unwrap().map(|e| e.unwrap().path()).collect();
    entries.sort();
    for crate_dir in entries.into_iter().filter(|d| d.join("src").is_dir()) {
        crates += 1;
        for unit in units(&crate_dir) {
            modules += unit.modules.len();
            let edges = graph(&unit, &root);
            let nodes: BTreeSet<String> = unit.modules.keys().cloned().collect();
            for component in cycles(&edges, &nodes) {
                report.push(format!("{}:\n{}", unit.name, describe(&component, &edges)));
            }
        }
    }
    assert!(crates >= 12 && modules > 100, "expected the workspace's crates under {}: {crates} crates, {modules} modules", server.display());
    assert!(
        report.is_empty(),
        "import circles between modules (move the shared items to the module lower in the order, or to a small module \
         of their own):\n{}",
        report.join("\n")
    );
}

#[test]
fn the_cycle_finder_sees_a_circle_and_reads_use_trees() {
    let edges = BTreeMap::from([
        ("a".to_string(), BTreeMap::from([("b".to_string(), "a.rs:1".to_string())])),
        ("b".to_string(), BTreeMap::from([("c".to_string(), "b.rs:2".to_string())])),
        ("c".to_string(), BTreeMap::from([("a".to_string(), "c.rs:3".to_string())])),
    ]);
    let nodes: BTreeSet<String> = ["a", "b", "c", "d"].iter().map(|s| s.to_string()).collect();
    let found = cycles(&edges, &nodes);
    assert_eq!(found, vec![vec!["a".to_string(), "b".to_string(), "c".to_string()]]);
    let text = describe(&found[0], &edges);
    assert!(text.contains("a → b → c → a") && text.contains("c → a (c.rs:3)"), "{text}");
    assert_eq!(
        expand_use_tree("crate::{judge::{evaluator::Evaluator, diagnostics as d}, registry, self}"),
        ["crate::judge::evaluator::Evaluator", "crate::judge::diagnostics", "crate::registry", "crate"]
    );
    let unit = Unit {
        name: "t".into(),
        modules: BTreeMap::from([
            (String::new(), PathBuf::from("lib.rs")),
            ("judge".to_string(), PathBuf::from("judge/mod.rs")),
            ("judge::evaluator".to_string(), PathBuf::from("judge/evaluator.rs")),
            ("judge::diagnostics".to_string(), PathBuf::from("judge/diagnostics.rs")),
        ]),
    };
    assert_eq!(resolve(&unit, "judge::evaluator", &[], "super::diagnostics::Stage").as_deref(), Some("judge::diagnostics"));
    assert_eq!(resolve(&unit, "judge::evaluator", &["tests".into()], "super::Evaluator").as_deref(), Some("judge::evaluator"));
    assert_eq!(resolve(&unit, "judge", &[], "crate::judge::evaluator::X").as_deref(), Some("judge::evaluator"));
    assert_eq!(resolve(&unit, "judge", &[], "std::fmt"), None);
}
