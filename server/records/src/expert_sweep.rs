//! The expert sweep's table (`libero-agent expert --all`: `tasks/results/expert_sweep.jsonl`, one row per task,
//! and `expert_sweep.meta.json` beside it), typed for its writer (the sweep command) and its reader (the console's
//! task pages). Here, below both, so that neither reaches up the crate tower for the other's format.
//!
//! The rows are [`record!`](crate::typed) structs: every key not named here survives a read and write as it was,
//! which is how older tables still read (their rows say `wall_time_s` instead of `seconds`, and end with a summary
//! line `{"runs", "solved", "summary", "tasks"}` that has no `task`).
use crate::typed::record;

record! {
    /// One task's line of the sweep (also the lines of the sweep's journal after its header).
    pub struct ExpertSweepRow {
        /// The id the expert ran under: `T14`, `libero_90/<NAME>`, `robomemarena/<name>`. Absent only on the
        /// summary line that older tables end with (not an entry).
        pub task: Option<String>,
        /// `release`, a stock LIBERO suite (`libero_90`) or a pool suite (`robomemarena`).
        pub suite: Option<String>,
        /// The pool address of a pool entry (`libero_90/35`): its console page. Absent for release tasks.
        pub entry: Option<String>,
        /// Runs of the solving expert asked for (`--runs`); 0 when the expert could not plan the goal.
        pub runs: Option<u64>,
        /// Runs whose episode the evaluator judged a success.
        pub successes: Option<u64>,
        /// Whether the task has an expert that could plan its goal (false: see `no_expert`).
        pub expert: Option<bool>,
        /// Why the task's sweep could not run at all (an error or a panic); the row still counts, unsolved.
        pub error: Option<String>,
        /// The goal atom the generic stock expert could not plan (with `expert: false`).
        pub no_expert: Option<String>,
        /// The planned steps of a stock task's generic expert (`place akita_black_bowl_1 on plate_1`).
        pub plan: Option<Vec<String>>,
        /// Actions each run took, in run order (one entry per run that ended).
        pub actions: Option<Vec<u64>>,
        /// The runs that did not succeed, in run order.
        pub failures: Option<Vec<SweepFailure>>,
        /// Wall time of the task's whole sweep (plan and every run), seconds, rounded to 0.1 s.
        pub seconds: Option<f64>,
        /// When the row was written (`2026-11-28T04:09:45Z`): journaled rows and rows an `--update` replaced.
        /// Absent: the table's own date in its metadata.
        pub date_utc: Option<String>,
        /// `git rev-parse --short HEAD` the row was run at (with `date_utc`).
        pub commit: Option<String>,
    }
}

record! {
    /// One run of the solving expert that did not succeed.
    pub struct SweepFailure {
        /// 1-based run number.
        pub run: Option<u64>,
        /// The episode the run played (its run directory under the data folder).
        pub episode_id: Option<String>,
        /// The goal atoms the final state failed, or `"k of n stages"` where the task has no terminal checks.
        pub failed: Option<Vec<String>>,
        /// Why the run ended without a verdict (the episode errored).
        pub error: Option<String>,
    }
}

record! {
    /// `expert_sweep.meta.json`: how and when the table was made.
    pub struct ExpertSweepMeta {
        /// [`META_SCHEMA`].
        pub schema_version: Option<String>,
        /// When the sweep finished (`2026-11-28T04:09:45Z`): the date of every row without its own.
        pub date_utc: Option<String>,
        /// `git rev-parse --short HEAD` of the sweep (`unknown` outside a checkout).
        pub commit: Option<String>,
        /// The command line, as typed.
        pub command: Option<String>,
        /// CPU cores the machine had.
        pub cores: Option<u64>,
        /// Tasks run at a time (`--jobs`, capped by the tasks to run).
        pub jobs: Option<u64>,
        /// Runs per task (`--runs`): an `--update` must use the same, or its rows would not compare.
        pub runs: Option<u64>,
        /// Rows in the table.
        pub tasks: Option<u64>,
        /// `N of M solved k/k` of the whole table.
        pub summary: Option<String>,
        /// Wall time of the sweep, seconds, rounded to 0.1 s.
        pub seconds: Option<f64>,
        /// Each `--update` since, in order.
        pub updates: Option<Vec<SweepUpdate>>,
    }
}

