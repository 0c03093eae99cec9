//! openpi's wire encoding: msgpack, with numpy arrays as maps `{b"__ndarray__": True, b"data": <bin>,
//! b"dtype": <str>, b"shape": [..]}` and numpy scalars as `{b"__npgeneric__": True, b"data": <item>,
//! b"dtype": <str>}` (openpi_client/msgpack_numpy.py, 0.1.2). The marker keys are msgpack *binary*, the
//! dtype a msgpack *string* such as `"<f4"` or `"|u1"`; Python's `msgpack.Packer` writes `bytes` as bin and
//! `str` as str, floats as float64, ints in their shortest form, and keeps dict order, and so does this
//! codec, so that a request packs to the same bytes as openpi's own client packs it.
use rmpv::Value;

use crate::PolicyError;

/// Element types this client sends or accepts (little-endian or byte-sized only: numpy on every
/// platform openpi serves from writes `<`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dtype {
    U8,
    I32,
    I64,
    F32,
    F64,
    Bool,
}

impl Dtype {
    /// numpy's `dtype.str`.
    pub fn numpy_str(self) -> &'static str {
        match self {
            Dtype::U8 => "|u1",
            Dtype::I32 => "<i4",
            Dtype::I64 => "<i8",
            Dtype::F32 => "<f4",
            Dtype::F64 => "<f8",
            Dtype::Bool => "|b1",
        }
    }

    pub fn from_numpy_str(s: &str) -> Option<Self> {
        Some(match s {
            "|u1" | "<u1" => Dtype::U8,
            "<i4" => Dtype::I32,
            "<i8" => Dtype::I64,
            "<f4" => Dtype::F32,
            "<f8" => Dtype::F64,
            "|b1" | "<b1" => Dtype::Bool,
            _ => return None,
        })
    }

    pub fn item_size(self) -> usize {
        match self {
            Dtype::U8 | Dtype::Bool => 1,
            Dtype::I32 | Dtype::F32 => 4,
            Dtype::I64 | Dtype::F64 => 8,
        }
    }
}

/// A C-ordered numpy array: its raw little-endian bytes, checked against dtype and shape.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    pub data: Vec<u8>,
}

impl NdArray {
    /// `data.len()` must be `product(shape) · item size`.
    pub fn new(dtype: Dtype, shape: Vec<usize>, data: Vec<u8>) -> Result<Self, PolicyError> {
        let count = shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
        match count.and_then(|n| n.checked_mul(dtype.item_size())) {
            Some(bytes) if bytes == data.len() => Ok(Self { dtype, shape, data }),
            _ => Err(PolicyError::Protocol(format!(
                "an array of dtype {} and shape {shape:?} cannot hold {} bytes",
                dtype.numpy_str(),
                data.len()
            ))),
        }
    }

    pub fn from_u8(shape: Vec<usize>, data: Vec<u8>) -> Result<Self, PolicyError> {
        Self::new(Dtype::U8, shape, data)
    }

    pub fn from_f64(shape: Vec<usize>, values: &[f64]) -> Result<Self, PolicyError> {
        Self::new(Dtype::F64, shape, values.iter().flat_map(|v| v.to_le_bytes()).collect())
    }

    pub fn from_f32(shape: Vec<usize>, values: &[f32]) -> Result<Self, PolicyError> {
        Self::new(Dtype::F32, shape, values.iter().flat_map(|v| v.to_le_bytes()).collect())
    }

    /// The elements widened to f64 (floats and integers; booleans as 0/1).
    pub fn to_f64(&self) -> Vec<f64> {
        let chunks = self.data.chunks_exact(self.dtype.item_size());
        let le4 = |c: &[u8]| [c[0], c[1], c[2], c[3]];
        let le8 = |c: &[u8]| [c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]];
        match self.dtype {
            Dtype::U8 | Dtype::Bool => chunks.map(|c| f64::from(c[0])).collect(),
            Dtype::I32 => chunks.map(|c| f64::from(i32::from_le_bytes(le4(c)))).collect(),
            Dtype::I64 => chunks.map(|c| i64::from_le_bytes(le8(c)) as f64).collect(),
            Dtype::F32 => chunks.map(|c| f64::from(f32::from_le_bytes(le4(c)))).collect(),
            Dtype::F64 => chunks.map(|c| f64::from_le_bytes(le8(c))).collect(),
        }
    }

    /// The map openpi's `pack_array` writes, keys in its order.
    pub fn to_value(&self) -> Value {
        Value::Map(vec![
            (Value::Binary(b"__ndarray__".to_vec()), Value::Boolean(true)),
            (Value::Binary(b"data".to_vec()), Value::Binary(self.data.clone())),
            (Value::Binary(b"dtype".to_vec()), Value::from(self.dtype.numpy_str())),
            (Value::Binary(b"shape".to_vec()), Value::Array(self.shape.iter().map(|&d| Value::from(d as u64)).collect())),
        ])
    }

    /// The array of an `__ndarray__` map; `None` when `value` is no such map. Keys are matched as
    /// binary (openpi) or string (other msgpack-numpy writers).
    pub fn from_value(value: &Value) -> Result<Option<Self>, PolicyError> {
        let Value::Map(entries) = value else { return Ok(None) };
        if map_get(entries, "__ndarray__").is_none() {
            return Ok(None);
        }
        let bad = |what: &str| PolicyError::Protocol(format!("an __ndarray__ map {what}"));
        let data = match map_get(entries, "data") {
            Some(Value::Binary(b)) => b.clone(),
            _ => return Err(bad("has no binary data")),
        };
        let dtype_str = match map_get(entries, "dtype") {
            Some(Value::String(s)) => s.as_str().unwrap_or_default().to_string(),
            Some(Value::Binary(b)) => String::from_utf8_lossy(b).into_owned(),
            _ => return Err(bad("has no dtype")),
        };
        let dtype = Dtype::from_numpy_str(&dtype_str).ok_or_else(|| bad(&format!("has the unsupported dtype {dtype_str:?}")))?;
        let shape = match map_get(entries, "shape") {
            Some(Value::Array(dims)) => dims
                .iter()
                .map(|d| d.as_u64().and_then(|d| usize::try_from(d).ok()).ok_or_else(|| bad("has a non-integer dimension")))
                .collect::<Result<Vec<_>, _>>()?,
            _ => return Err(bad("has no shape")),
        };
        Self::new(dtype, shape, data).map(Some)
    }
}

