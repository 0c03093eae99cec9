//! Our predicates agree with LIBERO's own on states recorded from the real stack
//! (`tests/fixtures/predicates/*.json`, written by `scripts/reference_stack/predicate_fixtures.py`): init states,
//! articulated joints at and around their thresholds, objects just inside/outside region boxes, settled drops.
//! Each state is restored into our composed scene (stock BDDL, placement seed 0 as the fixtures use).
use std::path::PathBuf;
use std::sync::Arc;

use libero_bddl::{Atom, Pos};
use libero_sim::compose::compose_file;
use libero_sim::placement::Placement;
use libero_sim::{AssetPaths, Simulation};
use libero_tasks::GoalChecker;
use libero_tasks::judge::predicates::CompiledAtom;
use serde::Deserialize;

#[derive(Deserialize)]
struct Case {
    label: String,
    time: f64,
    qpos: Vec<f64>,
    qvel: Vec<f64>,
    check_success: bool,
    values: Vec<bool>,
}

#[derive(Deserialize)]
struct Fixture {
    suite: String,
    task: String,
    placement_seed: u32,
    goal_atoms: Vec<String>,
    extra_atoms: Vec<String>,
    cases: Vec<Case>,
}

fn fixture_dir() -> PathBuf {
    libero_testkit::tests_dir().join("fixtures/predicates")
}

/// `(pred a b)` → an atom.
fn atom(text: &str) -> Atom {
    let mut words = text.trim_matches(|c| c == '(' || c == ')').split_whitespace().map(str::to_owned);
    let predicate = words.next().unwrap_or_default();
    Atom { predicate, args: words.collect(), pos: Pos::default() }
}

#[test]
fn predicate_values_equal_libero_on_recorded_states() {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let mut files: Vec<PathBuf> = std::fs::read_dir(fixture_dir())
        .expect("fixture directory")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .collect();
    files.sort();
    assert!(files.len() >= 8, "expected at least the 8 golden tasks, found {}", files.len());
    let (mut compared, mut true_values, mut mismatches) = (0usize, 0usize, Vec::new());
    for file in &files {
        let f: Fixture = serde_json::from_slice(&std::fs::read(file).unwrap()).unwrap();
        let scene = compose_file(&paths.stock_bddl(&f.suite, &f.task), &paths).unwrap();
        let mut model = scene.compile().unwrap();
        Placement::sample(&scene, f.placement_seed, Some(&model)).unwrap().apply(&mut model).unwrap();
        let model = Arc::new(model);
        let checker = GoalChecker::for_scene(&scene, &model).unwrap();
        let ours_goal: Vec<&str> = checker.atoms().iter().map(|a| a.text.as_str()).collect();
        assert_eq!(ours_goal, f.goal_atoms, "{}: goal atoms", f.task);
        let extra: Vec<CompiledAtom> = f
            .extra_atoms
            .iter()
            .map(|t| CompiledAtom::compile(checker.index(), &atom(t)).unwrap_or_else(|e| panic!("{}: {e}", f.task)))
            .collect();
        let mut sim = Simulation::new(model.clone()).unwrap();
        for case in &f.cases {
            let row: Vec<f64> = std::iter::once(case.time).chain(case.qpos.iter().copied()).chain(case.qvel.iter().copied()).collect();
            sim.set_init_state(&row).unwrap();
            let report = checker.evaluate(sim.data());
            let ours = report
                .predicates
                .iter()
                .map(|p| p.value)
                .chain(extra.iter().map(|a| a.evaluate(checker.index(), sim.data())));
            let names = f.goal_atoms.iter().chain(&f.extra_atoms);
            for ((ours, theirs), name) in ours.zip(&case.values).zip(names) {
                compared += 1;
                true_values += usize::from(*theirs);
                if ours != *theirs {
                    mismatches.push(format!("{} [{}] {name}: ours {ours}, LIBERO {theirs}", f.task, case.label));
                }
            }
            if report.success != case.check_success {
                mismatches.push(format!("{} [{}] _check_success: ours {}, LIBERO {}", f.task, case.label, report.success, case.check_success));
            }
        }
    }
    println!("{} fixture files, {compared} predicate values compared ({true_values} true in LIBERO)", files.len());
    assert!(mismatches.is_empty(), "{} mismatches:\n{}", mismatches.len(), mismatches.join("\n"));
}
