//! The stage-level diagnosis of the long-horizon tasks: the paper's Table 4 ([`diagnose_paper`]) and this project's
//! richer all-tasks extension ([`diagnose`]), both over *stage opportunities* — one required stage of one counted
//! rollout — labelled from the evidence in the evaluator's private record ([`StageEvidence`]) unless a person
//! annotated the stage ([`StageAnnotation`], which then wins).
//!
//! **Reached** (the same rule for both tables, and for the record's own `stage_diagnostics[].reached`): a stage is
//! reached only when the record shows the agent got to it — never because it comes first:
//!
//! * its goal held at some point of the episode (completed, regressed, or held at the end); or
//! * ordered stages after the first: the stage before it completed, so the agent established its preconditions; or
//! * the gripper touched the stage's mechanism during the stage's operation (a contact run in its monitored
//!   operation: drawers, doors, the latch, the microwave); or
//! * the agent changed the task's objects while the stage was the current one (a strict-order violation, or a
//!   forbidden contact, latched with this stage current).
//!
//! So the first ordered stage and every unordered goal (T21/T22) count as reached only on evidence of interaction,
//! and a rollout that never touched the task has no reached stage. Evidence is missing for an object the agent
//! grasped and let go without completing or disturbing anything; such a stage reads as not reached unless annotated.
//!
//! **Success**: the stage latched as completed (ordered evaluators) or holds on the final state (unordered goals).
//!
//! **The paper's Table 4** ([`diagnose_paper`]; the hard long-horizon tasks T21, T22, T25, T28, T30 — 20 stages):
//! Reached and Success over all stage opportunities; Execution SR per stage type = successes / reached stages of that
//! type, after excluding reached stages whose failure is attributed to cross-stage interference; Local Execution and
//! Cross-stage Interference as shares of the reached-but-failed stages, which may overlap (a stage may have both
//! modes). A stage that completed and was undone later but still counts as completed is a success, not a failure.
//!
//! **Automatic failure modes** of a reached stage that did not succeed: cross-stage interference when its completed
//! state was undone (a regression) or a later stage's state made before its turn blocked it (the strict order's
//! violation latch); otherwise local execution. The automatic labels never overlap and never name geometric error or
//! another mode; annotations may.
//!
//! **The extension** ([`diagnose`], "Table 4+", every long-horizon task, automatic labels only): execution success
//! over reached stages without the exclusion, with Wilson intervals, and exclusive modes whose failures also count a
//! completed stage that a later stage undid.
use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::{Proportion, Split};

/// What the report reads of the release tasks beside their records: each task's declared stage types (for records
/// written before the evaluator reported them) and its required stages K (Appendix E's K row). Plain data, so the
/// report computes without the task catalog (and so without the simulator): its callers fill it from the catalog
/// (`libero_tasks::catalog::task_facts`); empty, the report takes what the records say.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TaskFacts {
    /// Per task number, its stages' names and declared types, in order.
    pub stage_types: BTreeMap<u32, Vec<(String, Option<StageType>)>>,
    /// Per task number, its required stages K.
    pub stage_counts: BTreeMap<u32, u32>,
}

/// What a stage asks of the agent (declared per stage in `tasks/manifest.json` and `tasks/pool.json`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StageType {
    /// Grasp, move, place, pour, insert, wipe an object.
    ObjectManipulation,
    /// Operate an articulated or actuated mechanism: drawers, doors, latches, knobs, buttons, a seesaw.
    MechanismInteraction,
}

impl StageType {
    pub const ALL: [StageType; 2] = [StageType::ObjectManipulation, StageType::MechanismInteraction];

    /// The paper's name.
    pub fn label(self) -> &'static str {
        match self {
            StageType::ObjectManipulation => "Object Manipulation",
            StageType::MechanismInteraction => "Mechanism Interaction",
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            StageType::ObjectManipulation => "object_manipulation",
            StageType::MechanismInteraction => "mechanism_interaction",
        }
    }
}

/// Why a reached stage failed. The paper's Table 4 reports the first two; a person annotating a stage may also name
/// a geometric error (§5.3: a wrong position, orientation or clearance) or another cause. A stage may have several.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FailureMode {
    LocalExecution,
    CrossStageInterference,
    GeometricError,
    Other,
}

