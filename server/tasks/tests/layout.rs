//! The crate's layout rules (tasks/README.md, "Where the code is"): the shared machinery (`judge/`, `expert/`) imports
//! no family and not the registry, and a family imports no other family, so that adding a family touches its folder,
//! the registry and the manifest only.
use std::path::{Path, PathBuf};

fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("read {}: {e}", dir.display())) {
        let path = entry.unwrap().path();
        if path.is_dir() {
            out.extend(rust_files(&path));
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
    out
}

fn src() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

/// Every `crate::…` path a file names, with its line number (comments included: a doc link is a dependency too).
fn crate_paths(file: &Path) -> Vec<(usize, String)> {
    let text = std::fs::read_to_string(file).unwrap();
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        for (i, _) in line.match_indices("crate::") {
            let path: String =
                line[i..].chars().take_while(|c| c.is_alphanumeric() || *c == '_' || *c == ':').collect();
            out.push((n + 1, path));
        }
    }
    out
}

#[test]
fn the_shared_machinery_imports_no_family_and_not_the_registry() {
    let mut violations = Vec::new();
    for dir in ["judge", "expert"] {
        for file in rust_files(&src().join(dir)) {
            for (line, path) in crate_paths(&file) {
                if ["crate::families", "crate::registry", "crate::catalog"].iter().any(|p| path.starts_with(p)) {
                    violations.push(format!("{}:{line}: {path}", file.display()));
                }
            }
        }
    }
    assert!(violations.is_empty(), "judge/ and expert/ must stay leaves:\n{}", violations.join("\n"));
}

#[test]
fn a_family_imports_no_other_family_and_not_the_registry() {
    let families = src().join("families");
    let mut violations = Vec::new();
    let mut seen = 0;
    for entry in std::fs::read_dir(&families).unwrap() {
        let dir = entry.unwrap().path();
        if !dir.is_dir() {
            continue;
        }
        seen += 1;
        let own = format!("crate::families::{}", dir.file_name().unwrap().to_string_lossy());
        for file in rust_files(&dir) {
            for (line, path) in crate_paths(&file) {
                let foreign_family = path.starts_with("crate::families") && !path.starts_with(&own);
                if foreign_family || path.starts_with("crate::registry") {
                    violations.push(format!("{}:{line}: {path}", file.display()));
                }
            }
        }
    }
    assert!(seen >= 5, "expected the family folders under {}", families.display());
    assert!(violations.is_empty(), "a family may use judge/ and expert/ only:\n{}", violations.join("\n"));
}
