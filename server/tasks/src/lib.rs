//! Tasks: the LIBERO goal predicates on a composed scene, the private evaluators that judge an episode, and the
//! catalog of the 30 release tasks (`tasks/manifest.json`). No I/O servers and no rendering here.
pub mod bddl_terminal;
pub mod button_press;
pub mod catalog;
pub mod commitment;
pub mod diagnostics;
pub mod error;
pub mod evaluator;
pub mod expert;
pub mod factory;
pub mod goal;
pub mod hammer_contact;
pub mod pour;
pub mod predicates;
pub mod seesaw;
pub mod staged;
pub mod tube_insertion;
pub mod weighing;
pub mod wipe;

pub use error::TasksError;
pub use catalog::{Catalog, TaskEntry};
pub use evaluator::{EvaluationRecord, Evaluator, Tick};
pub use factory::{apply_private_model_edits, build_evaluator};
pub use goal::{GoalChecker, GoalReport, PredicateValue};
pub use predicates::{ArticulationRule, EntityRef, JointTest, PredicateKind, SceneIndex, articulation_rule};
