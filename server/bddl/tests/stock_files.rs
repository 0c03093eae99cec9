//! Every BDDL file shipped with hf-libero 0.1.4 parses, and the parse agrees with what the real LIBERO env
//! reported for the 130 benchmark tasks (`tests/reference/ref/task_survey.json`: problem class, object and
//! fixture dict order, goal atoms).
use std::path::{Path, PathBuf};

use libero_bddl::Problem;

fn cache_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("LIBERO_AGENT_CACHE") {
        return PathBuf::from(d);
    }
    PathBuf::from(std::env::var_os("HOME").expect("HOME")).join(".cache/libero-agent")
}

/// The repository's `tests/reference/`: data recorded from the real Python stack (provenance in its README.md).
fn reference_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/reference")
}

fn bddl_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let p = e.unwrap().path();
        if p.is_dir() {
            bddl_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "bddl") {
            out.push(p);
        }
    }
}

#[test]
fn all_stock_bddl_files_parse() {
    let root = cache_dir().join("hf-libero-0.1.4/bddl_files");
    let mut files = Vec::new();
    bddl_files(&root, &mut files);
    assert!(files.len() >= 130, "expected the 130 stock files under {}, found {}", root.display(), files.len());
    for f in &files {
        let p = Problem::from_file(f).unwrap_or_else(|e| panic!("{e}"));
        assert!(p.problem_name.starts_with("libero_"), "{}", f.display());
        assert!(p.goal_atoms().is_some_and(|g| !g.is_empty()), "{}: goal is not a non-empty conjunction", f.display());
        assert!(p.ignored_sections.is_empty(), "{}: {:?}", f.display(), p.ignored_sections);
        for a in &p.init {
            assert!(!a.args.is_empty(), "{}: {:?}", f.display(), a);
        }
    }
}

#[test]
fn parse_matches_the_real_libero_survey_of_130_tasks() {
    let survey_path = reference_dir().join("ref/task_survey.json");
    let text = std::fs::read_to_string(&survey_path).unwrap_or_else(|e| panic!("{}: {e}", survey_path.display()));
    let rows: serde_json::Value = serde_json::from_str(&text).unwrap();
    let rows = rows.as_array().unwrap();
    assert_eq!(rows.len(), 130);
    let root = cache_dir().join("hf-libero-0.1.4/bddl_files");
    for row in rows {
        let suite = row["suite"].as_str().unwrap();
        let task = row["task"].as_str().unwrap();
        let p = Problem::from_file(root.join(suite).join(format!("{task}.bddl"))).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(p.problem_name, row["problem"].as_str().unwrap(), "{task}");
        let names = |v: &serde_json::Value| -> Vec<String> {
            v.as_array().unwrap().iter().map(|x| x.as_str().unwrap().to_string()).collect()
        };
        let objs: Vec<String> = p.objects.iter().map(|i| i.name.clone()).collect();
        assert_eq!(objs, names(&row["objects"]), "{task}: objects order");
        // LIBERO skips the workspace fixture (table, kitchen_table, ...) when building fixtures_dict
        let fixtures: Vec<String> = p
            .fixtures
            .iter()
            .filter(|i| !matches!(i.category.as_str(), "table" | "kitchen_table" | "living_room_table" | "study_table" | "floor" | "coffee_table"))
            .map(|i| i.name.clone())
            .collect();
        assert_eq!(fixtures, names(&row["fixtures"]), "{task}: fixtures order");
        let goal: Vec<Vec<String>> = p
            .goal_atoms()
            .unwrap()
            .iter()
            .map(|a| std::iter::once(a.predicate.clone()).chain(a.args.iter().cloned()).collect())
            .collect();
        let want: Vec<Vec<String>> = row["goal"].as_array().unwrap().iter().map(names).collect();
        assert_eq!(goal, want, "{task}: goal");
        assert_eq!(p.language, row["language"].as_str().unwrap(), "{task}: language");
    }
}
