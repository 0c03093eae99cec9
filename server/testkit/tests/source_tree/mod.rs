//! What the drift tests of this folder (`no_import_cycles`, `one_name_per_module`, `repository_layout`,
//! `doc_paths`) read the repository with: its root, its files, the Rust files of a crate and their module paths.
#![allow(dead_code)] // each test binary uses a part

use std::path::{Path, PathBuf};
use std::process::Command;

#[allow(unused_imports)] // each test binary uses a part
pub use libero_testkit::{repo_root, server_dir};

/// Every `.rs` file below `dir`.
pub fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("read {}: {e}", dir.display())) {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The module path of `file` relative to `root_dir` (the directory of the unit's root file): `a.rs` and `a/mod.rs`
/// are `a`, `a/b.rs` is `a::b`, `lib.rs` and `main.rs` the root (empty).
pub fn module_path(root_dir: &Path, file: &Path) -> String {
    let rel = file.strip_prefix(root_dir).unwrap();
    let mut parts: Vec<String> = rel.iter().map(|p| p.to_string_lossy().to_string()).collect();
    let last = parts.pop().unwrap();
    let stem = last.trim_end_matches(".rs");
    if !matches!(stem, "mod" | "lib" | "main") {
        parts.push(stem.to_string());
    }
    parts.join("::")
}

/// The repository's files: tracked ones plus new ones git does not ignore (a violation fails before it is committed).
/// Without git (an exported tree), every file below the root except `.git/` and the folders `.gitignore` names.
pub fn repository_files(root: &Path) -> Vec<PathBuf> {
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
