//! LIBERO initial-state files (`.pruned_init`), read without Python.
//!
//! A `.pruned_init` is a `torch.save` zip archive whose `archive/data.pkl` is a protocol-2 pickle of one
//! float64 NumPy array built through `numpy.core.multiarray._reconstruct` (shape `(50, 1 + nq + nv)`, rows
//! `[time, qpos, qvel]`, port notes §6.1). This module runs a tiny pickle machine that understands exactly
//! the opcodes such a pickle uses and rejects everything else with `SimError::Input`; it never imports or
//! calls anything, so a hostile file cannot execute code.
use std::io::Read;
use std::path::Path;

use crate::SimError;

/// The 2-D float64 array of an init-state file, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct InitStates {
    rows: usize,
    cols: usize,
    values: Vec<f64>,
}

impl InitStates {
    /// Reads a `.pruned_init` / `.init` torch zip archive.
    pub fn read(path: &Path) -> Result<Self, SimError> {
        let file = std::fs::File::open(path)
            .map_err(|e| SimError::Input(format!("cannot open init-state file {}: {e}", path.display())))?;
        let mut archive = zip::ZipArchive::new(file)
            .map_err(|e| SimError::Input(format!("{} is not a torch zip archive: {e}", path.display())))?;
        let name = archive
            .file_names()
            .find(|n| n.ends_with("data.pkl"))
            .map(str::to_owned)
            .ok_or_else(|| SimError::Input(format!("{} holds no data.pkl", path.display())))?;
        let mut entry = archive
            .by_name(&name)
            .map_err(|e| SimError::Input(format!("{}: cannot read {name}: {e}", path.display())))?;
        let mut bytes = Vec::with_capacity(entry.size() as usize);
        entry.read_to_end(&mut bytes)?;
        Self::from_pickle(&bytes).map_err(|e| match e {
            SimError::Input(msg) => SimError::Input(format!("{}: {msg}", path.display())),
            other => other,
        })
    }

    /// Decodes the pickle of a NumPy float64 2-D array (`data.pkl`).
    pub fn from_pickle(bytes: &[u8]) -> Result<Self, SimError> {
        let value = Machine::new(bytes).run()?;
        ndarray_from_value(&value)
    }

    /// Number of states (rows).
    pub fn len(&self) -> usize {
        self.rows
    }

    pub fn is_empty(&self) -> bool {
        self.rows == 0
    }

    /// Length of one state row (`1 + nq + nv`).
    pub fn row_len(&self) -> usize {
        self.cols
    }

    /// State `index` as `[time, qpos…, qvel…]`.
    pub fn row(&self, index: usize) -> Option<&[f64]> {
        (index < self.rows).then(|| &self.values[index * self.cols..(index + 1) * self.cols])
    }

    /// State `index`, or a clear error naming the valid range.
    pub fn get(&self, index: usize) -> Result<&[f64], SimError> {
        self.row(index).ok_or_else(|| {
            SimError::Input(format!("init-state index {index} out of range (file holds {} states)", self.rows))
        })
    }
}

/// Values of the restricted pickle machine.
#[derive(Debug, Clone)]
enum Value {
    None,
    Bool(bool),
    Int(i64),
    Str(String),
    Bytes(Vec<u8>),
    Tuple(Vec<Value>),
    /// `module.name` reference from GLOBAL; never resolved or called.
    Global(String, String),
    /// `callable(*args)` recorded symbolically by REDUCE.
    Reduce(Box<Value>, Vec<Value>),
    /// `obj.__setstate__(state)` recorded symbolically by BUILD.
    Build(Box<Value>, Box<Value>),
    Mark,
}

fn bad(msg: impl Into<String>) -> SimError {
    SimError::Input(format!("unsupported init-state pickle: {}", msg.into()))
}

struct Machine<'a> {
    bytes: &'a [u8],
    pos: usize,
    stack: Vec<Value>,
    memo: Vec<Option<Value>>,
}

