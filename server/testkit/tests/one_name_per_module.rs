//! One name per module (docs/ARCHITECTURE.md, "Rules"): a module of the workspace is reached by one path only, the
//! crate that defines it and its place there (`libero_records::records`, never also `libero_episode::records`). A
//! second name hides where the code lives: a reader follows the alias to a file that is not there, a grep for the
//! module's users misses half of them, and moving the module means keeping the alias forever.
//!
//! Two checks. (1) No source file under `server/*/src` re-exports a module or a whole crate of the workspace:
//! no `pub use <crate>::<module>;` (in any `use` tree, `pub(crate)` included), no `pub use <module>::*;` of another
//! module or crate, and no `use <module> as <name>;` at all (a renamed module is a second name even when private).
//! Items (types, functions, constants) may be re-exported: they keep their module's path. (2) No source or document
//! still writes a path retired by this rule ([`RETIRED`]): the compiler catches them in code once the alias is gone,
//! but not in docs, comments or scripts.
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

mod source_tree;
use source_tree::{module_path, repo_root, repository_files, rust_files};

/// Module paths that were aliases and are gone, each with the one path to write instead.
const RETIRED: &[(&str, &str)] = &[
    ("libero_episode::agent_events", "libero_records::agent_events"),
    ("libero_episode::batch_doc", "libero_records::batch_doc"),
    ("libero_episode::demo_manifest", "libero_records::demo_manifest"),
    ("libero_episode::json", "libero_records::json"),
    ("libero_episode::records", "libero_records::records"),
    ("libero_server::store", "libero_store"),
    ("libero_server::memory", "libero_episode::memory"),
    ("libero_dashboard::dashboard", "libero_dashboard::routes"),
];

/// `source` with comments, string literals and char literals blanked (lifetimes kept), so that only code remains.
fn code_only(source: &str) -> String {
    let chars: Vec<char> = source.chars().collect();
    let mut out = String::with_capacity(source.len());
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        let next = chars.get(i + 1).copied();
        if c == '/' && next == Some('/') {
            while i < chars.len() && chars[i] != '\n' {
                i += 1;
            }
        } else if c == '/' && next == Some('*') {
            let mut depth = 0;
            while i < chars.len() {
                if chars[i] == '/' && chars.get(i + 1) == Some(&'*') {
                    depth += 1;
                    i += 2;
                } else if chars[i] == '*' && chars.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    i += 1;
                }
            }
            out.push(' ');
        } else if c == 'r' && matches!(next, Some('"') | Some('#')) && (i == 0 || !is_ident(chars[i - 1])) {
            // A raw string `r"…"`, `r#"…"#`.
            let hashes = chars[i + 1..].iter().take_while(|c| **c == '#').count();
            if chars.get(i + 1 + hashes) != Some(&'"') {
                out.push(c);
                i += 1;
                continue;
            }
            i += 2 + hashes;
            while i < chars.len() && !(chars[i] == '"' && chars[i + 1..].iter().take(hashes).filter(|c| **c == '#').count() == hashes) {
                i += 1;
            }
            i += 1 + hashes;
            out.push_str("\"\"");
        } else if c == '"' {
            i += 1;
            while i < chars.len() && chars[i] != '"' {
                i += if chars[i] == '\\' { 2 } else { 1 };
            }
            i += 1;
            out.push_str("\"\"");
        } else if c == '\'' {
            // A char literal (`'x'`, `'\n'`, `'\u{1F600}'`) or a lifetime (`'a`).
            let close = if next == Some('\\') {
                chars[i + 2..].iter().position(|c| *c == '\'').map(|p| i + 2 + p)
            } else {
                (chars.get(i + 2) == Some(&'\'')).then_some(i + 2)
            };
            match close {
                Some(end) => {
                    out.push_str("' '");
                    i = end + 1;
                }
                None => {
                    out.push(c);
                    i += 1;
                }
            }
        } else {
            out.push(c);
            i += 1;
        }
    }
    out
}

fn is_ident(c: char) -> bool {
    c.is_alphanumeric() || c == '_'
}

