//! The staged evaluator's language: the kinds' `checker.params` as the manifest writes them (stages of atoms,
//! bindings, pour counters, failure monitors, forbidden contacts), parsed and not yet compiled.
use serde::{Deserialize, Serialize};

use crate::judge::evaluator::FailureReason;
use crate::judge::pouring::PourCounterConfig;
use crate::judge::stage_types::StageType;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OrderMode {
    #[default]
    Ordered,
    Strict,
    Unordered,
}

/// One atom of a stage or terminal conjunction.
#[derive(Debug, Clone, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum AtomSpec {
    /// `[predicate, arg…]`, a LIBERO predicate.
    Bddl(Vec<String>),
    /// `object`'s root within `xy_max_m` of `anchor` (an instance's root or a site) horizontally and `dz_range_m` above
    /// it; with `square`, |dx| and |dy| each below `xy_max_m` (RoboMemArena's microwave rule) instead of the distance.
    Near {
        object: String,
        anchor: String,
        xy_max_m: f64,
        dz_range_m: [f64; 2],
        #[serde(default)]
        square: bool,
    },
    /// Object root minus the anchor's current position (instance root body, else site), world axes, strictly inside each range.
    Window { object: String, anchor: String, x_m: [f64; 2], y_m: [f64; 2], z_m: [f64; 2] },
    DrawerOpen { site: String, min_displacement_m: f64 },
    DrawerClosed { site: String, max_displacement_m: f64 },
    InBox { object: String, site: String, lower_z_m: f64, upper_z_m: f64 },
    Released(String),
    ReleasedAndClear { object: String, min_distance_m: f64 },
    Lifted { object: String, above_m: f64 },
    /// A joint's position (rad for hinges, m for slides) strictly above `min` and below `max` where given; with
    /// `abs`, its magnitude (a handle that unlatches turned either way).
    Joint {
        name: String,
        #[serde(default)]
        min: Option<f64>,
        #[serde(default)]
        max: Option<f64>,
        #[serde(default)]
        abs: bool,
    },
    /// The named pour counter (`pour_counters`) has registered at least `at_least` pours.
    PourCount { counter: String, at_least: usize },
    /// `object`'s root at least `min_xy_m` (horizontal) from its position when stage `stage` completed; false while
    /// that stage has not completed.
    DisplacedSince { object: String, stage: String, min_xy_m: f64 },
    /// A contact between `object`'s and `other`'s body subtrees with distance ≤ `max_distance_m` (a live support,
    /// not a hover inside a region).
    Touching { object: String, other: String, max_distance_m: f64 },
    /// `object`'s root is at least `min_m` from its reset position horizontally (it was really moved).
    MovedXy { object: String, min_m: f64 },
    /// At least one of the atoms holds.
    Any(Vec<AtomSpec>),
    /// Every one of the atoms holds (inside an `any`: RoboMemArena task 14's "the drawer holding the object is closed").
    All(Vec<AtomSpec>),
    Not(Box<AtomSpec>),
}

/// A site chosen per episode: among `sites`, the one whose world position at reset is nearest (3-D) to the root of
/// `nearest_to`. Atoms name it `$<name>`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BindingParams {
    pub name: String,
    pub nearest_to: String,
    pub sites: Vec<String>,
}

/// A named pour counter: `bottle` poured over `target_site` (catalog §4 T20 algorithm and thresholds).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PourCounterParams {
    pub name: String,
    pub bottle: String,
    pub target_site: String,
    #[serde(flatten)]
    pub config: PourCounterConfig,
}

/// A permanent failure latched at the first control step, at or after `after_stage` completed, where `when` holds.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FailureMonitorParams {
    pub name: String,
    pub after_stage: String,
    pub when: AtomSpec,
    pub reason: FailureReason,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StageParams {
    pub name: String,
    /// The stage's type for the stage-level diagnosis (read from the catalog by [`crate::judge::stage_types`]).
    #[serde(default, rename = "type")]
    pub stage_type: Option<StageType>,
    pub all: Vec<AtomSpec>,
    /// Body (subtree) whose contact with the gripper is monitored while this stage is current, instead of the
    /// moving bodies its atoms imply (a handle narrower than the door, or a closing).
    #[serde(default)]
    pub contact_body: Option<String>,
}

