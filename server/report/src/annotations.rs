//! People's stage annotations (issue 48; the paper annotated its stage analysis by hand): what a person said about
//! one stage of one long-horizon rollout — reached, succeeded, failure modes, a note — with who and when. The
//! dashboard keeps them in the store and appends each one to its batch's `stage_annotations.jsonl`, which travels
//! with the batch; the last line per (episode, stage) is the one counted, earlier lines are the history. Table 4
//! takes an annotated stage's label from it and says how many stages are annotated and how many automatic.
use std::io::Write as _;
use std::path::{Path, PathBuf};

use libero_metrics::{FailureMode, StageAnnotation, StageAnnotations, StageKey, StageOpportunity, TaskFacts};
use serde::{Deserialize, Serialize};

use crate::batch::{LoadedBatch, RolloutRecord};

/// The batch's annotation file.
pub const ANNOTATIONS_FILE: &str = "stage_annotations.jsonl";
/// Longest note and annotator name accepted (characters).
pub const MAX_NOTE_CHARS: usize = 2000;
pub const MAX_ANNOTATOR_CHARS: usize = 64;

/// One line of `stage_annotations.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AnnotationLine {
    pub episode_id: String,
    pub stage_name: String,
    #[serde(flatten)]
    pub annotation: StageAnnotation,
}

pub fn annotations_path(batch_dir: &Path) -> PathBuf {
    batch_dir.join(ANNOTATIONS_FILE)
}

/// The annotations of one batch directory: the last line per (episode, stage); unreadable lines are skipped.
pub fn read_annotations(batch_dir: &Path) -> StageAnnotations {
    let mut out = StageAnnotations::new();
    let Ok(text) = std::fs::read_to_string(annotations_path(batch_dir)) else { return out };
    for line in text.lines().filter_map(|l| serde_json::from_str::<AnnotationLine>(l).ok()) {
        out.insert(StageKey { episode_id: line.episode_id, stage_name: line.stage_name }, line.annotation);
    }
    out
}

/// Every annotation of the batches' directories.
pub fn batches_annotations(batches: &[LoadedBatch]) -> StageAnnotations {
    batches.iter().flat_map(|b| read_annotations(&b.dir)).collect()
}

/// Appends one annotation to the batch's file (one `write` of one line: readers never see half of it).
pub fn append_annotation(batch_dir: &Path, line: &AnnotationLine) -> std::io::Result<()> {
    let mut text = serde_json::to_string(line).map_err(std::io::Error::other)?;
    text.push('\n');
    let mut f = std::fs::OpenOptions::new().create(true).append(true).open(annotations_path(batch_dir))?;
    f.write_all(text.as_bytes())
}

/// Why an annotation from outside may not be stored (None when it may): the stage must be one of the rollout's
/// required stages, the note and the name bounded, the modes only on a reached stage that did not succeed.
pub fn invalid_annotation(stages: &[StageOpportunity], stage_name: &str, a: &StageAnnotation) -> Option<String> {
    if !stages.iter().any(|s| s.stage_name == stage_name) {
        let names: Vec<&str> = stages.iter().map(|s| s.stage_name.as_str()).collect();
        return Some(format!("no required stage {stage_name:?} in this episode (its stages: {})", names.join(", ")));
    }
    if a.note.chars().count() > MAX_NOTE_CHARS {
        return Some(format!("a note holds at most {MAX_NOTE_CHARS} characters"));
    }
    let name = a.annotator.trim();
    if name.is_empty() || name.chars().count() > MAX_ANNOTATOR_CHARS || name.chars().any(char::is_control) {
        return Some(format!("the annotator is a name of 1 to {MAX_ANNOTATOR_CHARS} printable characters"));
    }
    if !a.failure_modes.is_empty() && (a.succeeded || !a.reached) {
        return Some("failure modes belong to a stage that was reached and did not succeed".to_owned());
    }
    None
}

/// The required stages of one rollout with their automatic evidence ([`StageOpportunity`]), from its private
/// record (stage types it lacks from `facts`); empty when the rollout has none.
pub fn rollout_stages(r: &RolloutRecord, facts: &TaskFacts) -> Vec<StageOpportunity> {
    crate::stages::rollout_opportunities(r, facts)
}

/// The failure modes in the order the page lists them (keys 1–4).
pub const MODES: [FailureMode; 4] = [FailureMode::LocalExecution, FailureMode::CrossStageInterference, FailureMode::GeometricError, FailureMode::Other];

#[cfg(test)]
mod tests {
    use super::*;
    use libero_metrics::StageEvidence;

    fn note(reached: bool, succeeded: bool, modes: &[FailureMode], at: &str) -> StageAnnotation {
        StageAnnotation { reached, succeeded, failure_modes: modes.to_vec(), note: "n".into(), annotator: "ana".into(), annotated_at: at.into() }
    }

    #[test]
    fn the_last_line_per_stage_counts_and_the_file_keeps_the_history() {
        let dir = tempfile::tempdir().unwrap();
        let line = |stage: &str, a: StageAnnotation| AnnotationLine { episode_id: "ep-1".into(), stage_name: stage.into(), annotation: a };
        append_annotation(dir.path(), &line("01_open", note(true, false, &[FailureMode::LocalExecution], "t1"))).unwrap();
        append_annotation(dir.path(), &line("02_place", note(false, false, &[], "t2"))).unwrap();
        append_annotation(dir.path(), &line("01_open", note(true, false, &[FailureMode::GeometricError], "t3"))).unwrap();
        std::fs::OpenOptions::new().append(true).open(annotations_path(dir.path())).unwrap().write_all(b"{not json\n").unwrap();
        let got = read_annotations(dir.path());
        assert_eq!(got.len(), 2);
        let open = &got[&StageKey { episode_id: "ep-1".into(), stage_name: "01_open".into() }];
        assert_eq!((open.failure_modes.as_slice(), open.annotated_at.as_str()), (&[FailureMode::GeometricError][..], "t3"));
        assert_eq!(std::fs::read_to_string(annotations_path(dir.path())).unwrap().lines().count(), 4, "history kept");
    }

    #[test]
    fn annotations_from_outside_are_checked_against_the_rollouts_stages() {
        let stage = |n: &str| StageOpportunity { episode_id: Some("ep-1".into()), task_number: 21, stage_name: n.into(), stage_type: None, evidence: StageEvidence::default() };
        let stages = [stage("01_open"), stage("02_place")];
        assert_eq!(invalid_annotation(&stages, "01_open", &note(true, false, &[FailureMode::Other], "t")), None);
        assert!(invalid_annotation(&stages, "03_nope", &note(true, true, &[], "t")).unwrap().contains("01_open, 02_place"));
        assert!(invalid_annotation(&stages, "01_open", &note(true, true, &[FailureMode::Other], "t")).unwrap().contains("did not succeed"));
        assert!(invalid_annotation(&stages, "01_open", &note(false, false, &[FailureMode::Other], "t")).is_some());
        let mut long = note(true, true, &[], "t");
        long.note = "x".repeat(MAX_NOTE_CHARS + 1);
        assert!(invalid_annotation(&stages, "01_open", &long).unwrap().contains("2000"));
        let mut nobody = note(true, true, &[], "t");
        nobody.annotator = " ".into();
        assert!(invalid_annotation(&stages, "01_open", &nobody).unwrap().contains("annotator"));
    }
}