impl FailureMode {
    pub const ALL: [FailureMode; 4] =
        [FailureMode::LocalExecution, FailureMode::CrossStageInterference, FailureMode::GeometricError, FailureMode::Other];

    pub fn as_str(self) -> &'static str {
        match self {
            FailureMode::LocalExecution => "local_execution",
            FailureMode::CrossStageInterference => "cross_stage_interference",
            FailureMode::GeometricError => "geometric_error",
            FailureMode::Other => "other",
        }
    }

    /// The paper's name.
    pub fn label(self) -> &'static str {
        match self {
            FailureMode::LocalExecution => "Local Execution",
            FailureMode::CrossStageInterference => "Cross-stage Interference",
            FailureMode::GeometricError => "Geometric Error",
            FailureMode::Other => "Other",
        }
    }
}

/// The tasks of the paper's Table 4: the hard long-horizon ones (T21, T22, T25, T28, T30).
pub fn in_paper_table4(task_number: u32) -> bool {
    Split::LongHorizonHard.members().contains(&task_number)
}

/// What one rollout's private record shows about one required stage (see the module documentation for how it
/// decides reached and the automatic failure modes).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StageEvidence {
    /// The stage latched as completed (ordered) or holds on the final state (unordered): the benchmark's success.
    pub succeeded: bool,
    /// The stage's goal held at some point of the episode (a completion event, a regression, or success).
    #[serde(default)]
    pub completed_at_some_point: bool,
    /// Ordered stages after the first: the stage before it completed. Never set for the first ordered stage or an
    /// unordered goal (their preconditions hold at reset, which says nothing about the agent).
    #[serde(default)]
    pub preconditions_established: bool,
    /// The gripper touched the stage's mechanism during the stage's operation (a contact run).
    #[serde(default)]
    pub touched_mechanism: bool,
    /// The agent changed the task's objects while this stage was current (a strict-order violation or a forbidden
    /// contact latched then).
    #[serde(default)]
    pub acted_while_current: bool,
    /// Times a completed stage stopped holding.
    #[serde(default)]
    pub regressions: u32,
    /// A completed stage stopped holding while a later stage was worked on.
    #[serde(default)]
    pub regressed_during_later_stage: bool,
    /// The stage could not complete because another stage's state was made before its turn (order violation).
    #[serde(default)]
    pub blocked_by_other_stage: bool,
}

impl StageEvidence {
    /// Reached on evidence only (module documentation).
    pub fn reached(&self) -> bool {
        self.succeeded
            || self.completed_at_some_point
            || self.regressions > 0
            || self.preconditions_established
            || self.touched_mechanism
            || self.acted_while_current
    }

    /// The automatic failure modes: none unless reached and not succeeded; then cross-stage interference when the
    /// stage's state was undone or another stage's state blocked it, else local execution.
    pub fn failure_modes(&self) -> Vec<FailureMode> {
        if !self.reached() || self.succeeded {
            Vec::new()
        } else if self.regressions > 0 || self.blocked_by_other_stage {
            vec![FailureMode::CrossStageInterference]
        } else {
            vec![FailureMode::LocalExecution]
        }
    }
}

/// One required stage of one counted rollout, with its record's evidence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageOpportunity {
    /// The rollout's episode (annotations are keyed by it); `None` for a record without one.
    #[serde(default)]
    pub episode_id: Option<String>,
    pub task_number: u32,
    pub stage_name: String,
    /// `None` when neither the record nor the catalog declares it (counted, but in no per-type column).
    pub stage_type: Option<StageType>,
    #[serde(flatten)]
    pub evidence: StageEvidence,
}

/// The extension's single failure of an opportunity (automatic, exclusive).
impl StageOpportunity {
    pub fn reached(&self) -> bool {
        self.evidence.reached()
    }

    /// The extension's failure, if any: a reached stage that did not succeed (interference when it regressed or
    /// was blocked), or a completed stage that a later stage undid (interference).
    pub fn failure(&self) -> Option<FailureMode> {
        let e = &self.evidence;
        if self.reached() && !e.succeeded {
            let interfered = e.regressions > 0 || e.blocked_by_other_stage;
            Some(if interfered { FailureMode::CrossStageInterference } else { FailureMode::LocalExecution })
        } else if e.succeeded && e.regressed_during_later_stage {
            Some(FailureMode::CrossStageInterference)
        } else {
            None
        }
    }

