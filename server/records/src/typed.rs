//! How the run directory's records are typed without losing a byte of what they hold. A record struct (declared
//! with `record!`) has one `Option` field per key its readers use and a `rest` map. Reading fills a field when
//! the key's value has the field's type and leaves everything else in `rest` as it was: unknown keys, and known
//! keys whose value is null (for a plain `Option<T>` field) or of another type. Writing puts the fields back over
//! `rest`. So a record read and written back is byte-identical (the files are written with sorted keys), readers
//! see what `value["key"].as_…()` used to give them, and an ill-typed value is neither an error nor lost.
//!
//! A key a writer sets to null is an `Option<Option<T>>` field: `Some(None)` is the null, `None` its absence.
use std::path::PathBuf;

use serde::Serialize;
use serde::de::DeserializeOwned;
use serde_json::{Map, Value};

/// Why a record file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("cannot read {}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Not JSON, or JSON that is not an object.
    #[error("{} is not a JSON object: {source}", path.display())]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
}

/// Takes `key` out of `rest` when its value reads as `T`. The value leaves `rest` only when `T` writes it back
/// the same way: an integer read into an `f64` field stays in `rest` (written back `30`, not `30.0`).
pub(crate) fn take<T: DeserializeOwned + Serialize>(rest: &mut Map<String, Value>, key: &str) -> Option<T> {
    let raw = rest.get(key)?;
    let typed = T::deserialize(raw).ok()?;
    if serde_json::to_value(&typed).is_ok_and(|v| v == *raw) {
        rest.remove(key);
    }
    Some(typed)
}

/// Puts a field into `out` (a copy of `rest`) for writing. `out` already holding the same value in another
/// spelling (what [`take`] left there) keeps it as read.
pub(crate) fn put<T: DeserializeOwned + Serialize + PartialEq>(
    out: &mut Map<String, Value>,
    key: &str,
    value: &Option<T>,
) -> Result<(), serde_json::Error> {
    let Some(value) = value else { return Ok(()) };
    if out.get(key).and_then(|raw| T::deserialize(raw).ok()).is_some_and(|as_read| as_read == *value) {
        return Ok(());
    }
    out.insert(key.to_owned(), serde_json::to_value(value)?);
    Ok(())
}

/// Declares a record struct: each field an `Option` named as its JSON key (or `pub field as "key": …` for a key
/// that is no Rust name), plus `rest`, with the (de)serialization of the module docs.
macro_rules! record {
    (@key $field:ident $key:literal) => { $key };
    (@key $field:ident) => { stringify!($field) };
    (
        $(#[$meta:meta])*
        pub struct $name:ident {
            $( $(#[$field_meta:meta])* pub $field:ident $(as $key:literal)? : Option<$ty:ty> ),* $(,)?
        }
    ) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Default, PartialEq)]
        pub struct $name {
            $( $(#[$field_meta])* pub $field: Option<$ty>, )*
            /// Every other key as read, and known keys whose value is null or not of the field's type.
            pub rest: serde_json::Map<String, serde_json::Value>,
        }

        impl<'de> serde::Deserialize<'de> for $name {
            fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
                let mut rest = <serde_json::Map<String, serde_json::Value> as serde::Deserialize>::deserialize(deserializer)?;
                Ok(Self { $( $field: $crate::typed::take(&mut rest, $crate::typed::record!(@key $field $($key)?)), )* rest })
            }
        }

        impl serde::Serialize for $name {
            fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
                let mut out = self.rest.clone();
                $( $crate::typed::put(&mut out, $crate::typed::record!(@key $field $($key)?), &self.$field)
                    .map_err(<S::Error as serde::ser::Error>::custom)?; )*
                serde::Serialize::serialize(&out, serializer)
            }
        }

        impl $name {
            /// Reads the record from JSON (an object; anything else is an error).
            pub fn from_value(value: serde_json::Value) -> Result<Self, serde_json::Error> {
                serde_json::from_value(value)
            }

            /// The record as JSON, exactly as read where it was read (null only if it cannot be serialized,
            /// which the types of its fields rule out).
            pub fn to_value(&self) -> serde_json::Value {
                serde_json::to_value(self).unwrap_or(serde_json::Value::Null)
            }
        }

        impl std::fmt::Display for $name {
            /// Compact JSON with sorted keys, as the logs write records.
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str(&$crate::json::compact_sorted(&self.to_value()))
            }
        }
    };
}
pub(crate) use record;