/// One leaf of a `use` tree: its full path, its new name (`as x`) and whether it is a glob.
#[derive(Debug, PartialEq)]
struct Leaf {
    path: Vec<String>,
    rename: Option<String>,
    glob: bool,
}

/// Every `use` item of a code text (comments and literals already blanked): whether it is public (any `pub`) and
/// its leaves.
fn use_items(code: &str) -> Vec<(bool, Vec<Leaf>)> {
    let mut out = Vec::new();
    let bytes = code.as_bytes();
    let mut from = 0;
    while let Some(at) = code[from..].find("use").map(|a| a + from) {
        from = at + 3;
        let before_ok = at == 0 || !is_ident(code[..at].chars().next_back().unwrap());
        let after_ok = bytes.get(at + 3).is_some_and(|b| b.is_ascii_whitespace());
        if !before_ok || !after_ok {
            continue;
        }
        let Some(end) = code[at..].find(';').map(|e| e + at) else { break };
        // The visibility is what stands between the previous item's end and `use`.
        let start = code[..at].rfind([';', '{', '}', ']']).map_or(0, |s| s + 1);
        let public = code[start..at].split(|c: char| !is_ident(c)).any(|w| w == "pub");
        let tokens = tokens(&code[at + 3..end]);
        let mut leaves = Vec::new();
        let mut pos = 0;
        tree(&tokens, &mut pos, &[], &mut leaves);
        out.push((public, leaves));
        from = end;
    }
    out
}

fn tokens(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let chars: Vec<char> = text.chars().collect();
    let mut i = 0;
    while i < chars.len() {
        let c = chars[i];
        if c.is_whitespace() {
            i += 1;
        } else if is_ident(c) {
            let word: String = chars[i..].iter().take_while(|c| is_ident(**c)).collect();
            i += word.chars().count();
            out.push(word);
        } else if c == ':' && chars.get(i + 1) == Some(&':') {
            out.push("::".into());
            i += 2;
        } else {
            out.push(c.to_string());
            i += 1;
        }
    }
    out
}

/// Parses one use tree at `tokens[*pos]` under `prefix`, pushing its leaves.
fn tree(tokens: &[String], pos: &mut usize, prefix: &[String], leaves: &mut Vec<Leaf>) {
    let mut path = prefix.to_vec();
    loop {
        match tokens.get(*pos).map(String::as_str) {
            Some("::") => *pos += 1,
            Some("{") => {
                *pos += 1;
                while tokens.get(*pos).is_some_and(|t| t != "}") {
                    tree(tokens, pos, &path, leaves);
                    if tokens.get(*pos).is_some_and(|t| t == ",") {
                        *pos += 1;
                    }
                }
                *pos += 1;
                return;
            }
            Some("*") => {
                *pos += 1;
                leaves.push(Leaf { path, rename: None, glob: true });
                return;
            }
            Some(word) if is_ident(word.chars().next().unwrap()) => {
                path.push(word.to_string());
                *pos += 1;
                if tokens.get(*pos).is_some_and(|t| t == "::") {
                    continue;
                }
                let rename = (tokens.get(*pos).is_some_and(|t| t == "as")).then(|| {
                    *pos += 2;
                    tokens[*pos - 1].clone()
                });
                // `a::{self, B}`: `self` is `a`.
                if path.last().is_some_and(|w| w == "self") && path.len() > 1 {
                    path.pop();
                }
                leaves.push(Leaf { path, rename, glob: false });
                return;
            }
            _ => return,
        }
    }
}

/// The workspace's crates: library name (`libero_records`) → the module paths it declares (`records`, `demo::mod`…;
/// the root is the empty path).
struct Workspace {
    crates: BTreeMap<String, BTreeSet<String>>,
}