    /// The automatic label of this stage.
    pub fn automatic(&self) -> StageLabel {
        StageLabel {
            reached: self.reached(),
            succeeded: self.evidence.succeeded,
            failure_modes: self.evidence.failure_modes(),
            source: LabelSource::Automatic,
        }
    }

    /// The stage's label: the person's annotation where there is one for this episode and stage, else automatic.
    pub fn label(&self, annotations: Option<&StageAnnotations>) -> StageLabel {
        let annotated = self.episode_id.as_ref().and_then(|episode| {
            annotations?.get(&StageKey { episode_id: episode.clone(), stage_name: self.stage_name.clone() })
        });
        match annotated {
            Some(a) => a.label(),
            None => self.automatic(),
        }
    }
}

/// Who labelled a stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LabelSource {
    Automatic,
    Annotated,
}

/// A stage's label as Table 4 counts it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct StageLabel {
    pub reached: bool,
    pub succeeded: bool,
    /// Modes of a reached stage that did not succeed (empty otherwise); several may apply.
    pub failure_modes: Vec<FailureMode>,
    pub source: LabelSource,
}

impl StageLabel {
    /// Reached and not succeeded.
    pub fn failed(&self) -> bool {
        self.reached && !self.succeeded
    }

    pub fn has(&self, mode: FailureMode) -> bool {
        self.failed() && self.failure_modes.contains(&mode)
    }
}

/// A person's judgment of one stage of one episode. Where given, it replaces the automatic diagnosis of that stage
/// in the paper's Table 4 (reached, succeeded and the failure modes together).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct StageAnnotation {
    pub reached: bool,
    /// A succeeded stage counts as reached whatever `reached` says.
    pub succeeded: bool,
    /// Why a reached stage failed; several allowed; ignored when the stage succeeded or was not reached.
    #[serde(default)]
    pub failure_modes: Vec<FailureMode>,
    #[serde(default)]
    pub note: String,
    /// Who annotated.
    pub annotator: String,
    /// When (RFC 3339).
    pub annotated_at: String,
}

impl StageAnnotation {
    pub fn label(&self) -> StageLabel {
        let reached = self.reached || self.succeeded;
        let mut failure_modes = if reached && !self.succeeded { self.failure_modes.clone() } else { Vec::new() };
        failure_modes.sort_unstable();
        failure_modes.dedup();
        StageLabel { reached, succeeded: self.succeeded, failure_modes, source: LabelSource::Annotated }
    }
}

/// Which stage an annotation is about: the episode (`rollouts.jsonl` → `episode_id`) and the stage's name.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct StageKey {
    pub episode_id: String,
    pub stage_name: String,
}

/// Every annotation at hand, by stage.
pub type StageAnnotations = BTreeMap<StageKey, StageAnnotation>;

// ------------------------------------------------------------------------------------------- the paper's Table 4

/// One Execution SR column of the paper's Table 4.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExecutionRate {
    pub stage_type: StageType,
    pub opportunities: usize,
    pub reached: usize,
    /// Reached stages of this type whose failure is attributed to cross-stage interference (left out).
    pub excluded_interference: usize,
    /// Successes / (reached − excluded).
    pub execution_success: Proportion,
}

/// The paper's Table 4 for one agent under one condition.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PaperStageDiagnosis {
    pub rollouts: usize,
    /// Stage opportunities (required stages × rollouts).
    pub opportunities: usize,
    /// Opportunities labelled by a person's annotation / by the automatic diagnosis.
    pub annotated: usize,
    pub automatic: usize,
    /// Reached / all opportunities.
    pub reached: Proportion,
    /// Succeeded / all opportunities.
    pub success: Proportion,
    pub object_manipulation: ExecutionRate,
    pub mechanism_interaction: ExecutionRate,
    /// Opportunities whose stage type is declared nowhere (in neither Execution SR column).
    pub untyped_opportunities: usize,
    /// Reached stages that did not succeed: the denominator of the two modes.
    pub failed: usize,
    /// Failed stages with local execution among their modes / failed.
    pub local_execution: Proportion,
    /// Failed stages with cross-stage interference among their modes / failed (may overlap local execution).
    pub cross_stage_interference: Proportion,
    /// Failed stages an annotation labels a geometric error / another cause (not columns of the paper's table).
    pub geometric_error: usize,
    pub other: usize,
    /// Failed stages with no mode at all (an annotation that names none).
    pub unattributed: usize,
}

