//! Stage types for the paper's stage-level diagnosis (Table 4: Object Manipulation / Mechanism Interaction), declared
//! per stage in the catalog's checker parameters (`tasks/manifest.json`, `tasks/pool.json`):
//! `{"name": "01_Open_Top_Drawer", "type": "mechanism_interaction", "all": […]}`. Evaluators whose stages are names
//! only (T19, T20, T29, T30, the coffee machine, the seesaws) take `{"name", "type"}` objects as well as bare names.
//! The type is a label for reports; no evaluator judges by it.
use serde::{Deserialize, Deserializer};
use serde_json::Value;

pub use libero_metrics::StageType;

/// A stage listed by name, with or without its declared type.
#[derive(Deserialize)]
#[serde(untagged)]
enum NamedStage {
    Bare(String),
    Typed {
        name: String,
        #[serde(rename = "type")]
        #[allow(dead_code)] // read by `declared_stage_types` from the JSON, not here
        stage_type: StageType,
    },
}

/// `deserialize_with` for a name-only stage list: bare names or `{"name", "type"}` objects, as names.
pub fn stage_names<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<String>, D::Error> {
    let stages = Vec::<NamedStage>::deserialize(d)?;
    Ok(stages
        .into_iter()
        .map(|s| match s {
            NamedStage::Bare(name) | NamedStage::Typed { name, .. } => name,
        })
        .collect())
}

/// A stage object of a checker's parameters as far as its type goes (values kept as JSON, so that a declared type
/// of any shape, `null` included, is refused with the stage's name).
#[derive(Deserialize, Default)]
struct DeclaredStage {
    #[serde(default)]
    name: Value,
    #[serde(rename = "type", default, deserialize_with = "present")]
    stage_type: Option<Value>,
}

/// A key that is there, whatever its value (`null` too): `Some`.
fn present<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Value>, D::Error> {
    Value::deserialize(d).map(Some)
}

/// Every stage of a checker's parameters (`stages`, then `optional_stages`) with its declared type, in order;
/// `None` where a stage declares none. An unknown type is an error naming the stage.
pub fn declared_stage_types(params: &Value) -> Result<Vec<(String, Option<StageType>)>, String> {
    let mut out = Vec::new();
    for key in ["stages", "optional_stages"] {
        for stage in params.get(key).and_then(Value::as_array).into_iter().flatten() {
            let (name, declared) = match stage {
                Value::String(name) => (name.clone(), None),
                Value::Object(_) => {
                    let d = DeclaredStage::deserialize(stage).unwrap_or_default();
                    (d.name.as_str().unwrap_or_default().to_owned(), d.stage_type)
                }
                _ => (String::new(), None),
            };
            let stage_type = declared
                .map(|t| serde_json::from_value::<StageType>(t.clone()).map_err(|e| format!("stage {name:?}: type {t}: {e}")))
                .transpose()?;
            out.push((name, stage_type));
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;

    #[derive(Deserialize)]
    struct Params {
        #[serde(deserialize_with = "stage_names")]
        stages: Vec<String>,
    }

    #[test]
    fn name_only_stage_lists_take_bare_names_and_typed_objects() {
        let p: Params =
            serde_json::from_value(json!({"stages": ["01_A", {"name": "02_B", "type": "mechanism_interaction"}]})).unwrap();
        assert_eq!(p.stages, ["01_A", "02_B"]);
        assert!(serde_json::from_value::<Params>(json!({"stages": [{"name": "x", "type": "dance"}]})).is_err());
    }

    #[test]
    fn declared_types_follow_stage_order_and_reject_unknown_ones() {
        let params = json!({
            "stages": [{"name": "01", "type": "object_manipulation", "all": []}, "02"],
            "optional_stages": [{"name": "03", "type": "mechanism_interaction", "all": []}],
        });
        let got = declared_stage_types(&params).unwrap();
        assert_eq!(
            got,
            [
                ("01".to_owned(), Some(StageType::ObjectManipulation)),
                ("02".to_owned(), None),
                ("03".to_owned(), Some(StageType::MechanismInteraction))
            ]
        );
        let err = declared_stage_types(&json!({"stages": [{"name": "01", "type": "both"}]})).unwrap_err();
        assert!(err.contains("\"01\""), "{err}");
        assert!(declared_stage_types(&json!({})).unwrap().is_empty());
    }
}
