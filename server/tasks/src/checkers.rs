//! The checker kinds this build can judge, as data: the catalog and the pool check their entries against it when they
//! load, and the registry (which builds each kind's evaluator) re-exports it. It names each family's `CHECKER`
//! constant and nothing else, so the catalog and pool sit below the registry (no import circle: the registry reads
//! them, they never read it). A kind added here needs its evaluator in `registry::build_evaluator`.
use crate::families::adapted::{hammer_contact, pour_wine as pour, wipe};
use crate::families::libero::bddl_terminal;
use crate::families::long_horizon::{coffee, staged};
use crate::families::perception::weighing;
use crate::families::vlabench::{button_press, seesaw, tube_insertion};

/// The checker types this build can judge (the catalog refuses an implemented task whose checker is not here).
pub const EVALUATOR_KINDS: &[&str] = &[
    bddl_terminal::CHECKER,
    "bddl_terminal_open",
    button_press::CHECKER,
    button_press::GATED_CHECKER,
    tube_insertion::CHECKER,
    wipe::CHECKER,
    pour::CHECKER,
    staged::CHECKER_ORDERED,
    staged::CHECKER_UNORDERED,
    staged::CHECKER_BUFFER_ROTATION,
    coffee::CHECKER,
    weighing::CHECKER,
    hammer_contact::CHECKER,
    seesaw::CHECKER,
];