impl<'a> Machine<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        Self { bytes, pos: 0, stack: Vec::new(), memo: Vec::new() }
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], SimError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.bytes.len()).ok_or_else(|| bad("truncated"))?;
        let s = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn u8(&mut self) -> Result<u8, SimError> {
        Ok(self.take(1)?[0])
    }

    fn u32le(&mut self) -> Result<u32, SimError> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn line(&mut self) -> Result<String, SimError> {
        let rest = &self.bytes[self.pos..];
        let nl = rest.iter().position(|&c| c == b'\n').ok_or_else(|| bad("unterminated GLOBAL"))?;
        let s = std::str::from_utf8(&rest[..nl]).map_err(|_| bad("non-UTF-8 GLOBAL"))?.to_owned();
        self.pos += nl + 1;
        Ok(s)
    }

    fn pop(&mut self) -> Result<Value, SimError> {
        self.stack.pop().ok_or_else(|| bad("stack underflow"))
    }

    fn pop_to_mark(&mut self) -> Result<Vec<Value>, SimError> {
        let mark = self
            .stack
            .iter()
            .rposition(|v| matches!(v, Value::Mark))
            .ok_or_else(|| bad("missing MARK"))?;
        let items = self.stack.split_off(mark + 1);
        self.stack.pop();
        Ok(items)
    }

    fn memo_put(&mut self, idx: usize) -> Result<(), SimError> {
        let top = self.stack.last().cloned().ok_or_else(|| bad("PUT on empty stack"))?;
        if idx > 1_000_000 {
            return Err(bad("memo index too large"));
        }
        if self.memo.len() <= idx {
            self.memo.resize(idx + 1, None);
        }
        self.memo[idx] = Some(top);
        Ok(())
    }

    fn memo_get(&mut self, idx: usize) -> Result<(), SimError> {
        let v = self.memo.get(idx).cloned().flatten().ok_or_else(|| bad("GET of unset memo"))?;
        self.stack.push(v);
        Ok(())
    }

    fn run(mut self) -> Result<Value, SimError> {
        loop {
            let op = self.u8()?;
            match op {
                0x80 => {
                    let proto = self.u8()?;
                    if proto > 4 {
                        return Err(bad(format!("pickle protocol {proto}")));
                    }
                }
                0x95 => {
                    self.take(8)?; // FRAME length (protocol 4); frames are transparent here
                }
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    self.stack.push(Value::Global(module, name));
                }
                b'q' => {
                    let i = self.u8()? as usize;
                    self.memo_put(i)?;
                }
                b'r' => {
                    let i = self.u32le()? as usize;
                    self.memo_put(i)?;
                }
                0x94 => {
                    let i = self.memo.len();
                    self.memo_put(i)?;
                }
                b'h' => {
                    let i = self.u8()? as usize;
                    self.memo_get(i)?;
                }
                b'j' => {
                    let i = self.u32le()? as usize;
                    self.memo_get(i)?;
                }
                b'K' => {
                    let v = self.u8()? as i64;
                    self.stack.push(Value::Int(v));
                }
                b'M' => {
                    let b = self.take(2)?;
                    self.stack.push(Value::Int(u16::from_le_bytes([b[0], b[1]]) as i64));
                }
                b'J' => {
                    let v = self.u32le()? as i32 as i64;
                    self.stack.push(Value::Int(v));
                }
                b'N' => self.stack.push(Value::None),
                0x88 => self.stack.push(Value::Bool(true)),
                0x89 => self.stack.push(Value::Bool(false)),
                b'(' => self.stack.push(Value::Mark),
                b')' => self.stack.push(Value::Tuple(Vec::new())),
                b't' => {
                    let items = self.pop_to_mark()?;
                    self.stack.push(Value::Tuple(items));
                }
                0x85 | 0x86 | 0x87 => {
                    let n = (op - 0x84) as usize;
                    if self.stack.len() < n {
                        return Err(bad("stack underflow in TUPLEn"));
                    }
                    let items = self.stack.split_off(self.stack.len() - n);
                    self.stack.push(Value::Tuple(items));
                }
                b'X' => {
                    let n = self.u32le()? as usize;
                    let s = std::str::from_utf8(self.take(n)?).map_err(|_| bad("invalid UTF-8 string"))?;
                    self.stack.push(Value::Str(s.to_owned()));
                }
                0x8c => {
                    let n = self.u8()? as usize;
                    let s = std::str::from_utf8(self.take(n)?).map_err(|_| bad("invalid UTF-8 string"))?;
                    self.stack.push(Value::Str(s.to_owned()));
                }
                b'B' => {
                    let n = self.u32le()? as usize;
                    let b = self.take(n)?.to_vec();
                    self.stack.push(Value::Bytes(b));
                }
                b'C' => {
                    let n = self.u8()? as usize;
                    let b = self.take(n)?.to_vec();
                    self.stack.push(Value::Bytes(b));
                }
                b'R' => {
                    let args = self.pop()?;
                    let callable = self.pop()?;
                    let Value::Tuple(args) = args else { return Err(bad("REDUCE arguments are not a tuple")) };
                    self.stack.push(Value::Reduce(Box::new(callable), args));
                }
                b'b' => {
                    let state = self.pop()?;
                    let obj = self.pop()?;
                    self.stack.push(Value::Build(Box::new(obj), Box::new(state)));
                }
                b'.' => return self.pop(),
                other => return Err(bad(format!("opcode 0x{other:02x} at byte {}", self.pos - 1))),
            }
        }
    }
}

fn is_global(v: &Value, module: &str, name: &str) -> bool {
    matches!(v, Value::Global(m, n) if m == module && n == name)
}

