//! Tasks: the LIBERO goal predicates on a composed scene, the private evaluators that judge an episode, the scripted
//! experts that prove each task solvable, the catalog of the release tasks (`tasks/manifest.json`) and the pool of
//! every task the original registers (`tasks/pool.json`). No I/O servers and no rendering here.
//!
//! Layout: `judge` is the shared machinery every evaluator builds on and imports no family; `expert` is the same
//! for the scripted experts; `families/<family>` holds a task family's evaluators and experts; `registry` is the one
//! place that knows every checker kind and every family's experts.
pub mod catalog;
pub mod checkers;
pub mod error;
pub mod expert;
pub mod families;
pub mod judge;
pub mod pool;
pub mod registry;
pub mod selector;

pub use catalog::{Catalog, TaskEntry};
pub use error::TasksError;
pub use pool::{Pool, PoolEntry};
pub use selector::{Member, Pick, Selection, SelectionError};
pub use judge::evaluator::{EvaluationRecord, Evaluator, Tick};
pub use judge::goal::{GoalChecker, GoalReport, PredicateValue};
pub use judge::predicates::{ArticulationRule, EntityRef, JointTest, PredicateKind, SceneIndex, articulation_rule};
pub use registry::{STOCK_SUITES, apply_private_model_edits, build_evaluator, expert_behaviours, expert_for, expert_plan};