record! {
    /// One `expert --tasks … --update` of a table: it replaced the rows of `tasks` tasks.
    pub struct SweepUpdate {
        pub date_utc: Option<String>,
        pub commit: Option<String>,
        pub command: Option<String>,
        /// Tasks run at a time.
        pub jobs: Option<u64>,
        /// Rows the update replaced or added.
        pub tasks: Option<u64>,
        /// `N of M solved k/k` of the update's own rows.
        pub summary: Option<String>,
        /// Wall time of the update, seconds, rounded to 0.1 s.
        pub seconds: Option<f64>,
    }
}

/// `schema_version` of `expert_sweep.meta.json`.
pub const META_SCHEMA: &str = "libero.expert_sweep_meta.v1";

impl ExpertSweepRow {
    /// Whether the row is a task's (older tables end with a summary line, which is not).
    pub fn is_entry(&self) -> bool {
        self.task.is_some()
    }

    /// Whether the sweep errored on the task: any `error` but null (a string, or a value of another type).
    pub fn has_error(&self) -> bool {
        self.error.is_some() || self.rest.get("error").is_some_and(|e| !e.is_null())
    }

    /// Whether the task has an expert that planned its goal and ran (no error).
    pub fn has_working_expert(&self) -> bool {
        self.expert == Some(true) && !self.has_error()
    }

    /// Whether an expert solved every one of `runs` runs.
    pub fn solved(&self, runs: u64) -> bool {
        self.has_working_expert() && self.successes == Some(runs)
    }

