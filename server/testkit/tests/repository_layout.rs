//! The repository stands alone: a clone builds and tests with nothing beside it, so no file of it names a path
//! outside the clone — in particular not the sibling `shared` folder the project was started from. The data the
//! tests compare against lives in `tests/reference/` (provenance in its README.md), the protocol the code comments
//! cite by section in `docs/protocol.md`.
mod source_tree;
use source_tree::{repo_root, repository_files};

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
    let this_file = root.join("server/testkit/tests/repository_layout.rs");
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
