//! Every goal of the 130 stock LIBERO tasks binds to its composed scene: names resolve to MuJoCo bodies, sites
//! and joints, and each articulation test has a threshold.
use std::collections::BTreeMap;

use libero_sim::AssetPaths;
use libero_sim::compose::compose_file;
use libero_sim::simulation::SimData;
use libero_tasks::GoalChecker;

const SUITES: [&str; 5] = ["libero_10", "libero_90", "libero_goal", "libero_object", "libero_spatial"];

#[test]
fn all_130_stock_goals_compile_against_their_composed_scenes() {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let mut checked = 0;
    let mut failures = Vec::new();
    let mut predicate_counts: BTreeMap<String, usize> = BTreeMap::new();
    for suite in SUITES {
        let dir = paths.stock_bddl(suite, "x").parent().expect("suite dir").to_path_buf();
        let mut files: Vec<_> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "bddl"))
            .collect();
        files.sort();
        for file in files {
            checked += 1;
            let result = compose_file(&file, &paths).map_err(|e| e.to_string()).and_then(|scene| {
                let model = std::sync::Arc::new(scene.compile().map_err(|e| e.to_string())?);
                let checker = GoalChecker::for_scene(&scene, &model).map_err(|e| e.to_string())?;
                // evaluating on the model's default state must not panic
                let data = SimData::new(model.clone());
                let report = checker.evaluate(&data);
                Ok((checker, report))
            });
            match result {
                Ok((checker, report)) => {
                    assert_eq!(report.predicates.len(), checker.atoms().len());
                    assert!(!checker.atoms().is_empty(), "{}: empty goal", file.display());
                    for a in checker.atoms() {
                        *predicate_counts.entry(format!("{:?}", a.kind)).or_default() += 1;
                    }
                }
                Err(e) => failures.push(format!("{suite}/{}: {e}", file.file_name().unwrap().to_string_lossy())),
            }
        }
    }
    println!("predicates bound: {predicate_counts:?}");
    assert!(failures.is_empty(), "{} of {checked} goals failed:\n{}", failures.len(), failures.join("\n"));
    assert_eq!(checked, 130, "expected the 130 stock LIBERO tasks");
}