    /// Whether an expert solved all of the row's own runs (at least one).
    pub fn solved_every_run(&self) -> bool {
        let runs = self.runs.unwrap_or(0);
        self.expert == Some(true) && runs > 0 && self.successes == Some(runs)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::json::pretty_sorted;

    const FIXTURES: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/fixtures/expert_sweep");

    fn golden(name: &str) -> String {
        std::fs::read_to_string(format!("{FIXTURES}/{name}")).unwrap_or_else(|e| panic!("{FIXTURES}/{name}: {e}"))
    }

    /// Every line of every golden shape (solved, stock with a plan and a failed goal, a run that errored, no
    /// expert, a sweep error, an older row with `wall_time_s`, an older summary line) reads and writes back
    /// byte for byte, as the sweep writes its lines (compact, keys sorted).
    #[test]
    fn every_golden_sweep_line_reads_and_writes_back_byte_for_byte() {
        let text = golden("expert_sweep.jsonl");
        let rows: Vec<ExpertSweepRow> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        let back: String = rows.iter().map(|r| format!("{r}\n")).collect();
        assert_eq!(back, text);
        assert_eq!(rows.len(), 7);
        assert!(rows[..6].iter().all(ExpertSweepRow::is_entry) && !rows[6].is_entry(), "the summary line is no entry");
    }

    /// The fields the writer sets read back typed, in the golden file's spelling.
    #[test]
    fn golden_rows_read_as_typed_fields() {
        let rows: Vec<ExpertSweepRow> = golden("expert_sweep.jsonl").lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        let solved = &rows[0];
        assert_eq!(
            (solved.task.as_deref(), solved.suite.as_deref(), solved.runs, solved.successes, solved.expert),
            (Some("T01"), Some("release"), Some(3), Some(3), Some(true))
        );
        assert_eq!((solved.seconds, solved.date_utc.as_deref(), solved.commit.as_deref()), (Some(6.4), Some("2026-11-29T05:04:33Z"), Some("bfc58d2")));
        assert_eq!(solved.actions.as_deref(), Some(&[251, 251, 251][..]));
        assert!(solved.solved(3) && !solved.solved(1) && solved.solved_every_run());

        let stock = &rows[1];
        assert_eq!(stock.entry.as_deref(), Some("libero_90/89"));
        assert_eq!(stock.plan.as_deref(), Some(&["place yellow_book_1 in wooden_two_layer_shelf_1_bottom_region".to_owned()][..]));
        let failure = &stock.failures.as_ref().unwrap()[0];
        assert_eq!((failure.run, failure.episode_id.as_deref()), (Some(1), Some("ep-20261128T014458Z-533b9e2b")));
        assert_eq!(failure.failed.as_deref(), Some(&["(in yellow_book_1 wooden_two_layer_shelf_1_bottom_region)".to_owned()][..]));
        assert!(!stock.solved(1));

        let errored_run = &rows[2].failures.as_ref().unwrap()[0];
        assert_eq!((errored_run.error.as_deref(), errored_run.failed.as_ref()), (Some("episode timed out"), None));

        let no_expert = &rows[3];
        assert_eq!((no_expert.expert, no_expert.runs, no_expert.no_expert.as_deref()), (Some(false), Some(0), Some("cannot plan (open microwave_1)")));
        assert!(!no_expert.has_working_expert());

        let error = &rows[4];
        assert!(error.has_error() && !error.has_working_expert() && !error.solved(3));

        let older = &rows[5];
        assert_eq!(older.seconds, None, "older rows say wall_time_s");
        assert_eq!(older.rest.get("wall_time_s").and_then(|v| v.as_f64()), Some(16.6));
        assert!(older.solved(3));

        assert_eq!((rows[6].runs, rows[6].rest.get("summary").and_then(|v| v.as_str())), (Some(3), Some("5 of 5 solved 3/3")));
    }

    /// A row built by the sweep's writer (typed fields only) is exactly the golden line: the wire format of new rows.
    #[test]
    fn a_row_built_from_its_fields_is_the_golden_line() {
        let row = ExpertSweepRow {
            task: Some("libero_90/STUDY_SCENE4_pick_up_the_book_on_the_right_and_place_it_under_the_cabinet_shelf".into()),
            suite: Some("libero_90".into()),
            entry: Some("libero_90/89".into()),
            runs: Some(1),
            successes: Some(0),
            expert: Some(true),
            plan: Some(vec!["place yellow_book_1 in wooden_two_layer_shelf_1_bottom_region".into()]),
            actions: Some(vec![499]),
            failures: Some(vec![SweepFailure {
                run: Some(1),
                episode_id: Some("ep-20261128T014458Z-533b9e2b".into()),
                failed: Some(vec!["(in yellow_book_1 wooden_two_layer_shelf_1_bottom_region)".into()]),
                ..SweepFailure::default()
            }]),
            seconds: Some(4.5),
            ..ExpertSweepRow::default()
        };
        assert_eq!(format!("{row}"), golden("expert_sweep.jsonl").lines().nth(1).unwrap());
        let whole = ExpertSweepRow { seconds: Some(7.0), ..ExpertSweepRow::default() };
        assert_eq!(format!("{whole}"), r#"{"seconds":7.0}"#, "seconds stay a float, as the sweep wrote them");
    }

    /// The metadata (with an update listed) reads typed and writes back as the sweep writes it (`indent=2`, sorted).
    #[test]
    fn the_golden_metadata_reads_and_writes_back_byte_for_byte() {
        let text = golden("expert_sweep.meta.json");
        let meta: ExpertSweepMeta = serde_json::from_str(&text).unwrap();
        assert_eq!(format!("{}\n", pretty_sorted(&meta.to_value())), text);
        assert_eq!((meta.schema_version.as_deref(), meta.runs, meta.tasks, meta.cores), (Some(META_SCHEMA), Some(3), Some(208), Some(2)));
        assert_eq!((meta.date_utc.as_deref(), meta.commit.as_deref()), (Some("2026-11-29T05:24:09Z"), Some("bfc58d2")));
        let update = &meta.updates.as_ref().unwrap()[0];
        assert_eq!((update.tasks, update.seconds, update.summary.as_deref()), (Some(4), Some(18.6), Some("4 of 4 solved 3/3")));
    }

    /// The committed sweep tables (today's and the older per-suite ones) read, and write back unchanged.
    #[test]
    fn the_committed_sweep_tables_read_and_write_back_unchanged() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../../tasks/results");
        let mut checked = 0;
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            let name = path.file_name().unwrap().to_string_lossy().into_owned();
            if !(name.starts_with("expert_") && name.ends_with(".jsonl")) {
                continue;
            }
            for line in std::fs::read_to_string(&path).unwrap().lines().filter(|l| !l.trim().is_empty()) {
                let row: ExpertSweepRow = serde_json::from_str(line).unwrap_or_else(|e| panic!("{name}: {e}: {line}"));
                assert_eq!(format!("{row}"), line, "{name}");
                checked += 1;
            }
        }
        assert!(checked > 200, "only {checked} rows under {dir}");
    }
}
