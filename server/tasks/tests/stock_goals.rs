//! Every goal of the 130 stock LIBERO tasks binds to its composed scene: names resolve to MuJoCo bodies, sites
//! and joints, and each articulation test has a threshold. Scenes are composed and compiled once each, on all cores.
//!
//! An ordinary run binds the day's third of them (a seeded shuffle of the 130, the seed printed; every task is
//! bound once every three days on average): the whole sweep is 90 s of both cores of a CI machine.
//! `LIBERO_AGENT_STOCK_GOALS=all` binds all 130, `LIBERO_AGENT_STOCK_GOALS_SEED=N` repeats day N's sample.
use std::path::Path;
use std::sync::{Arc, Mutex};

use libero_sim::AssetPaths;
use libero_sim::compose::compose_file;
use libero_sim::simulation::SimData;
use libero_tasks::GoalChecker;
use libero_testkit::sample::{day_seed, seeded_pick};

const SUITES: [&str; 5] = ["libero_10", "libero_90", "libero_goal", "libero_object", "libero_spatial"];
/// Goals an ordinary run binds.
const DAILY_SAMPLE: usize = 44;

/// Binds the goal of one stock BDDL file and evaluates it once on the model's default state.
fn bind(file: &Path, paths: &AssetPaths) -> Result<Vec<String>, String> {
    let scene = compose_file(file, paths).map_err(|e| e.to_string())?;
    let model = Arc::new(scene.compile().map_err(|e| e.to_string())?);
    let checker = GoalChecker::for_scene(&scene, &model).map_err(|e| e.to_string())?;
    let report = checker.evaluate(&SimData::new(model.clone()));
    if checker.atoms().is_empty() || report.predicates.len() != checker.atoms().len() {
        return Err(format!("{} atoms bound, {} values", checker.atoms().len(), report.predicates.len()));
    }
    Ok(checker.atoms().iter().map(|a| format!("{:?}", a.kind)).collect())
}

#[test]
fn the_days_sample_of_the_130_stock_goals_compiles_against_their_composed_scenes() {
    let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
    let mut files = Vec::new();
    for suite in SUITES {
        let dir = paths.stock_bddl(suite, "x").parent().expect("suite dir").to_path_buf();
        files.extend(
            std::fs::read_dir(&dir)
                .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|x| x == "bddl")),
        );
    }
    files.sort();
    assert_eq!(files.len(), 130, "expected the 130 stock LIBERO tasks");
    if std::env::var("LIBERO_AGENT_STOCK_GOALS").as_deref() != Ok("all") {
        let seed = day_seed("LIBERO_AGENT_STOCK_GOALS_SEED");
        files = seeded_pick(files, DAILY_SAMPLE, seed);
        files.sort();
        eprintln!("binding {DAILY_SAMPLE} of the 130 goals (LIBERO_AGENT_STOCK_GOALS_SEED={seed}); LIBERO_AGENT_STOCK_GOALS=all for every one");
    }
    let expected = files.len();
    let queue = Mutex::new(files.iter());
    let results = Mutex::new(Vec::new());
    let workers = std::thread::available_parallelism().map_or(2, |n| n.get());
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| {
                while let Some(file) = { queue.lock().unwrap().next() } {
                    let r = bind(file, &paths);
                    results.lock().unwrap().push((file.clone(), r));
                }
            });
        }
    });
    let results = results.into_inner().unwrap();
    let mut kinds = std::collections::BTreeMap::<String, usize>::new();
    let mut failures = Vec::new();
    for (file, r) in &results {
        match r {
            Ok(k) => k.iter().for_each(|k| *kinds.entry(k.clone()).or_default() += 1),
            Err(e) => failures.push(format!("{}: {e}", file.display())),
        }
    }
    println!("predicates bound: {kinds:?}");
    assert_eq!(results.len(), expected);
    assert!(failures.is_empty(), "{} goals failed:\n{}", failures.len(), failures.join("\n"));
}
