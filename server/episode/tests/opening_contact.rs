//! Figure 3's sustained-contact ratio is recorded for every opening operation, not only for stages that name a
//! contact body: the scripted expert opens the microwave of T16 (a single-goal BDDL task, watched by the generic
//! goal-opening monitor) and of T21 (an unordered cooking goal), played through the episode's own evaluation path
//! (`WorldPhysics`, as `libero-agent expert --trace` runs it), and each record carries the operation: its
//! direction, the door's moving body, its control steps from the first gripper contact, its contact runs and SCR,
//! and the stage diagnostic it belongs to.
use libero_episode::Level;
use libero_episode::expert_run::run_replica_only;
use libero_episode::physics::WorldSpec;
use libero_episode::task::resolve_task;
use libero_sim::AssetPaths;
use serde_json::Value;

/// The expert's `solve` on `task`'s release start, judged as an episode is.
fn solve(task: &str) -> Value {
    let paths = AssetPaths::discover().expect("assets: run scripts/setup.py");
    let spec = WorldSpec { task: resolve_task(task, &paths).unwrap(), level: Level::L1, seed: 100, init_index: 0, paths };
    let record = run_replica_only(&spec, task, "solve", 6_000, |_, _| {}).unwrap();
    assert_eq!(record["success"], true, "{task}: {record}");
    record
}

/// The one opening operation of `record` on stage `stage`, checked to be a completed microwave opening held for a
/// while by the expert.
fn microwave_opening<'a>(task: &str, record: &'a Value, stage: &str) -> &'a Value {
    let ops = record["details"]["opening_operations"].as_array().unwrap_or_else(|| panic!("{task}: no operations: {record}"));
    let op = ops.iter().find(|o| o["stage_name"] == stage).unwrap_or_else(|| panic!("{task}: no operation on {stage}: {ops:?}"));
    eprintln!("{task}: {op}");
    assert_eq!((op["operation"].as_str(), op["window"].as_str(), op["completed"].as_bool()), (Some("open"), Some("first_contact"), Some(true)), "{task}");
    let bodies: Vec<&str> = op["mechanism_bodies"].as_array().unwrap().iter().filter_map(Value::as_str).collect();
    assert!(!bodies.is_empty() && bodies.iter().all(|b| b.starts_with("microwave_1")), "{task}: the door's body: {bodies:?}");
    let runs: Vec<u64> = op["contact_runs"].as_array().unwrap().iter().filter_map(Value::as_u64).collect();
    let exec = op["exec_steps"].as_u64().unwrap();
    let sustained: u64 = runs.iter().filter(|&&r| r >= 5).sum();
    assert!(exec > 0 && runs.iter().sum::<u64>() <= exec, "{task}: {op}");
    assert_eq!(op["sustained_steps"].as_u64(), Some(sustained), "{task}");
    let scr = op["sustained_contact_ratio_percent"].as_f64().unwrap();
    assert!((scr - 100.0 * sustained as f64 / exec as f64).abs() < 1e-9, "{task}: SCR = N_sustained / N_exec");
    assert!(scr > 0.0, "{task}: the expert holds the door for at least 5 steps: {op}");
    op
}

#[test]
fn the_experts_microwave_openings_record_their_sustained_contact_ratio() {
    // T16: `bddl_terminal`, one stage; the goal's `(open microwave_1)` is the operation of that stage.
    let t16 = solve("T16");
    let op = microwave_opening("T16", &t16, "01_BDDL_Goal_At_Finish");
    assert_eq!(op["goal"], "(open microwave_1)");
    let d = &t16["stage_diagnostics"][0];
    assert_eq!((d["operation"].as_str(), d["sustained_contact_ratio_percent"].as_f64()), (Some("open"), op["sustained_contact_ratio_percent"].as_f64()));

    // T21: the unordered cooking goals; the microwave goal is one of five, all available from the start.
    let t21 = solve("T21");
    let op = microwave_opening("T21", &t21, "Microwave_Open");
    let ops = t21["details"]["opening_operations"].as_array().unwrap();
    assert_eq!(ops.len(), 1, "only the microwave opens a mechanism; the stoves turn on: {ops:?}");
    let d = t21["stage_diagnostics"].as_array().unwrap().iter().find(|d| d["stage_name"] == "Microwave_Open").unwrap();
    assert_eq!((d["type"].as_str(), d["operation"].as_str()), (Some("mechanism_interaction"), Some("open")));
    assert_eq!(d["contact_exec_steps"], op["exec_steps"]);
    let pot = t21["stage_diagnostics"].as_array().unwrap().iter().find(|d| d["stage_name"] == "Moka_Pot_On_Second_Stove").unwrap();
    assert_eq!((pot["type"].as_str(), pot.get("operation")), (Some("object_manipulation"), None));
}