/// The value under `key` of a msgpack map whose keys are binary or string.
pub fn map_get<'a>(entries: &'a [(Value, Value)], key: &str) -> Option<&'a Value> {
    entries.iter().find(|(k, _)| key_str(k) == Some(key)).map(|(_, v)| v)
}

/// A map key as text: msgpack string or binary.
pub fn key_str(k: &Value) -> Option<&str> {
    match k {
        Value::String(s) => s.as_str(),
        Value::Binary(b) => std::str::from_utf8(b).ok(),
        _ => None,
    }
}

/// One message: msgpack of `value`.
pub fn pack(value: &Value) -> Vec<u8> {
    let mut out = Vec::new();
    // Writing into a Vec cannot fail.
    let _ = rmpv::encode::write_value(&mut out, value);
    out
}

/// Decodes one whole message; trailing bytes are a protocol error. Nesting depth is bounded by rmpv.
pub fn unpack(bytes: &[u8]) -> Result<Value, PolicyError> {
    let mut cursor = bytes;
    let value = rmpv::decode::read_value(&mut cursor).map_err(|e| PolicyError::Protocol(format!("not msgpack: {e}")))?;
    if !cursor.is_empty() {
        return Err(PolicyError::Protocol(format!("{} bytes after the msgpack value", cursor.len())));
    }
    Ok(value)
}

/// A JSON view of a decoded value for records and logs: arrays become `{"dtype", "shape"}` (their data
/// left out), numpy scalars their value, binary other than arrays its length.
pub fn to_json(value: &Value) -> serde_json::Value {
    use serde_json::json;
    match value {
        Value::Nil => serde_json::Value::Null,
        Value::Boolean(b) => json!(b),
        Value::Integer(i) => i.as_i64().map(|v| json!(v)).or_else(|| i.as_u64().map(|v| json!(v))).unwrap_or(serde_json::Value::Null),
        Value::F32(f) => json!(f),
        Value::F64(f) => json!(f),
        Value::String(s) => json!(s.as_str().unwrap_or_default()),
        Value::Binary(b) => json!({"binary_bytes": b.len()}),
        Value::Array(items) => serde_json::Value::Array(items.iter().map(to_json).collect()),
        Value::Map(entries) => {
            if let Ok(Some(a)) = NdArray::from_value(value) {
                return json!({"dtype": a.dtype.numpy_str(), "shape": a.shape});
            }
            if map_get(entries, "__npgeneric__").is_some() {
                return map_get(entries, "data").map(to_json).unwrap_or(serde_json::Value::Null);
            }
            let mut out = serde_json::Map::new();
            for (k, v) in entries {
                let key = key_str(k).map(str::to_string).unwrap_or_else(|| k.to_string());
                out.insert(key, to_json(v));
            }
            serde_json::Value::Object(out)
        }
        Value::Ext(tag, data) => json!({"ext": tag, "bytes": data.len()}),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_array_round_trips_through_its_map() {
        let a = NdArray::from_f32(vec![2, 3], &[1.0, -2.5, 3.0, 0.0, f32::MIN_POSITIVE, 7.0]).unwrap();
        let back = NdArray::from_value(&unpack(&pack(&a.to_value())).unwrap()).unwrap().unwrap();
        assert_eq!(back, a);
        assert_eq!(back.to_f64()[1], -2.5);
    }

    #[test]
    fn a_shape_that_does_not_match_the_data_is_refused() {
        assert!(NdArray::from_u8(vec![2, 2], vec![0; 3]).is_err());
        assert!(NdArray::from_u8(vec![usize::MAX, 2], vec![]).is_err());
    }

    #[test]
    fn trailing_bytes_are_a_protocol_error() {
        let mut bytes = pack(&Value::from(1));
        bytes.push(0xc0);
        assert!(unpack(&bytes).is_err());
    }
}
