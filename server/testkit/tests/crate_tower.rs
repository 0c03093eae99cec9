//! The crate tower (docs/ARCHITECTURE.md, "The layers"): every workspace crate under `server/` depends only on the
//! crates below it in [`TOWER`] that its line allows. Cargo already refuses a cycle; this keeps the layers it cannot
//! see: the records, store, metrics, artifacts, report and sandbox never link the simulator (nor MuJoCo), the report links
//! no runner, and neither the server nor the runner links the console, nor the console the runner. A new dependency between workspace crates is a change of architecture: change this
//! list and docs/ARCHITECTURE.md together.
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use libero_testkit::server_dir;

/// Bottom to top: each crate and the workspace crates its `[dependencies]` may name.
const TOWER: &[(&str, &[&str])] = &[
    ("libero-bddl", &[]),
    ("libero-sim", &["libero-bddl"]),
    ("libero-render", &[]),
    ("libero-records", &[]),
    ("libero-metrics", &["libero-records"]),
    ("libero-tasks", &["libero-bddl", "libero-sim", "libero-metrics"]),
    ("libero-episode", &["libero-bddl", "libero-sim", "libero-render", "libero-tasks", "libero-records"]),
    ("libero-store", &["libero-records"]),
    ("libero-artifacts", &[]),
    // The binaries' logger, shared by libero-agent and libero-worker.
    ("libero-logging", &[]),
    // openpi's policy-server client and LIBERO contract: reads published observation files, links no simulator.
    ("libero-policy", &[]),
    // The agent's boundary (bubblewrap, sandbox-net, seccomp, the model-API gateway, caps, log scrubbing, the
    // toolbox): records only, so that what guards the machine builds and is tested without the simulator or a server.
    ("libero-sandbox", &["libero-records"]),
    // The paper's reports and the batch readers: records and metrics only (the catalog's facts come in as data).
    ("libero-report", &["libero-records", "libero-metrics"]),
    (
        "libero-server",
        &["libero-sim", "libero-render", "libero-tasks", "libero-records", "libero-episode", "libero-store", "libero-artifacts"],
    ),
    (
        "libero-runner",
        &["libero-tasks", "libero-metrics", "libero-records", "libero-episode", "libero-store", "libero-artifacts", "libero-report", "libero-server",
            "libero-sandbox", "libero-logging"],
    ),
    (
        "libero-dashboard",
        &[
            "libero-sim", "libero-tasks", "libero-metrics", "libero-records", "libero-episode", "libero-store", "libero-artifacts",
            "libero-report", "libero-server",
        ],
    ),
    (
        "libero-agent",
        &[
            "libero-bddl", "libero-sim", "libero-render", "libero-records", "libero-tasks", "libero-metrics", "libero-episode",
            "libero-store", "libero-report", "libero-server", "libero-sandbox", "libero-runner", "libero-dashboard", "libero-logging",
        ],
    ),
    // The tests' helpers, above everything (no crate's `[dependencies]` may name it; `[dev-dependencies]` do).
    ("libero-testkit", &["libero-store", "libero-server", "libero-dashboard"]),
];

/// The simulator and what drives it: the crates (with MuJoCo itself) the readers of records must never link.
const SIMULATOR: &[&str] = &["libero-sim", "libero-render", "libero-tasks", "libero-episode"];

/// The package name and the workspace crates named in `[dependencies]` (and target-specific dependency tables) of
/// a manifest; dev-dependencies are the tests' business.
fn manifest(path: &Path) -> (String, BTreeSet<String>) {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("read {}: {e}", path.display()));
    let mut name = String::new();
    let mut deps = BTreeSet::new();
    let mut section = String::new();
    for line in text.lines() {
        let line = line.trim();
        if line.starts_with('[') {
            section = line.trim_matches(['[', ']']).to_string();
            continue;
        }
        if section == "package" && line.starts_with("name") {
            name = line.split('"').nth(1).unwrap_or_default().to_string();
        }
        let runtime = section == "dependencies" || (section.starts_with("target.") && section.ends_with(".dependencies"));
        if runtime && (line.starts_with("libero-") || line.starts_with("mujoco")) {
            deps.insert(line.split(|c: char| c == '=' || c == '.' || c.is_whitespace()).next().unwrap().to_string());
        }
    }
    (name, deps)
}