/// Raw array bytes: either a bytes object or `_codecs.encode(str, 'latin1')` (how NumPy pickles bytes
/// under protocol 2 for Python-2 compatibility).
fn raw_bytes(v: &Value) -> Result<Vec<u8>, SimError> {
    match v {
        Value::Bytes(b) => Ok(b.clone()),
        Value::Reduce(f, args) if is_global(f, "_codecs", "encode") => match args.as_slice() {
            [Value::Str(s), Value::Str(enc)] if enc == "latin1" || enc == "latin-1" => s
                .chars()
                .map(|c| u8::try_from(c as u32).map_err(|_| bad("non-latin1 character in array data")))
                .collect(),
            _ => Err(bad("unexpected _codecs.encode arguments")),
        },
        _ => Err(bad("array data is neither bytes nor latin1-encoded text")),
    }
}

/// Accepts `dtype('f8')` (little-endian) only.
fn check_dtype(v: &Value) -> Result<(), SimError> {
    let Value::Build(obj, state) = v else { return Err(bad("dtype without state")) };
    let Value::Reduce(f, args) = obj.as_ref() else { return Err(bad("dtype is not constructed")) };
    if !is_global(f, "numpy", "dtype") {
        return Err(bad("array dtype is not numpy.dtype"));
    }
    match args.first() {
        Some(Value::Str(s)) if s == "f8" => {}
        Some(Value::Str(s)) => return Err(bad(format!("dtype {s} (expected f8 = float64)"))),
        _ => return Err(bad("dtype name missing")),
    }
    let Value::Tuple(st) = state.as_ref() else { return Err(bad("dtype state is not a tuple")) };
    match st.get(1) {
        Some(Value::Str(order)) if order == "<" || order == "=" || order == "|" => Ok(()),
        Some(Value::Str(order)) => Err(bad(format!("byte order {order:?} (expected little-endian)"))),
        _ => Err(bad("dtype byte order missing")),
    }
}

fn ndarray_from_value(v: &Value) -> Result<InitStates, SimError> {
    let Value::Build(obj, state) = v else { return Err(bad("top-level object is not a built ndarray")) };
    let Value::Reduce(f, _) = obj.as_ref() else { return Err(bad("top-level object is not reconstructed")) };
    if !(is_global(f, "numpy.core.multiarray", "_reconstruct") || is_global(f, "numpy._core.multiarray", "_reconstruct")) {
        return Err(bad("top-level object is not numpy.core.multiarray._reconstruct"));
    }
    let Value::Tuple(st) = state.as_ref() else { return Err(bad("ndarray state is not a tuple")) };
    let [_version, Value::Tuple(shape), dtype, Value::Bool(fortran), data] = st.as_slice() else {
        return Err(bad("ndarray state is not (version, shape, dtype, fortran, data)"));
    };
    check_dtype(dtype)?;
    let dims: Vec<usize> = shape
        .iter()
        .map(|d| match d {
            Value::Int(n) if *n >= 0 => Ok(*n as usize),
            _ => Err(bad("non-integer array dimension")),
        })
        .collect::<Result<_, _>>()?;
    let [rows, cols] = dims.as_slice() else {
        return Err(bad(format!("array has {} dimensions (expected 2)", dims.len())));
    };
    let (rows, cols) = (*rows, *cols);
    let bytes = raw_bytes(data)?;
    let n = rows.checked_mul(cols).ok_or_else(|| bad("array too large"))?;
    if bytes.len() != n * 8 {
        return Err(bad(format!("array data holds {} bytes, shape ({rows}, {cols}) needs {}", bytes.len(), n * 8)));
    }
    let flat: Vec<f64> =
        bytes.chunks_exact(8).map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]])).collect();
    let values = if *fortran {
        let mut v = vec![0.0; n];
        for r in 0..rows {
            for c in 0..cols {
                v[r * cols + c] = flat[c * rows + r];
            }
        }
        v
    } else {
        flat
    };
    if values.iter().any(|x| !x.is_finite()) {
        return Err(SimError::Input("init-state array holds non-finite values".into()));
    }
    Ok(InitStates { rows, cols, values })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_arbitrary_callables_and_garbage() {
        // GLOBAL os.system + REDUCE: must be refused (symbolic), never executed.
        let evil = b"\x80\x02cos\nsystem\nq\x00X\x02\x00\x00\x00lsq\x01\x85q\x02Rq\x03.";
        assert!(matches!(InitStates::from_pickle(evil), Err(SimError::Input(_))));
        assert!(matches!(InitStates::from_pickle(b"\x80\x02\xff"), Err(SimError::Input(_))));
        assert!(matches!(InitStates::from_pickle(b""), Err(SimError::Input(_))));
    }
}
