//! The checker kinds this build can judge, as one table: each family's `EVALUATORS` rows (and the staged kinds of
//! `judge::staged`, which several families share), concatenated. The catalog and the pool check their entries
//! against it when they load, and the registry builds each kind's evaluator from it. It names each family's table
//! and nothing else, so the catalog and pool sit below the registry (no import circle: the registry reads them, they
//! never read it). A kind is added by a row in its family's table.
use std::sync::LazyLock;

use crate::TasksError;
use crate::families::{adapted, libero, long_horizon, perception, vlabench};
use crate::judge::kind::{CheckerParams, EvaluatorKind};
use crate::judge::staged;

/// Every kind (and seesaw variant) this build judges.
pub static KINDS: LazyLock<Vec<EvaluatorKind>> = LazyLock::new(|| {
    [libero::EVALUATORS, vlabench::EVALUATORS, adapted::EVALUATORS, staged::EVALUATORS, long_horizon::EVALUATORS, perception::EVALUATORS]
        .concat()
});

/// The checker types this build can judge (the catalog refuses an implemented task whose checker is not here), in
/// table order, each once.
pub static EVALUATOR_KINDS: LazyLock<Vec<&'static str>> = LazyLock::new(|| {
    let mut names: Vec<&'static str> = Vec::new();
    for k in KINDS.iter() {
        if !names.contains(&k.name) {
            names.push(k.name);
        }
    }
    names
});

/// The table row that judges `checker` (see [`crate::judge::kind::find`]).
pub fn kind_of(checker: &CheckerParams) -> Result<&'static EvaluatorKind, TasksError> {
    crate::judge::kind::find(&KINDS, checker)
}

/// Whether `params` are well-formed for checker `kind` (known kind and variant, every field present and known), so a
/// malformed checker is refused when the manifest or the pool loads.
pub fn check_params(kind: &str, params: &serde_json::Value, task_id: &str) -> Result<(), String> {
    let checker = CheckerParams::new(kind, params, Some(task_id));
    let message = |e: TasksError| match e {
        TasksError::Catalog { message, .. } => message,
        other => other.to_string(),
    };
    (kind_of(&checker).map_err(message)?.check_params)(&checker).map_err(message)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_and_variant_has_one_row() {
        let mut rows: Vec<(&str, Option<&str>)> = KINDS.iter().map(|k| (k.name, k.variant)).collect();
        let n = rows.len();
        rows.sort();
        rows.dedup();
        assert_eq!(rows.len(), n, "a kind (or variant) listed twice");
        assert_eq!(EVALUATOR_KINDS.len(), 14);
    }

    fn row(kind: &str, params: serde_json::Value) -> Result<(&'static str, Option<&'static str>), String> {
        let checker = CheckerParams { kind, params: &params, task_id: Some("T99") };
        kind_of(&checker).map(|k| (k.name, k.variant)).map_err(|e| e.to_string())
    }

    #[test]
    fn the_seesaw_variant_picks_its_row_and_other_kinds_ignore_the_field() {
        use crate::families::vlabench::{seesaw, seesaw_adaptive, seesaw_comparison};
        assert_eq!(row(seesaw::CHECKER, serde_json::json!({})), Ok((seesaw::CHECKER, None)));
        let adaptive = serde_json::json!({"variant": seesaw_adaptive::VARIANT});
        assert_eq!(row(seesaw::CHECKER, adaptive), Ok((seesaw::CHECKER, Some(seesaw_adaptive::VARIANT))));
        let comparison = serde_json::json!({"variant": seesaw_comparison::VARIANT});
        assert_eq!(row(seesaw::CHECKER, comparison), Ok((seesaw::CHECKER, Some(seesaw_comparison::VARIANT))));
        let err = row(seesaw::CHECKER, serde_json::json!({"variant": "juggling"})).unwrap_err();
        assert!(err.contains("T99") && err.contains("no variant \"juggling\" in this build"), "{err}");
        assert_eq!(row("bddl_terminal", serde_json::json!({"variant": "x"})), Ok(("bddl_terminal", None)));
        let err = row("private_juggling", serde_json::json!({})).unwrap_err();
        assert!(err.contains("no evaluator of type private_juggling in this build"), "{err}");
    }
}