impl Workspace {
    fn read(server: &Path) -> (Self, Vec<(String, PathBuf, String)>) {
        let mut crates = BTreeMap::new();
        let mut sources = Vec::new();
        let mut dirs: Vec<PathBuf> =
            std::fs::read_dir(server).unwrap().map(|e| e.unwrap().path()).filter(|d| d.join("Cargo.toml").is_file()).collect();
        dirs.sort();
        for dir in dirs {
            let manifest = std::fs::read_to_string(dir.join("Cargo.toml")).unwrap();
            let package = manifest
                .lines()
                .skip_while(|l| l.trim() != "[package]")
                .find(|l| l.trim_start().starts_with("name"))
                .and_then(|l| l.split('"').nth(1))
                .unwrap_or_else(|| panic!("{}: no package name", dir.display()))
                .replace('-', "_");
            let src = dir.join("src");
            let mut files = Vec::new();
            rust_files(&src, &mut files);
            files.sort();
            let mut modules = BTreeSet::from([String::new()]);
            for file in files.iter().filter(|f| !f.starts_with(src.join("bin"))) {
                let here = module_path(&src, file);
                let code = code_only(&std::fs::read_to_string(file).unwrap());
                for name in declared_modules(&code) {
                    modules.insert(if here.is_empty() { name } else { format!("{here}::{name}") });
                }
                sources.push((package.clone(), file.clone(), here));
            }
            crates.insert(package, modules);
        }
        (Workspace { crates }, sources)
    }

    /// The crate and module a `use` path names, if it names a workspace crate's root or one of its modules (an
    /// item, an external crate or a path this reading cannot follow gives `None`).
    fn module_of(&self, krate: &str, here: &str, path: &[String]) -> Option<String> {
        let here: Vec<&str> = here.split("::").filter(|s| !s.is_empty()).collect();
        let (target, mut base, rest): (&str, Vec<&str>, &[String]) = match path.first()?.as_str() {
            "crate" => (krate, vec![], &path[1..]),
            "self" => (krate, here.clone(), &path[1..]),
            "super" => {
                let supers = path.iter().take_while(|s| *s == "super").count();
                (krate, here[..here.len().checked_sub(supers)?].to_vec(), &path[supers..])
            }
            first if self.crates.contains_key(first) => (first, vec![], &path[1..]),
            // A path relative to the current module: `use routes as dashboard;`.
            first => {
                let child = here.iter().copied().chain([first]).collect::<Vec<_>>().join("::");
                if !self.crates.get(krate).is_some_and(|m| m.contains(&child)) {
                    return None;
                }
                (krate, here.clone(), path)
            }
        };
        base.extend(rest.iter().map(String::as_str));
        let module = base.join("::");
        self.crates[target].contains(&module).then(|| if module.is_empty() { target.to_string() } else { format!("{target}::{module}") })
    }
}

/// The names of the modules a file declares (`mod a;`, `pub mod b { … }`), at its top level or not.
fn declared_modules(code: &str) -> Vec<String> {
    let words = tokens(code);
    words
        .windows(3)
        .filter(|w| w[0] == "mod" && is_ident(w[1].chars().next().unwrap()) && (w[2] == ";" || w[2] == "{"))
        .map(|w| w[1].clone())
        .collect()
}

/// What is wrong with the `use` items of one file of crate `krate`, module `here`.
fn aliases_in(workspace: &Workspace, krate: &str, here: &str, code: &str) -> Vec<String> {
    let mut out = Vec::new();
    for (public, leaves) in use_items(code) {
        for leaf in leaves {
            let Some(module) = workspace.module_of(krate, here, &leaf.path) else { continue };
            let shown = leaf.path.join("::");
            let named_here = if here.is_empty() { krate.to_string() } else { format!("{krate}::{here}") };
            if leaf.glob && public {
                out.push(format!("`pub use {shown}::*` makes {named_here} a second name of every item of {module}"));
            } else if let Some(new) = leaf.rename.as_ref().filter(|n| *n != "_") {
                out.push(format!("`use {shown} as {new}` gives the module {module} a second name"));
            } else if public && !leaf.glob {
                out.push(format!("`pub use {shown}` gives the module {module} a second name, {named_here}::{}", leaf.path.last().unwrap()));
            }
        }
    }
    out
}