/// Reads a JSON record file: `Ok(None)` when there is none, an error when it cannot be read or is not an object.
pub fn read_record<T: DeserializeOwned>(path: &std::path::Path) -> Result<Option<T>, RecordError> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(source) => return Err(RecordError::Io { path: path.to_owned(), source }),
    };
    serde_json::from_str(&text).map(Some).map_err(|source| RecordError::Json { path: path.to_owned(), source })
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    crate::typed::record! {
        /// A record of every kind of field.
        pub struct Sample {
            pub name: Option<String>,
            pub seconds: Option<f64>,
            pub count: Option<u64>,
            pub maybe: Option<Option<String>>,
            pub kind as "type": Option<String>,
            pub inner: Option<Inner>,
        }
    }

    crate::typed::record! {
        pub struct Inner {
            pub flag: Option<bool>,
        }
    }

    fn round_trip(v: serde_json::Value) -> (Sample, serde_json::Value) {
        let s = Sample::from_value(v).unwrap();
        let back = s.to_value();
        (s, back)
    }

    #[test]
    fn typed_fields_are_filled_and_everything_else_is_kept() {
        let v = json!({"name": "a", "seconds": 1.5, "count": 3, "maybe": null, "type": "t", "inner": {"flag": true, "x": 1}, "extra": [1]});
        let (s, back) = round_trip(v.clone());
        assert_eq!((s.name.as_deref(), s.seconds, s.count, s.maybe.clone(), s.kind.as_deref()), (Some("a"), Some(1.5), Some(3), Some(None), Some("t")));
        assert_eq!(s.inner.as_ref().and_then(|i| i.flag), Some(true));
        assert_eq!(s.rest.keys().collect::<Vec<_>>(), ["extra"]);
        assert_eq!(back, v);
    }

    #[test]
    fn other_spellings_nulls_and_ill_typed_values_survive_a_round_trip() {
        let v = json!({"seconds": 30, "count": 2.0, "name": null, "maybe": 7, "inner": [1]});
        let (s, back) = round_trip(v.clone());
        assert_eq!(s.seconds, Some(30.0), "an integer reads as seconds, as as_f64 did");
        assert_eq!((s.count, s.name.as_deref(), s.maybe.clone(), s.inner.clone()), (None, None, None, None), "as as_u64/as_str did");
        assert_eq!(back, v);
        assert_eq!(serde_json::to_string(&s).unwrap(), serde_json::to_string(&v).unwrap(), "30 stays 30, not 30.0");
    }

    #[test]
    fn a_changed_field_is_written_over_what_was_read() {
        let (mut s, _) = round_trip(json!({"seconds": 30, "maybe": "x"}));
        s.seconds = Some(31.5);
        s.maybe = Some(None);
        assert_eq!(s.to_value(), json!({"seconds": 31.5, "maybe": null}));
    }

    #[test]
    fn a_record_is_an_object() {
        assert!(Sample::from_value(json!([1, 2])).is_err());
        assert!(Sample::from_value(json!("x")).is_err());
        assert_eq!(Sample::from_value(json!({})).unwrap(), Sample::default());
        assert!(Inner::from_value(json!(null)).is_err());
    }

    #[test]
    fn reading_a_file_says_what_went_wrong() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.json");
        assert!(super::read_record::<Sample>(&path).unwrap().is_none(), "no file, no record");
        std::fs::write(&path, "{\"name\": \"a\"").unwrap();
        let e = super::read_record::<Sample>(&path).unwrap_err().to_string();
        assert!(e.starts_with(&format!("{} is not a JSON object", path.display())), "{e}");
        std::fs::write(&path, "{\"name\": \"a\"}").unwrap();
        assert_eq!(super::read_record::<Sample>(&path).unwrap().unwrap().name.as_deref(), Some("a"));
    }
}