/// A contact that fails the run for good the first time it is seen (T25: a bowl touching the tabletop).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ForbiddenContactParams {
    /// Instances none of whose body subtrees may touch `body`.
    pub objects: Vec<String>,
    /// MuJoCo body whose subtree is forbidden (e.g. the kitchen table's `table`).
    pub body: String,
    /// Names the latch `<object>_touched_<label>`.
    pub label: String,
    /// A contact counts when its distance (negative = penetration) is at most this.
    pub max_distance_m: f64,
}

/// The staged kinds' `checker.params`. The fields that may be left out are structural (no optional stages, no pour
/// counters, …; `order` is `ordered`); every threshold is in the atoms, which have no defaults.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StagedParams {
    #[serde(default)]
    pub order: OrderMode,
    /// Also sample after every physics substep (not only at control steps).
    #[serde(default)]
    pub sample_substeps: bool,
    #[serde(default)]
    pub forbidden_contacts: Vec<ForbiddenContactParams>,
    pub stages: Vec<StageParams>,
    /// Reported but not counted toward K nor required for success.
    #[serde(default)]
    pub optional_stages: Vec<StageParams>,
    /// Checks on the final state, all required for success.
    #[serde(default)]
    pub terminal: Vec<StageParams>,
    #[serde(default)]
    pub bindings: Vec<BindingParams>,
    #[serde(default)]
    pub pour_counters: Vec<PourCounterParams>,
    #[serde(default)]
    pub failures: Vec<FailureMonitorParams>,
}


#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn joint_and_any_atoms_parse() {
        let p: StagedParams = serde_json::from_value(json!({
            "stages": [{"name": "01", "all": [{"any": [
                {"joint": {"name": "d_latch_joint", "min": 1.1, "abs": true}},
                {"joint": {"name": "d_hinge", "min": 0.05}}]}], "contact_body": "d_latch"}]
        }))
        .unwrap();
        let AtomSpec::Any(inner) = &p.stages[0].all[0] else { panic!("not an any atom") };
        assert!(matches!(&inner[0], AtomSpec::Joint { min: Some(m), max: None, abs: true, .. } if *m == 1.1));
        assert!(matches!(&inner[1], AtomSpec::Joint { abs: false, .. }));
    }

    #[test]
    fn params_parse_from_manifest_json() {
        let p: StagedParams = serde_json::from_value(json!({
            "order": "strict",
            "stages": [{"name": "01", "all": [{"bddl": ["on", "a", "b"]}, {"released": "a"}], "contact_body": "x"},
                       {"name": "02", "all": [{"not": {"drawer_open": {"site": "s", "min_displacement_m": 0.1}}}]}],
            "terminal": [{"name": "t", "all": [{"near": {"object": "a", "anchor": "c", "xy_max_m": 0.3, "dz_range_m": [0.1, 0.3]}}]}]
        }))
        .unwrap();
        assert_eq!(p.order, OrderMode::Strict);
        assert_eq!(p.stages.len(), 2);
        assert!(matches!(p.stages[1].all[0], AtomSpec::Not(_)));
        assert!(!p.sample_substeps && p.forbidden_contacts.is_empty(), "both default off");
    }

    #[test]
    fn guard_rate_and_release_atom_parse_from_manifest_json() {
        let p: StagedParams = serde_json::from_value(json!({
            "order": "strict",
            "sample_substeps": true,
            "forbidden_contacts": [{"objects": ["a", "b"], "body": "table", "label": "tabletop", "max_distance_m": 0.001}],
            "stages": [{"name": "01", "all": [{"released_and_clear": {"object": "a", "min_distance_m": 0.055}}]}]
        }))
        .unwrap();
        assert!(p.sample_substeps);
        assert_eq!(p.forbidden_contacts[0].objects, ["a", "b"]);
        assert!(matches!(&p.stages[0].all[0], AtomSpec::ReleasedAndClear { object, min_distance_m } if object == "a" && *min_distance_m == 0.055));
    }
}
