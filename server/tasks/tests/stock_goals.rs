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

const SUITES: [&str; 5] = ["libero_10", "libero_90", "libero_goal", "libero_object", "libero_spatial"];
/// Goals an ordinary run binds.
const DAILY_SAMPLE: usize = 44;

/// The day's sample seed (days since 1970, UTC), or `LIBERO_AGENT_STOCK_GOALS_SEED`.
fn sample_seed() -> u64 {
    std::env::var("LIBERO_AGENT_STOCK_GOALS_SEED").ok().and_then(|s| s.parse().ok()).unwrap_or_else(|| {
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs() / 86_400)
    })
}

/// `n` of `files` by a seeded shuffle (a 64-bit LCG): the same seed picks the same files on every machine.
fn pick(mut files: Vec<std::path::PathBuf>, n: usize, seed: u64) -> Vec<std::path::PathBuf> {
    let mut state = seed;
    for i in (1..files.len()).rev() {
        state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        files.swap(i, (state >> 33) as usize % (i + 1));
    }
    files.truncate(n);
    files.sort();
    files
}

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
        let seed = sample_seed();
        files = pick(files, DAILY_SAMPLE, seed);
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
