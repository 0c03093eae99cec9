//! Generic staged evaluator driven by manifest parameters (task catalog §1.4, §1.4a, §2.4): a list of stages, each a
//! conjunction of atoms, evaluated at control rate in one of three order modes, plus terminal checks at finish.
//!
//! * `ordered` — the RoboMemArena ordered evaluator: only the current stage is tested each control step (at most one
//!   stage per step); a later stage that already holds completes as soon as it becomes current (T23, T26, T27).
//! * `strict` — `_StrictPredicateSequence`: before the current stage every later stage is tested; one that already
//!   holds latches an ordering violation (permanent failure).
//! * `unordered` — the cooking goal evaluator (T21, T22): K goals, completed = goals true on the final state; the
//!   initial and maximum goal counts and every change of the satisfied set are recorded.
//!
//! Atoms: a LIBERO predicate (`{"bddl": ["on", "moka_pot_1", "flat_stove_2_cook_region"]}`), or one of the
//! RoboMemArena checks: `near` (object root within `xy_max_m` horizontally of an anchor body or site, height
//! difference inside `dz_range_m`), `window` (object root minus an anchor body's or site's current position, in world
//! axes, strictly inside `x_m`, `y_m`, `z_m`: RoboMemArena's in-drawer window around a drawer's moving region site),
//! `drawer_open` / `drawer_closed` (world-y displacement of a drawer's region site
//! from its value at reset above / below a threshold, catalog §2.2), `in_box` (RoboMemArena box rule: site box with
//! half-extent |R·size|, lower z extended by `lower_z_m`, upper by `upper_z_m`), `released` (not grasped by
//! robosuite's two-pad test), `released_and_clear` (not grasped and the object's root at least `min_distance_m` from
//! the grip site, catalog §2.4), `lifted` (root z − z at reset > `above_m`), `joint` (a joint's position, or its
//! magnitude, strictly inside `(min, max)`: rad for hinges, m for slides — T28's latch), `pour_count` (a named pour
//! counter has registered ≥ `at_least` pours), `displaced_since` (the object's root at least `min_xy_m` horizontally from
//! where it was when a named earlier stage completed: VLABench find_unseen_object's "taken out after the drawer opened"),
//! `touching` (a live contact between two instances' body subtrees, distance ≤ `max_distance_m`: VLABench's "on the
//! real container", not hovering inside its region), `moved_xy` (root moved ≥ `min_m` horizontally from its pose at
//! reset), `any` (disjunction), `all` (conjunction, for use inside `any`) and `not`.
//!
//! Bindings (T23's "occupied drawer"): a name `$<binding>` usable wherever an atom names a site (drawer sites, `near`
//! anchors); at reset it is bound to the candidate site nearest (3-D) to an object's root, and stays bound for the
//! episode.
//!
//! Pour counters (T24): named RoboMemArena pour counters ([`crate::judge::pouring::PourTracker`], the T20 algorithm). A counter is
//! created the first control step a stage naming it is current (RoboMemArena creates it when the pour stage is first
//! evaluated) and from then on updated once per control step, before the stages are tested; `pour_count` atoms read it
//! (0 before creation). Failure monitors latch a permanent failure (e.g. `extra_pour`) at the first control step at or
//! after a given stage's completion where their atom holds.
//!
//! Optional guards and rates (T25): `forbidden_contacts` latches a permanent failure the first tick any listed
//! object's body subtree touches a forbidden body's subtree (contact distance ≤ `max_distance_m`), recorded as
//! `<object>_touched_<label>`; it is checked first at every tick and stops all further tracking. With
//! `sample_substeps` the stage logic also runs after every physics substep (same rules at both rates).
//!
//! Completed stages are re-tested every control step: a completed stage whose conjunction stops holding is recorded
//! as a regression (event + count), and stays completed. Mechanism operations record the sustained-contact ratio as a
//! diagnostic (paper Figure 3: SCR = N_sustained / N_exec over gripper contact with the mechanism's declared handle,
//! [`crate::judge::mechanism`]; an opening whose mechanism has no declared handle is refused): every stage whose atoms
//! open an articulation (`bddl open`, `drawer_open`, a `joint` bound toward its class's open test) is an opening
//! operation on the moving bodies of the articulations it tests, and a stage naming a `contact_body` is an operation
//! on that body whatever its direction (T23's closings, T28's latch). Ordered modes count the control steps the stage
//! was current; the unordered mode, where every goal is available at once, counts from the first gripper contact with
//! the mechanism while the opening is pending. Each stage's catalog `type` (object_manipulation /
//! mechanism_interaction) is checked here and reported by the stage diagnostics.
//!
//! By job: `lang` is the params the manifest writes, `compile` resolves them against the scene into checks and
//! stages, `monitor` holds what is watched besides the stages (failure monitors, forbidden contacts, the unordered
//! goal set), and `eval` is the evaluator that samples and judges them.
mod compile;
mod eval;
mod lang;
mod monitor;

use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::support::scene_goal_and_commitment;

pub use crate::judge::mechanism::{ContactMonitor, SUSTAINED_RUN_STEPS};
pub use self::eval::StagedEvaluator;
pub use self::lang::{
    AtomSpec, BindingParams, FailureMonitorParams, ForbiddenContactParams, OrderMode, PourCounterParams, StageParams,
    StagedParams,
};
pub use self::monitor::{GoalSetChange, GoalSetTracker};

pub const CHECKER_ORDERED: &str = "private_ordered_stages";
pub const CHECKER_UNORDERED: &str = "private_unordered_goal_predicates";
/// T25's checker: strict stages, substep sampling and the bowl–table contact guard, all from the manifest params.
pub const CHECKER_BUFFER_ROTATION: &str = "private_ordered_buffer_rotation_and_tabletop_avoidance";

/// The three staged kinds' table rows (one builder: the params say how the stages are judged). They delimit
/// operations by their own stages.
pub const EVALUATORS: &[EvaluatorKind] = &[staged(CHECKER_ORDERED), staged(CHECKER_UNORDERED), staged(CHECKER_BUFFER_ROTATION)];

const fn staged(name: &'static str) -> EvaluatorKind {
    EvaluatorKind {
        stages_delimit_operations: true,
        ..EvaluatorKind::plain(name, check::<StagedParams>, |checker, scene, model| {
            let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
            let p = checker.parse()?;
            Ok(Box::new(StagedEvaluator::new(checker.kind, p, goal, commitment, model, checker.task_id_owned())?))
        })
    }
}