/// The paper's Table 4 over `opportunities` (those of the hard long-horizon tasks, see [`in_paper_table4`]) of
/// `rollouts` counted rollouts, each stage labelled by its annotation where `annotations` has one, else
/// automatically.
pub fn diagnose_paper(opportunities: &[StageOpportunity], rollouts: usize, annotations: Option<&StageAnnotations>) -> PaperStageDiagnosis {
    let labelled: Vec<(&StageOpportunity, StageLabel)> = opportunities.iter().map(|o| (o, o.label(annotations))).collect();
    let n = labelled.len() as u64;
    let count = |f: &dyn Fn(&StageOpportunity, &StageLabel) -> bool| labelled.iter().filter(|(o, l)| f(o, l)).count();
    let execution = |t: StageType| {
        let of_type = |o: &StageOpportunity| o.stage_type == Some(t);
        let reached = count(&|o, l| of_type(o) && l.reached);
        let excluded = count(&|o, l| of_type(o) && l.has(FailureMode::CrossStageInterference));
        let succeeded = count(&|o, l| of_type(o) && l.reached && l.succeeded);
        ExecutionRate {
            stage_type: t,
            opportunities: count(&|o, _| of_type(o)),
            reached,
            excluded_interference: excluded,
            execution_success: Proportion::new(succeeded as u64, (reached - excluded) as u64),
        }
    };
    let failed = count(&|_, l| l.failed()) as u64;
    let mode = |m: FailureMode| count(&|_, l| l.has(m));
    PaperStageDiagnosis {
        rollouts,
        opportunities: labelled.len(),
        annotated: count(&|_, l| l.source == LabelSource::Annotated),
        automatic: count(&|_, l| l.source == LabelSource::Automatic),
        reached: Proportion::new(count(&|_, l| l.reached) as u64, n),
        success: Proportion::new(count(&|_, l| l.reached && l.succeeded) as u64, n),
        object_manipulation: execution(StageType::ObjectManipulation),
        mechanism_interaction: execution(StageType::MechanismInteraction),
        untyped_opportunities: count(&|o, _| o.stage_type.is_none()),
        failed: failed as usize,
        local_execution: Proportion::new(mode(FailureMode::LocalExecution) as u64, failed),
        cross_stage_interference: Proportion::new(mode(FailureMode::CrossStageInterference) as u64, failed),
        geometric_error: mode(FailureMode::GeometricError),
        other: mode(FailureMode::Other),
        unattributed: count(&|_, l| l.failed() && l.failure_modes.is_empty()),
    }
}

// ------------------------------------------------------------------------------------------- the extension (Table 4+)

/// Execution success of one stage type (the extension).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TypeExecution {
    pub stage_type: StageType,
    pub opportunities: usize,
    pub reached: usize,
    /// Successes over reached opportunities of this type, with its Wilson interval.
    pub execution_success: Proportion,
}

/// The extension ("Table 4+", every long-horizon task, automatic labels) for one agent under one condition.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageDiagnosis {
    pub rollouts: usize,
    pub opportunities: usize,
    /// Reached opportunities over all opportunities.
    pub reached: Proportion,
    /// Successful opportunities over all opportunities.
    pub success: Proportion,
    pub by_type: Vec<TypeExecution>,
    /// Opportunities whose stage type is declared nowhere.
    pub untyped_opportunities: usize,
    pub failures: usize,
    pub local_execution: usize,
    pub cross_stage_interference: usize,
    /// Cross-stage interference over all failures.
    pub interference_share: Option<f64>,
}