#[test]
fn every_crate_depends_only_on_the_crates_its_layer_allows() {
    let mut dirs: Vec<PathBuf> =
        std::fs::read_dir(server_dir()).unwrap().map(|e| e.unwrap().path()).filter(|d| d.join("Cargo.toml").is_file()).collect();
    dirs.sort();
    let mut found = BTreeSet::new();
    let mut violations = Vec::new();
    for dir in &dirs {
        let (name, deps) = manifest(&dir.join("Cargo.toml"));
        let Some((_, allowed)) = TOWER.iter().find(|(n, _)| *n == name) else {
            violations.push(format!("{name} ({}) is not in the tower: add it to TOWER and docs/ARCHITECTURE.md", dir.display()));
            continue;
        };
        found.insert(name.clone());
        // MuJoCo itself is allowed wherever a simulator crate is.
        let simulator_layer = SIMULATOR.contains(&name.as_str()) || allowed.iter().any(|d| SIMULATOR.contains(d));
        for dep in deps.iter().filter(|d| !allowed.contains(&d.as_str()) && !(d.starts_with("mujoco") && simulator_layer)) {
            violations.push(format!("{name} depends on {dep}, which its layer does not allow"));
        }
    }
    let missing: Vec<&str> = TOWER.iter().map(|(n, _)| *n).filter(|n| !found.contains(*n)).collect();
    assert!(missing.is_empty(), "crates of the tower not found under {}: {missing:?}", server_dir().display());
    assert!(violations.is_empty(), "the crate tower is broken (docs/ARCHITECTURE.md):\n{}", violations.join("\n"));
}

#[test]
fn the_tower_itself_keeps_its_rules() {
    let position = |n: &str| TOWER.iter().position(|(c, _)| *c == n).unwrap_or_else(|| panic!("{n} is not in TOWER"));
    for (i, (name, allowed)) in TOWER.iter().enumerate() {
        for dep in *allowed {
            assert!(position(dep) < i, "{name} may depend on {dep}, which is not below it");
        }
    }
    let allowed = |n: &str| TOWER[position(n)].1;
    // What a crate links, directly or through the crates it may depend on.
    let links = |n: &str| {
        let mut seen = BTreeSet::new();
        let mut todo = vec![n];
        while let Some(c) = todo.pop() {
            for d in allowed(c) {
                if seen.insert(*d) {
                    todo.push(*d);
                }
            }
        }
        seen
    };
    for reader in ["libero-records", "libero-store", "libero-metrics", "libero-artifacts", "libero-bddl", "libero-report", "libero-sandbox"] {
        assert!(!links(reader).iter().any(|d| SIMULATOR.contains(d)), "{reader} must not link the simulator");
    }
    // Reports compute from records alone: no runner, so no sandbox, gateway or harness behind them.
    assert!(!links("libero-report").iter().any(|d| ["libero-runner", "libero-sandbox", "libero-server"].contains(d)), "libero-report must not link the runner");
    // The agent's boundary stands alone: no runner, server, console or report behind it.
    assert!(
        !links("libero-sandbox").iter().any(|d| ["libero-runner", "libero-server", "libero-dashboard", "libero-report"].contains(d)),
        "libero-sandbox must link none of the runner, the server, the console or the report"
    );
    // The console reads batches and prints tables through libero-report, and starts no agent.
    assert!(!links("libero-dashboard").contains(&"libero-runner"), "libero-dashboard must not link the runner");
    for server_side in ["libero-server", "libero-runner"] {
        assert!(!allowed(server_side).contains(&"libero-dashboard"), "{server_side} must not link the console");
    }
}
