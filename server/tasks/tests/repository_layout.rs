//! The repository stands alone: a clone builds and tests with nothing beside it, so no file of it names a path
//! outside the clone — in particular not the sibling `shared` folder the project was started from. The data the
//! tests compare against lives in `tests/reference/` (provenance in its README.md), the protocol the code comments
//! cite by section in `docs/protocol.md`.
use std::path::{Path, PathBuf};
use std::process::Command;

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..").canonicalize().expect("repository root")
}

/// The repository's files: tracked ones plus new ones git does not ignore (a violation fails before it is committed).
/// Without git (an exported tree), every file below the root except `.git/` and the folders `.gitignore` names.
fn repository_files(root: &Path) -> Vec<PathBuf> {
    let listed = Command::new("git")
        .arg("-C")
        .arg(root)
        .args(["ls-files", "-z", "--cached", "--others", "--exclude-standard"])
        .output()
        .ok()
        .filter(|o| o.status.success());
    match listed {
        Some(out) => out
            .stdout
            .split(|b| *b == 0)
            .filter(|name| !name.is_empty())
            .map(|name| root.join(String::from_utf8_lossy(name).as_ref()))
            .filter(|p| p.is_file()) // tracked but deleted in the working tree
            .collect(),
        None => {
            let ignored: Vec<String> = std::fs::read_to_string(root.join(".gitignore"))
                .unwrap_or_default()
                .lines()
                .map(|l| l.trim().trim_matches('/').to_string())
                .filter(|l| !l.is_empty() && !l.starts_with('#') && !l.contains(['*', '!', '/']))
                .collect();
            let mut out = Vec::new();
            walk(root, &ignored, &mut out);
            out
        }
    }
}

fn walk(dir: &Path, ignored: &[String], out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("read {}: {e}", dir.display())) {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        if path.is_dir() {
            if name != ".git" && !ignored.contains(&name) {
                walk(&path, ignored, out);
            }
        } else {
            out.push(path);
        }
    }
}

/// Text that names a path outside the clone. Built from pieces so that this file does not name them itself.
fn outside_paths() -> Vec<String> {
    let shared = ["sha", "red"].concat();
    vec![format!("../{shared}"), format!("/work/{shared}"), format!("{shared}/reference"), format!("{shared}/DESIGN")]
}

/// Whether `line` names `needle` as a whole folder name: followed by `/`, punctuation or the end of the line, not
/// by more of a name (a sibling `<needle>_store.rs` is not the folder).
fn names(line: &str, needle: &str) -> bool {
    line.match_indices(needle).any(|(i, _)| {
        let next = line[i + needle.len()..].chars().next();
        !next.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == '-')
    })
}

#[test]
fn no_file_names_a_path_outside_the_repository() {
    let root = repo_root();
    let files = repository_files(&root);
    let this_file = root.join("server/tasks/tests/repository_layout.rs");
    assert!(files.len() > 100 && files.contains(&this_file), "listing the repository's files found {} files", files.len());
    let needles = outside_paths();
    let mut violations = Vec::new();
    for file in &files {
        let bytes = std::fs::read(file).unwrap_or_else(|e| panic!("read {}: {e}", file.display()));
        let text = String::from_utf8_lossy(&bytes);
        for (n, line) in text.lines().enumerate() {
            for needle in needles.iter().filter(|needle| names(line, needle)) {
                let shown = file.strip_prefix(&root).unwrap_or(file).display();
                violations.push(format!("{shown}:{}: names `{needle}`", n + 1));
            }
        }
    }
    assert!(
        violations.is_empty(),
        "the repository must stand alone (reference data in tests/reference/, the protocol in docs/protocol.md):\n{}",
        violations.join("\n")
    );
}

#[test]
fn the_reference_data_and_the_protocol_are_in_the_repository() {
    let root = repo_root();
    for path in ["tests/reference/README.md", "tests/reference/golden", "tests/reference/ref/task_survey.json", "docs/protocol.md"] {
        assert!(root.join(path).exists(), "{path} is missing");
    }
}