/// The extension over the stage opportunities of `rollouts` counted rollouts (automatic labels).
pub fn diagnose(opportunities: &[StageOpportunity], rollouts: usize) -> StageDiagnosis {
    let count = |f: &dyn Fn(&StageOpportunity) -> bool| opportunities.iter().filter(|o| f(o)).count() as u64;
    let n = opportunities.len() as u64;
    let by_type = StageType::ALL
        .into_iter()
        .filter_map(|t| {
            let of_type: Vec<&StageOpportunity> = opportunities.iter().filter(|o| o.stage_type == Some(t)).collect();
            let reached = of_type.iter().filter(|o| o.reached()).count();
            let succeeded = of_type.iter().filter(|o| o.reached() && o.evidence.succeeded).count();
            (!of_type.is_empty()).then(|| TypeExecution {
                stage_type: t,
                opportunities: of_type.len(),
                reached,
                execution_success: Proportion::new(succeeded as u64, reached as u64),
            })
        })
        .collect();
    let failures: Vec<FailureMode> = opportunities.iter().filter_map(StageOpportunity::failure).collect();
    let interference = failures.iter().filter(|&&f| f == FailureMode::CrossStageInterference).count();
    StageDiagnosis {
        rollouts,
        opportunities: opportunities.len(),
        reached: Proportion::new(count(&|o| o.reached()), n),
        success: Proportion::new(count(&|o| o.reached() && o.evidence.succeeded), n),
        by_type,
        untyped_opportunities: opportunities.iter().filter(|o| o.stage_type.is_none()).count(),
        failures: failures.len(),
        local_execution: failures.len() - interference,
        cross_stage_interference: interference,
        interference_share: (!failures.is_empty()).then(|| interference as f64 / failures.len() as f64),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn op(t: StageType, reached: bool, succeeded: bool) -> StageOpportunity {
        StageOpportunity {
            episode_id: Some("ep".into()),
            task_number: 27,
            stage_name: "s".into(),
            stage_type: Some(t),
            evidence: StageEvidence { succeeded, preconditions_established: reached, ..StageEvidence::default() },
        }
    }

    #[test]
    fn execution_success_divides_by_reached_and_failures_split_by_cause() {
        use StageType::*;
        let mut regressed = op(ObjectManipulation, true, true);
        regressed.evidence.regressions = 1;
        regressed.evidence.regressed_during_later_stage = true;
        let mut blocked = op(ObjectManipulation, true, false);
        blocked.evidence.blocked_by_other_stage = true;
        let ops = [
            op(MechanismInteraction, true, true),
            op(MechanismInteraction, true, false), // local
            op(MechanismInteraction, false, false), // not reached: no failure
            regressed,                              // success, and interference
            blocked,                                // interference
        ];
        let d = diagnose(&ops, 2);
        assert_eq!((d.opportunities, d.reached.successes, d.success.successes), (5, 4, 2));
        let mech = d.by_type.iter().find(|t| t.stage_type == MechanismInteraction).unwrap();
        assert_eq!((mech.opportunities, mech.reached, mech.execution_success.successes, mech.execution_success.trials), (3, 2, 1, 2));
        let obj = d.by_type.iter().find(|t| t.stage_type == ObjectManipulation).unwrap();
        assert_eq!((obj.execution_success.successes, obj.execution_success.trials), (1, 2));
        assert_eq!((d.failures, d.local_execution, d.cross_stage_interference), (3, 1, 2));
        assert_eq!(d.interference_share, Some(2.0 / 3.0));
    }

    #[test]
    fn an_unordered_goal_lost_after_completing_is_interference() {
        let mut lost = op(StageType::MechanismInteraction, false, false);
        lost.evidence.regressions = 2;
        assert!(lost.reached(), "a goal that held once was reached");
        assert_eq!(lost.failure(), Some(FailureMode::CrossStageInterference));
        assert_eq!(op(StageType::MechanismInteraction, true, false).failure(), Some(FailureMode::LocalExecution));
    }

    #[test]
    fn reached_needs_evidence_of_the_agent() {
        let none = StageEvidence::default();
        assert!(!none.reached(), "a first stage nobody touched is not reached");
        assert!(none.failure_modes().is_empty());
        for e in [
            StageEvidence { succeeded: true, ..StageEvidence::default() },
            StageEvidence { completed_at_some_point: true, ..StageEvidence::default() },
            StageEvidence { preconditions_established: true, ..StageEvidence::default() },
            StageEvidence { touched_mechanism: true, ..StageEvidence::default() },
            StageEvidence { acted_while_current: true, blocked_by_other_stage: true, ..StageEvidence::default() },
        ] {
            assert!(e.reached(), "{e:?}");
        }
    }

    #[test]
    fn an_annotation_replaces_the_automatic_label_of_its_stage_only() {
        let o = op(StageType::ObjectManipulation, true, false);
        assert_eq!(o.automatic().failure_modes, [FailureMode::LocalExecution]);
        let mut notes = StageAnnotations::new();
        notes.insert(
            StageKey { episode_id: "ep".into(), stage_name: "s".into() },
            StageAnnotation {
                reached: true,
                succeeded: false,
                failure_modes: vec![FailureMode::GeometricError, FailureMode::CrossStageInterference, FailureMode::GeometricError],
                note: "bowl placed off the plate's centre".into(),
                annotator: "ann".into(),
                annotated_at: "2026-01-01T00:00:00Z".into(),
            },
        );
        let l = o.label(Some(&notes));
        assert_eq!(l.source, LabelSource::Annotated);
        assert_eq!(l.failure_modes, [FailureMode::CrossStageInterference, FailureMode::GeometricError]);
        let mut other = o.clone();
        other.episode_id = Some("ep2".into());
        assert_eq!(other.label(Some(&notes)).source, LabelSource::Automatic);
        // a success implies reached, and a success has no failure mode
        let ok = StageAnnotation { reached: false, succeeded: true, failure_modes: vec![FailureMode::Other], note: String::new(),
            annotator: "a".into(), annotated_at: "t".into() };
        assert_eq!((ok.label().reached, ok.label().failure_modes.len()), (true, 0));
    }

    /// Six opportunities by hand: OM success; OM failed by interference (left out of OM's Execution SR); OM not
    /// reached; MI success after a regression (still a success, no failure); MI failed locally; MI failed, annotated
    /// with both modes. Reached 5/6, success 2/6; OM 1/(2 − 1) = 1/1; MI 1/(3 − 1) = 1/2; failed 3: local execution 2/3,
    /// interference 2/3 (overlapping on the annotated stage).
    #[test]
    fn the_paper_table_excludes_interference_failures_and_lets_modes_overlap() {
        use StageType::*;
        let mut om_csi = op(ObjectManipulation, true, false);
        om_csi.evidence.blocked_by_other_stage = true;
        let mut mi_regressed = op(MechanismInteraction, false, true);
        mi_regressed.evidence.regressions = 1;
        mi_regressed.evidence.regressed_during_later_stage = true;
        let mut both = op(MechanismInteraction, false, false);
        both.stage_name = "annotated".into();
        let ops = [op(ObjectManipulation, true, true), om_csi, op(ObjectManipulation, false, false), mi_regressed, op(MechanismInteraction, true, false), both];
        let mut notes = StageAnnotations::new();
        notes.insert(
            StageKey { episode_id: "ep".into(), stage_name: "annotated".into() },
            StageAnnotation {
                reached: true,
                succeeded: false,
                failure_modes: vec![FailureMode::LocalExecution, FailureMode::CrossStageInterference],
                note: String::new(),
                annotator: "a".into(),
                annotated_at: "2026-01-01T00:00:00Z".into(),
            },
        );
        let d = diagnose_paper(&ops, 2, Some(&notes));
        let pair = |p: &Proportion| (p.successes, p.trials);
        assert_eq!((d.opportunities, d.annotated, d.automatic), (6, 1, 5));
        assert_eq!((pair(&d.reached), pair(&d.success)), ((5, 6), (2, 6)));
        assert_eq!(pair(&d.object_manipulation.execution_success), (1, 1));
        assert_eq!(pair(&d.mechanism_interaction.execution_success), (1, 2));
        assert_eq!(d.failed, 3);
        assert_eq!((pair(&d.local_execution), pair(&d.cross_stage_interference)), ((2, 3), (2, 3)));
        // without the annotation that stage is not reached: 4/6 reached; MI reached 2 (the success, the local
        // failure), none left out → 1/2; local 1/2, interference 1/2
        let auto = diagnose_paper(&ops, 2, None);
        assert_eq!((pair(&auto.reached), pair(&auto.mechanism_interaction.execution_success)), ((4, 6), (1, 2)));
        assert_eq!((pair(&auto.local_execution), pair(&auto.cross_stage_interference)), ((1, 2), (1, 2)));
    }

    #[test]
    fn failure_modes_serialize_by_their_snake_case_names() {
        for m in FailureMode::ALL {
            assert_eq!(serde_json::to_value(m).unwrap(), m.as_str());
        }
        let a: StageAnnotation = serde_json::from_value(serde_json::json!({"reached": true, "succeeded": false,
            "failure_modes": ["local_execution", "geometric_error"], "annotator": "x", "annotated_at": "2026-01-01T00:00:00Z"}))
        .unwrap();
        assert_eq!(a.failure_modes, [FailureMode::LocalExecution, FailureMode::GeometricError]);
    }
}