#[test]
fn no_crate_reexports_a_module_under_a_second_name() {
    let server = repo_root().join("server");
    let (workspace, sources) = Workspace::read(&server);
    assert!(workspace.crates.len() >= 10 && sources.len() >= 100, "found {} crates, {} files: is the walk broken?", workspace.crates.len(), sources.len());
    let mut found = Vec::new();
    for (krate, file, here) in &sources {
        let code = code_only(&std::fs::read_to_string(file).unwrap());
        for why in aliases_in(&workspace, krate, here, &code) {
            found.push(format!("{}: {why}", file.strip_prefix(&server).unwrap().display()));
        }
    }
    assert!(
        found.is_empty(),
        "modules re-exported under a second name (write the module's own path at every use instead, and delete the re-export):\n{}",
        found.join("\n")
    );
}

#[test]
fn no_source_or_document_writes_a_retired_module_path() {
    let root = repo_root();
    let text_kinds = ["rs", "md", "toml", "py", "cjs", "js", "sh", "html", "txt"];
    let mut files: Vec<PathBuf> = repository_files(&root)
        .into_iter()
        .filter(|f| f.extension().is_some_and(|e| text_kinds.iter().any(|k| e == *k)) || f.ends_with("Makefile"))
        .collect();
    files.sort();
    let this_file = Path::new(file!()).file_name().unwrap();
    let mut found = Vec::new();
    for file in files.iter().filter(|f| f.file_name() != Some(this_file)) {
        let Ok(text) = std::fs::read_to_string(file) else { continue };
        for (n, line) in text.lines().enumerate() {
            for (old, new) in RETIRED {
                let hit = line.match_indices(old).any(|(at, _)| {
                    let before = line[..at].chars().next_back();
                    let after = line[at + old.len()..].chars().next();
                    !before.is_some_and(is_ident) && !after.is_some_and(is_ident)
                });
                if hit {
                    found.push(format!("{}:{}: `{old}` is `{new}`", file.strip_prefix(&root).unwrap().display(), n + 1));
                }
            }
        }
    }
    assert!(files.len() >= 300, "found only {} files: is the walk broken?", files.len());
    assert!(found.is_empty(), "retired module paths still written:\n{}", found.join("\n"));
}

/// The check reads the aliases it exists to refuse (and lets items and external renames through).
#[test]
fn the_check_catches_module_aliases_and_lets_items_through() {
    let workspace = Workspace {
        crates: BTreeMap::from([
            ("libero_records".into(), BTreeSet::from(["".into(), "records".into(), "json".into()])),
            ("libero_episode".into(), BTreeSet::from(["".into(), "memory".into(), "demo".into(), "demo::record".into()])),
            ("libero_dashboard".into(), BTreeSet::from(["".into(), "routes".into()])),
        ]),
    };
    let check = |krate: &str, here: &str, source: &str| aliases_in(&workspace, krate, here, &code_only(source)).len();
    // The aliases this rule removed, in their old shapes.
    assert_eq!(check("libero_episode", "", "/// doc\npub use libero_records::{json, records};"), 2);
    assert_eq!(check("libero_episode", "", "#[cfg(x)]\npub use libero_records::records;"), 1);
    assert_eq!(check("libero_dashboard", "", "pub use routes as dashboard;"), 1);
    assert_eq!(check("libero_dashboard", "x", "pub(crate) use crate::routes;"), 1);
    assert_eq!(check("libero_server", "store", "//! The store.\npub use libero_records::*;"), 1);
    assert_eq!(check("libero_server", "", "use libero_episode::memory as mem;"), 1);
    assert_eq!(check("libero_server", "", "pub use libero_episode as episode;"), 1);
    assert_eq!(check("libero_episode", "demo", "pub use super::memory;\npub use self::record::{self};"), 2);
    // Items keep their module's path; private imports of modules are uses, not names; external crates are not ours.
    assert_eq!(check("libero_episode", "", "pub use libero_records::records::{Outcome, RunDir as Dir};"), 0);
    assert_eq!(check("libero_episode", "", "use libero_records::records;\nuse std::io::Write as _;\npub use serde_json::json;"), 0);
    assert_eq!(check("libero_episode", "", "// pub use libero_records::records;\nconst S: &str = \"pub use libero_records::json;\";"), 0);
    assert_eq!(check("libero_episode", "", "fn f<'a>(c: char) -> bool { c == '{' }\nfn reuse() {}\npub use memory::return_freed_memory;"), 0);
}
