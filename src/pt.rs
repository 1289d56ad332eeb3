//! Reader for PyTorch `.pt` files that hold a single tensor: the motion clips
//! of Ingrid789/SkillMimic-V2 (`skillmimic/data/motions/`, loaded there with
//! `torch.load` in `skillmimic/utils/motion_data_handler.py`).
//!
//! # Container format
//!
//! `torch.save(tensor, path)` (the "new" zip serialisation, default since
//! torch 1.6) writes a zip archive whose entries are all *stored*
//! (uncompressed) and live under one directory, the *prefix*:
//!
//! * `<prefix>/data.pkl` — a pickle (protocol 2) that rebuilds the object;
//! * `<prefix>/data/<key>` — one entry per storage, the raw little-endian
//!   element bytes;
//! * `<prefix>/version` — the format version (`3` in our data).
//!
//! The prefix is usually `archive` but may be any stem (our clips contain e.g.
//! `006pickle_dribble2shot/`), so it is found by locating the entry named
//! `data.pkl` rather than assumed.
//!
//! For a bare tensor the pickle is essentially
//!
//! ```text
//! torch._utils._rebuild_tensor_v2(
//!     persistent_load(('storage', torch.FloatStorage, '0', 'cuda:0', numel)),
//!     storage_offset, (rows, cols), (stride0, stride1),
//!     False, collections.OrderedDict())
//! ```
//!
//! expressed with `GLOBAL` + `REDUCE` for the two calls and `BINPERSID` for
//! the storage reference. The tensor's element `(i, j)` is storage element
//! `storage_offset + i * stride0 + j * stride1`.
//!
//! # Why a hand-written pickle machine
//!
//! * `serde-pickle` cannot resolve torch's persistent ids (`BINPERSID`) nor
//!   evaluate `REDUCE` of `torch._utils._rebuild_tensor_v2`, which is exactly
//!   what a tensor pickle consists of.
//! * candle's `.pt` readers (`read_pth_tensor_info`, `PthTensors`, candle-core
//!   0.11, already a dependency) return the tensors of a dict (a state dict)
//!   and nothing for a bare `torch.save(tensor)`, which is what every clip
//!   is; only its lower-level pickle stack (`candle_core::pickle::Stack`)
//!   could be used, and that is unsafe on malformed or hostile files, and a
//!   clip file is user input. Tried on candle-core 0.11.1 with a scratch
//!   program (the stress cases of this module's tests, not kept in the
//!   repository): `_rebuild_tensor_v2` called with a 2-tuple panics in
//!   `rebuild_args` (an unchecked `Vec::remove`, reached from
//!   `Object::into_tensor_info`; a panic could be caught, the next two
//!   cannot); memo
//!   references copy the memoised object (`memo_get` clones), so a 286-byte
//!   pickle that re-memoises `(m, m)` 40 times asks for 2^40 objects and
//!   aborts on allocation failure; 200,000 nested `TUPLE1` (a 200 kB pickle)
//!   overflow the stack when the nested objects are dropped. Each of these
//!   aborts the whole stage instead of naming the bad file.
//!
//! The machine below implements only the opcodes `torch.save` emits at
//! protocol 2 (plus a few neighbours that cost nothing), never imports or
//! executes anything: the only "callables" are `_rebuild_tensor_v2` and
//! `collections.OrderedDict`; any other global called through `REDUCE` or
//! `NEWOBJ` becomes an opaque object, so the caller can report what the file
//! holds instead of a tensor. Every malformed stream (unknown opcode,
//! truncation, stack underflow, memo miss, ill-typed arguments) is an error,
//! never a panic.

use std::fmt;
use std::io::{Cursor, Read};
use std::path::Path;

/// Element type of a tensor, as named by the storage class in the pickle
/// (`torch.FloatStorage` → [`DType::F32`], and so on).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DType {
    /// `torch.FloatStorage`
    F32,
    /// `torch.DoubleStorage`
    F64,
    /// `torch.HalfStorage`
    F16,
    /// `torch.BFloat16Storage`
    BF16,
    /// `torch.LongStorage`
    I64,
    /// `torch.IntStorage`
    I32,
    /// `torch.ShortStorage`
    I16,
    /// `torch.CharStorage`
    I8,
    /// `torch.ByteStorage`
    U8,
    /// `torch.BoolStorage`
    Bool,
}

impl DType {
    /// Maps a storage class name in module `torch` to its dtype.
    pub fn from_storage_class(name: &str) -> Option<DType> {
        Some(match name {
            "FloatStorage" => DType::F32,
            "DoubleStorage" => DType::F64,
            "HalfStorage" => DType::F16,
            "BFloat16Storage" => DType::BF16,
            "LongStorage" => DType::I64,
            "IntStorage" => DType::I32,
            "ShortStorage" => DType::I16,
            "CharStorage" => DType::I8,
            "ByteStorage" => DType::U8,
            "BoolStorage" => DType::Bool,
            _ => return None,
        })
    }

    /// Name of the storage class (in module `torch`) that denotes this dtype.
    pub fn storage_class(self) -> &'static str {
        match self {
            DType::F32 => "FloatStorage",
            DType::F64 => "DoubleStorage",
            DType::F16 => "HalfStorage",
            DType::BF16 => "BFloat16Storage",
            DType::I64 => "LongStorage",
            DType::I32 => "IntStorage",
            DType::I16 => "ShortStorage",
            DType::I8 => "CharStorage",
            DType::U8 => "ByteStorage",
            DType::Bool => "BoolStorage",
        }
    }

    /// Size of one element in bytes, as laid out in the storage entry.
    pub fn element_size(self) -> usize {
        match self {
            DType::F64 | DType::I64 => 8,
            DType::F32 | DType::I32 => 4,
            DType::F16 | DType::BF16 | DType::I16 => 2,
            DType::I8 | DType::U8 | DType::Bool => 1,
        }
    }
}

impl fmt::Display for DType {
    /// Uses torch's dtype names (`float32`, `int64`, ...).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            DType::F32 => "float32",
            DType::F64 => "float64",
            DType::F16 => "float16",
            DType::BF16 => "bfloat16",
            DType::I64 => "int64",
            DType::I32 => "int32",
            DType::I16 => "int16",
            DType::I8 => "int8",
            DType::U8 => "uint8",
            DType::Bool => "bool",
        })
    }
}

/// Everything the pickle says about the tensor, without its data.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TensorInfo {
    /// Element type, from the storage class.
    pub dtype: DType,
    /// Tensor size per dimension.
    pub shape: Vec<usize>,
    /// Stride per dimension, in elements (same length as `shape`).
    pub stride: Vec<usize>,
    /// Index of the tensor's first element within the storage, in elements.
    pub storage_offset: usize,
    /// Storage key: the data lives in the entry `<prefix>/data/<key>`.
    pub storage_key: String,
    /// Number of elements in the storage as recorded in the pickle.
    pub storage_numel: usize,
    /// Device the tensor was saved from (e.g. `cuda:0`); informational only.
    pub location: String,
    /// Directory of the archive entries (e.g. `archive`); empty when the
    /// entries sit at the archive root.
    pub prefix: String,
}

impl TensorInfo {
    /// Number of tensor elements (product of the shape), `None` on overflow.
    pub fn numel(&self) -> Option<usize> {
        self.shape
            .iter()
            .try_fold(1usize, |acc, &d| acc.checked_mul(d))
    }

    /// Largest storage index the tensor addresses, `None` when the tensor
    /// is empty (some dimension is 0) or the computation overflows.
    pub fn max_storage_index(&self) -> Option<usize> {
        if self.shape.contains(&0) {
            return None;
        }
        self.shape
            .iter()
            .zip(&self.stride)
            .try_fold(self.storage_offset, |acc, (&d, &s)| {
                (d - 1).checked_mul(s).and_then(|x| acc.checked_add(x))
            })
    }

    /// Archive entry name holding the storage bytes.
    pub fn storage_entry(&self) -> String {
        entry_name(&self.prefix, &format!("data/{}", self.storage_key))
    }
}

/// A 2-D float32 tensor, densely repacked in row-major order.
#[derive(Debug, Clone, PartialEq)]
pub struct F32Matrix {
    /// Size of dimension 0.
    pub rows: usize,
    /// Size of dimension 1.
    pub cols: usize,
    /// `rows * cols` values; element `(r, c)` is `data[r * cols + c]`,
    /// whatever the stride in the file was.
    pub data: Vec<f32>,
    /// What the pickle said about the tensor (original stride and offset).
    pub info: TensorInfo,
}

impl F32Matrix {
    /// Row `r` as a slice. Panics if `r >= rows`.
    pub fn row(&self, r: usize) -> &[f32] {
        &self.data[r * self.cols..(r + 1) * self.cols]
    }
}

/// Why a `.pt` file could not be read. Messages do not name the file; the
/// caller adds the path as context.
#[derive(Debug, thiserror::Error)]
pub enum PtError {
    /// The bytes are not a readable zip archive (garbage, truncated, ...).
    #[error("not a torch zip archive: {0}")]
    NotZip(String),
    /// An entry exists but could not be extracted (unsupported compression,
    /// CRC mismatch, truncated data).
    #[error("cannot read archive entry `{entry}`: {msg}")]
    Entry {
        /// Entry name.
        entry: String,
        /// What went wrong.
        msg: String,
    },
    /// A required entry is absent (or the archive layout is ambiguous).
    #[error("archive entry missing: {0}")]
    MissingEntry(String),
    /// The pickle stream is malformed or uses something this reader does not
    /// support; `offset` is the byte position of the offending opcode.
    #[error("bad pickle at byte {offset}: {msg}")]
    Pickle {
        /// Byte offset within `data.pkl`.
        offset: usize,
        /// What went wrong.
        msg: String,
    },
    /// The pickle is valid but its top-level object is not a tensor.
    #[error("the file holds {0}, not a tensor")]
    NotATensor(String),
    /// The tensor's dtype is not float32.
    #[error("expected a float32 tensor, found {0}")]
    DType(DType),
    /// The tensor is not 2-D.
    #[error("expected a 2-D tensor, found shape {0:?}")]
    Rank(Vec<usize>),
    /// The storage entry's length disagrees with the pickle.
    #[error(
        "storage entry `{entry}` holds {actual_bytes} bytes, but the pickle \
         declares {numel} elements of {dtype} = {expected_bytes} bytes"
    )]
    StorageSize {
        /// Entry name.
        entry: String,
        /// Elements declared in the pickle.
        numel: usize,
        /// Element type.
        dtype: DType,
        /// `numel * element_size` (saturating).
        expected_bytes: usize,
        /// Actual entry size.
        actual_bytes: usize,
    },
    /// Shape, stride and offset address elements outside the storage.
    #[error(
        "tensor of shape {shape:?}, stride {stride:?} at offset {offset} \
         addresses storage element {max_index}, but the storage holds {numel}"
    )]
    OutOfBounds {
        /// Tensor shape.
        shape: Vec<usize>,
        /// Tensor stride.
        stride: Vec<usize>,
        /// Storage offset.
        offset: usize,
        /// Largest addressed index (`usize::MAX` when it overflows).
        max_index: usize,
        /// Storage length in elements.
        numel: usize,
    },
    /// Reading the file from disk failed.
    #[error("i/o error: {0}")]
    Io(#[from] std::io::Error),
}

/// Parses the archive and the pickle and returns the tensor's metadata,
/// without reading or checking the storage bytes.
pub fn read_tensor_info(bytes: &[u8]) -> Result<TensorInfo, PtError> {
    open_and_unpickle(bytes).map(|(_, info)| info)
}

/// Opens the archive, locates and runs `data.pkl`; the archive is returned
/// so the caller can go on to read the storage entry.
fn open_and_unpickle(bytes: &[u8]) -> Result<(Archive<'_>, TensorInfo), PtError> {
    let mut archive = open_archive(bytes)?;
    let (prefix, pkl_name) = find_pickle(&archive)?;
    let pkl = read_entry(&mut archive, &pkl_name, bytes.len())?;
    let mut info = unpickle_tensor(&pkl)?;
    info.prefix = prefix;
    Ok((archive, info))
}

/// Reads a 2-D float32 tensor and repacks it row-major.
///
/// Honours the shape, stride and storage offset recorded in the pickle
/// (gathering element by element when the layout is not contiguous), checks
/// that the storage entry is exactly `storage_numel * 4` bytes and that every
/// addressed index lies inside the storage.
pub fn read_f32_matrix(bytes: &[u8]) -> Result<F32Matrix, PtError> {
    let (mut archive, info) = open_and_unpickle(bytes)?;

    if info.dtype != DType::F32 {
        return Err(PtError::DType(info.dtype));
    }
    let (rows, cols) = match info.shape[..] {
        [r, c] => (r, c),
        _ => return Err(PtError::Rank(info.shape.clone())),
    };
    let (s0, s1) = (info.stride[0], info.stride[1]);
    let n = rows.checked_mul(cols).ok_or_else(|| out_of_bounds(&info))?;
    if n > 0 {
        // Checked before touching the entry so that a hostile pickle cannot
        // make us index outside the storage.
        match info.max_storage_index() {
            Some(m) if m < info.storage_numel => {}
            _ => return Err(out_of_bounds(&info)),
        }
    }

    // Compare the declared size first: it avoids reading (and allocating
    // for) an entry that is wrong anyway.
    let entry = info.storage_entry();
    let expected_bytes = info.storage_numel.checked_mul(4);
    let declared = {
        let file = archive
            .by_name(&entry)
            .map_err(|e| missing_or_entry(&entry, e))?;
        file.size()
    };
    if expected_bytes.map(|e| e as u64) != Some(declared) {
        return Err(storage_size(&info, &entry, declared as usize));
    }
    let raw = read_entry(&mut archive, &entry, bytes.len())?;
    if Some(raw.len()) != expected_bytes {
        return Err(storage_size(&info, &entry, raw.len()));
    }

    let at = |i: usize| {
        let b = &raw[4 * i..4 * i + 4];
        f32::from_le_bytes([b[0], b[1], b[2], b[3]])
    };
    let off = info.storage_offset;
    let contiguous = (rows <= 1 || s0 == cols) && (cols <= 1 || s1 == 1);
    let data: Vec<f32> = if n == 0 {
        Vec::new()
    } else if contiguous {
        // The common case (all real clips): one linear slice.
        raw[4 * off..4 * (off + n)]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    } else {
        let mut v = Vec::with_capacity(n);
        for r in 0..rows {
            for c in 0..cols {
                // Cannot overflow or exceed the storage: bounded by
                // max_storage_index, checked above.
                v.push(at(off + r * s0 + c * s1));
            }
        }
        v
    };
    Ok(F32Matrix {
        rows,
        cols,
        data,
        info,
    })
}

/// Convenience wrapper: reads the file at `path` with [`read_f32_matrix`].
pub fn read_f32_matrix_path(path: &Path) -> Result<F32Matrix, PtError> {
    read_f32_matrix(&std::fs::read(path)?)
}

fn out_of_bounds(info: &TensorInfo) -> PtError {
    PtError::OutOfBounds {
        shape: info.shape.clone(),
        stride: info.stride.clone(),
        offset: info.storage_offset,
        max_index: info.max_storage_index().unwrap_or(usize::MAX),
        numel: info.storage_numel,
    }
}

fn storage_size(info: &TensorInfo, entry: &str, actual_bytes: usize) -> PtError {
    PtError::StorageSize {
        entry: entry.to_string(),
        numel: info.storage_numel,
        dtype: info.dtype,
        expected_bytes: info.storage_numel.saturating_mul(info.dtype.element_size()),
        actual_bytes,
    }
}

// ---------------------------------------------------------------------------
// Zip layer
// ---------------------------------------------------------------------------

type Archive<'a> = zip::ZipArchive<Cursor<&'a [u8]>>;

fn open_archive(bytes: &[u8]) -> Result<Archive<'_>, PtError> {
    zip::ZipArchive::new(Cursor::new(bytes)).map_err(|e| PtError::NotZip(e.to_string()))
}

fn entry_name(prefix: &str, rest: &str) -> String {
    if prefix.is_empty() {
        rest.to_string()
    } else {
        format!("{prefix}/{rest}")
    }
}

/// Finds the unique `data.pkl` entry; returns (prefix, entry name).
fn find_pickle(archive: &Archive<'_>) -> Result<(String, String), PtError> {
    let hits: Vec<&str> = archive
        .file_names()
        .filter(|n| *n == "data.pkl" || n.ends_with("/data.pkl"))
        .collect();
    match hits[..] {
        [name] => {
            let prefix = name.strip_suffix("data.pkl").unwrap_or("");
            let prefix = prefix.strip_suffix('/').unwrap_or(prefix);
            Ok((prefix.to_string(), name.to_string()))
        }
        [] => Err(PtError::MissingEntry(
            "data.pkl (no entry named `data.pkl` or `<prefix>/data.pkl`)".into(),
        )),
        _ => Err(PtError::MissingEntry(format!(
            "a unique data.pkl ({} candidates: {})",
            hits.len(),
            hits.join(", ")
        ))),
    }
}

fn missing_or_entry(name: &str, e: zip::result::ZipError) -> PtError {
    match e {
        zip::result::ZipError::FileNotFound => PtError::MissingEntry(name.to_string()),
        e => PtError::Entry {
            entry: name.to_string(),
            msg: e.to_string(),
        },
    }
}

/// Reads a whole entry. `limit` caps the pre-allocation: a stored entry can
/// never be larger than the archive, whatever its header claims.
fn read_entry(archive: &mut Archive<'_>, name: &str, limit: usize) -> Result<Vec<u8>, PtError> {
    let mut file = archive
        .by_name(name)
        .map_err(|e| missing_or_entry(name, e))?;
    let cap = usize::try_from(file.size())
        .unwrap_or(usize::MAX)
        .min(limit);
    let mut buf = Vec::with_capacity(cap);
    file.read_to_end(&mut buf).map_err(|e| PtError::Entry {
        entry: name.to_string(),
        msg: e.to_string(),
    })?;
    Ok(buf)
}

// ---------------------------------------------------------------------------
// Pickle virtual machine
// ---------------------------------------------------------------------------

/// Index of an object in the machine's arena.
///
/// Objects live in an arena and the stack, memo and containers hold indices.
/// This mirrors Python's reference semantics (a memoised list mutated later
/// is the same list everywhere) and, more importantly, keeps hostile input
/// harmless: `BINGET` is O(1) instead of a deep copy (no exponential blow-up
/// through repeated memo references), and nothing is dropped or walked
/// recursively (no stack overflow on deeply nested tuples, no infinite loop
/// on self-referencing lists). Memory is linear in the pickle length.
type Id = usize;

/// A value produced by the pickle machine.
#[derive(Debug, Clone, PartialEq)]
enum Value {
    None,
    Bool(bool),
    Int(i64),
    /// An integer from `LONG1` that does not fit in `i64`; only its size is kept.
    BigInt(usize),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    Tuple(Vec<Id>),
    List(Vec<Id>),
    /// Also used for `collections.OrderedDict()`; insertion order is kept.
    Dict(Vec<(Id, Id)>),
    /// A reference pushed by `GLOBAL`; only meaningful as a callable.
    Global {
        module: String,
        name: String,
    },
    /// A storage resolved from a persistent id.
    Storage {
        dtype: DType,
        key: String,
        location: String,
        numel: usize,
    },
    /// Boxed: it is much larger than the other variants.
    Tensor(Box<TensorInfo>),
    /// Result of calling (REDUCE/NEWOBJ) a global we do not model.
    Opaque {
        class: String,
    },
}

struct Machine<'a> {
    data: &'a [u8],
    pos: usize,
    /// Offset of the opcode being executed, for error messages.
    op_pos: usize,
    arena: Vec<Value>,
    stack: Vec<Id>,
    /// Stack lengths at each MARK.
    marks: Vec<usize>,
    memo: std::collections::HashMap<u32, Id>,
}

/// Runs the pickle and returns the tensor it builds.
fn unpickle_tensor(data: &[u8]) -> Result<TensorInfo, PtError> {
    let mut m = Machine::new(data);
    let top = m.run()?;
    match &m.arena[top] {
        Value::Tensor(info) => Ok(info.as_ref().clone()),
        _ => Err(PtError::NotATensor(m.describe(top))),
    }
}

impl<'a> Machine<'a> {
    fn new(data: &'a [u8]) -> Self {
        Machine {
            data,
            pos: 0,
            op_pos: 0,
            arena: Vec::new(),
            stack: Vec::new(),
            marks: Vec::new(),
            memo: std::collections::HashMap::new(),
        }
    }

    fn err<T>(&self, msg: impl Into<String>) -> Result<T, PtError> {
        Err(PtError::Pickle {
            offset: self.op_pos,
            msg: msg.into(),
        })
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], PtError> {
        match self.pos.checked_add(n) {
            Some(end) if end <= self.data.len() => {
                let s = &self.data[self.pos..end];
                self.pos = end;
                Ok(s)
            }
            _ => self.err(format!(
                "truncated: needs {n} more bytes, {} left",
                self.data.len() - self.pos
            )),
        }
    }

    fn u8(&mut self) -> Result<u8, PtError> {
        Ok(self.take(1)?[0])
    }

    fn u16(&mut self) -> Result<u16, PtError> {
        let b = self.take(2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }

    fn u32(&mut self) -> Result<u32, PtError> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// A newline-terminated UTF-8 line (for GLOBAL's module and name).
    fn line(&mut self) -> Result<String, PtError> {
        let rest = &self.data[self.pos..];
        let Some(nl) = rest.iter().position(|&b| b == b'\n') else {
            return self.err("truncated: unterminated line in GLOBAL");
        };
        self.pos += nl + 1;
        match std::str::from_utf8(&rest[..nl]) {
            Ok(s) => Ok(s.to_string()),
            Err(_) => self.err("GLOBAL name is not UTF-8"),
        }
    }

    fn utf8(&self, b: &[u8]) -> Result<String, PtError> {
        match std::str::from_utf8(b) {
            Ok(s) => Ok(s.to_string()),
            Err(e) => self.err(format!("string is not valid UTF-8: {e}")),
        }
    }

    fn alloc(&mut self, v: Value) -> Id {
        self.arena.push(v);
        self.arena.len() - 1
    }

    fn push(&mut self, v: Value) {
        let id = self.alloc(v);
        self.stack.push(id);
    }

    fn pop(&mut self) -> Result<Id, PtError> {
        // Objects below the innermost MARK belong to the enclosing
        // construct; Python refuses to pop across a mark, and so do we.
        let floor = self.marks.last().copied().unwrap_or(0);
        if self.stack.len() <= floor {
            return self.err("stack underflow");
        }
        Ok(self.stack.pop().expect("length checked above"))
    }

    fn top(&self) -> Result<Id, PtError> {
        let floor = self.marks.last().copied().unwrap_or(0);
        if self.stack.len() <= floor {
            return self.err("stack underflow (empty stack)");
        }
        Ok(self.stack[self.stack.len() - 1])
    }

    /// Pops everything above the innermost MARK, and the mark itself.
    fn pop_mark(&mut self) -> Result<Vec<Id>, PtError> {
        let Some(mark) = self.marks.pop() else {
            return self.err("no MARK on the stack");
        };
        Ok(self.stack.split_off(mark))
    }

    fn memo_get(&self, key: u32) -> Result<Id, PtError> {
        match self.memo.get(&key) {
            Some(&id) => Ok(id),
            None => self.err(format!("memo key {key} was never stored")),
        }
    }

    fn memo_put(&mut self, key: u32) -> Result<(), PtError> {
        let id = self.top()?;
        self.memo.insert(key, id);
        Ok(())
    }

    /// Executes opcodes until STOP and returns the resulting object.
    fn run(&mut self) -> Result<Id, PtError> {
        loop {
            self.op_pos = self.pos;
            if self.pos >= self.data.len() {
                return self.err("truncated: stream ends before STOP");
            }
            let op = self.u8()?;
            match op {
                // PROTO: version byte; only sanity-checked.
                0x80 => {
                    let v = self.u8()?;
                    if v > 5 {
                        return self.err(format!("unsupported pickle protocol {v}"));
                    }
                }
                // FRAME (protocol 4): a length hint; frames need no handling
                // when the whole stream is in memory, but a frame claiming
                // more bytes than remain means truncation.
                0x95 => {
                    let b = self.take(8)?;
                    let n = u64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]);
                    if n > (self.data.len() - self.pos) as u64 {
                        return self.err(format!("truncated: FRAME of {n} bytes"));
                    }
                }
                b'.' => {
                    // STOP
                    return self.pop();
                }
                b'c' => {
                    // GLOBAL
                    let module = self.line()?;
                    let name = self.line()?;
                    self.push(Value::Global { module, name });
                }
                b'q' => {
                    // BINPUT
                    let k = self.u8()? as u32;
                    self.memo_put(k)?;
                }
                b'r' => {
                    // LONG_BINPUT
                    let k = self.u32()?;
                    self.memo_put(k)?;
                }
                0x94 => {
                    // MEMOIZE: next free index is the memo size.
                    let k = match u32::try_from(self.memo.len()) {
                        Ok(k) => k,
                        Err(_) => return self.err("memo overflow"),
                    };
                    self.memo_put(k)?;
                }
                b'h' => {
                    // BINGET
                    let k = self.u8()? as u32;
                    let id = self.memo_get(k)?;
                    self.stack.push(id);
                }
                b'j' => {
                    // LONG_BINGET
                    let k = self.u32()?;
                    let id = self.memo_get(k)?;
                    self.stack.push(id);
                }
                b'(' => {
                    // MARK
                    self.marks.push(self.stack.len());
                }
                b')' => self.push(Value::Tuple(Vec::new())),
                b't' => {
                    // TUPLE
                    let items = self.pop_mark()?;
                    self.push(Value::Tuple(items));
                }
                0x85..=0x87 => {
                    // TUPLE1, TUPLE2, TUPLE3
                    let n = (op - 0x84) as usize;
                    let mut items = vec![0; n];
                    for slot in items.iter_mut().rev() {
                        *slot = self.pop()?;
                    }
                    self.push(Value::Tuple(items));
                }
                b']' => self.push(Value::List(Vec::new())),
                b'a' => {
                    // APPEND
                    let item = self.pop()?;
                    let list = self.top()?;
                    self.list_mut(list)?.push(item);
                }
                b'e' => {
                    // APPENDS
                    let items = self.pop_mark()?;
                    let list = self.top()?;
                    self.list_mut(list)?.extend(items);
                }
                b'}' => self.push(Value::Dict(Vec::new())),
                b's' => {
                    // SETITEM
                    let v = self.pop()?;
                    let k = self.pop()?;
                    let d = self.top()?;
                    self.dict_set(d, k, v)?;
                }
                b'u' => {
                    // SETITEMS
                    let items = self.pop_mark()?;
                    if items.len() % 2 != 0 {
                        return self.err("SETITEMS with an odd number of items");
                    }
                    let d = self.top()?;
                    for kv in items.chunks_exact(2) {
                        self.dict_set(d, kv[0], kv[1])?;
                    }
                }
                b'J' => {
                    // BININT: signed 32-bit
                    let v = self.u32()? as i32;
                    self.push(Value::Int(v as i64));
                }
                b'K' => {
                    // BININT1
                    let v = self.u8()?;
                    self.push(Value::Int(v as i64));
                }
                b'M' => {
                    // BININT2
                    let v = self.u16()?;
                    self.push(Value::Int(v as i64));
                }
                0x8a => {
                    // LONG1: little-endian two's complement of n bytes
                    let n = self.u8()? as usize;
                    let b = self.take(n)?;
                    let v = match le_signed(b) {
                        Some(i) => Value::Int(i),
                        None => Value::BigInt(n),
                    };
                    self.push(v);
                }
                b'G' => {
                    // BINFLOAT: big-endian f64
                    let b = self.take(8)?;
                    let v = f64::from_be_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]);
                    self.push(Value::Float(v));
                }
                b'N' => self.push(Value::None),
                0x88 => self.push(Value::Bool(true)),
                0x89 => self.push(Value::Bool(false)),
                b'X' => {
                    // BINUNICODE
                    let n = self.u32()? as usize;
                    let b = self.take(n)?;
                    let s = self.utf8(b)?;
                    self.push(Value::Str(s));
                }
                0x8c => {
                    // SHORT_BINUNICODE
                    let n = self.u8()? as usize;
                    let b = self.take(n)?;
                    let s = self.utf8(b)?;
                    self.push(Value::Str(s));
                }
                b'U' | b'T' => {
                    // SHORT_BINSTRING / BINSTRING: Python 2 `str`. Python 3
                    // decodes them as text; keep raw bytes when not UTF-8.
                    let n = if op == b'U' {
                        self.u8()? as usize
                    } else {
                        let n = self.u32()? as i32;
                        if n < 0 {
                            return self.err("BINSTRING with negative length");
                        }
                        n as usize
                    };
                    let b = self.take(n)?;
                    let v = match std::str::from_utf8(b) {
                        Ok(s) => Value::Str(s.to_string()),
                        Err(_) => Value::Bytes(b.to_vec()),
                    };
                    self.push(v);
                }
                b'B' | b'C' => {
                    // BINBYTES / SHORT_BINBYTES
                    let n = if op == b'B' {
                        self.u32()? as usize
                    } else {
                        self.u8()? as usize
                    };
                    let b = self.take(n)?;
                    self.push(Value::Bytes(b.to_vec()));
                }
                b'Q' => {
                    // BINPERSID
                    let pid = self.pop()?;
                    let storage = self.persistent_load(pid)?;
                    self.push(storage);
                }
                b'R' => {
                    // REDUCE
                    let args = self.pop()?;
                    let func = self.pop()?;
                    let v = self.call(func, args)?;
                    self.push(v);
                }
                0x81 => {
                    // NEWOBJ: cls.__new__(cls, *args); never modelled.
                    let args = self.pop()?;
                    let cls = self.pop()?;
                    if !matches!(self.arena[args], Value::Tuple(_)) {
                        return self.err("NEWOBJ arguments are not a tuple");
                    }
                    let v = match &self.arena[cls] {
                        Value::Global { module, name } => Value::Opaque {
                            class: format!("{module}.{name}"),
                        },
                        _ => return self.err("NEWOBJ on something that is not a class"),
                    };
                    self.push(v);
                }
                b'b' => {
                    // BUILD: obj.__setstate__(state). The state of the
                    // objects we model carries nothing we need (torch uses
                    // it for tensor subclasses), so it is validated as present
                    // and dropped.
                    self.pop()?;
                    self.top()?;
                }
                _ => {
                    return self.err(format!(
                        "unsupported opcode 0x{op:02x} ({})",
                        opcode_name(op)
                    ))
                }
            }
        }
    }

    fn list_mut(&mut self, id: Id) -> Result<&mut Vec<Id>, PtError> {
        if !matches!(self.arena[id], Value::List(_)) {
            return self.err(format!("APPEND to {}", self.describe(id)));
        }
        match &mut self.arena[id] {
            Value::List(v) => Ok(v),
            _ => unreachable!("checked above"),
        }
    }

    fn dict_set(&mut self, d: Id, k: Id, v: Id) -> Result<(), PtError> {
        let Value::Dict(entries) = &self.arena[d] else {
            return self.err(format!("SETITEM on {}", self.describe(d)));
        };
        // Replace an existing scalar key, as a Python dict would; composite
        // keys are rare enough in torch pickles to be treated as distinct.
        let existing = entries
            .iter()
            .position(|&(k2, _)| scalar_key_eq(&self.arena[k], &self.arena[k2]));
        let Value::Dict(entries) = &mut self.arena[d] else {
            unreachable!("checked above")
        };
        match existing {
            Some(i) => entries[i].1 = v,
            None => entries.push((k, v)),
        }
        Ok(())
    }

    /// Resolves `('storage', <storage class>, key, location, numel)`.
    fn persistent_load(&self, pid: Id) -> Result<Value, PtError> {
        let Value::Tuple(items) = &self.arena[pid] else {
            return self.err(format!(
                "persistent id is {}, expected a tuple",
                self.describe(pid)
            ));
        };
        let v: Vec<&Value> = items.iter().map(|&i| &self.arena[i]).collect();
        match v[..] {
            [Value::Str(tag), cls, Value::Str(key), Value::Str(location), numel]
                if tag == "storage" =>
            {
                let dtype = match cls {
                    Value::Global { module, name } if module == "torch" => {
                        match DType::from_storage_class(name) {
                            Some(d) => d,
                            None => {
                                return self.err(format!("unsupported storage class torch.{name}"))
                            }
                        }
                    }
                    Value::Global { module, name } => {
                        return self.err(format!("unsupported storage class {module}.{name}"))
                    }
                    _ => return self.err("storage class in persistent id is not a global"),
                };
                let numel = self.as_usize(numel, "storage numel")?;
                Ok(Value::Storage {
                    dtype,
                    key: key.clone(),
                    location: location.clone(),
                    numel,
                })
            }
            _ => self.err(format!(
                "unsupported persistent id ({}), expected \
                 ('storage', class, key, location, numel)",
                self.describe(pid)
            )),
        }
    }

    fn as_usize(&self, v: &Value, what: &str) -> Result<usize, PtError> {
        match v {
            Value::Int(i) if *i >= 0 => match usize::try_from(*i) {
                Ok(u) => Ok(u),
                Err(_) => self.err(format!("{what} {i} does not fit in usize")),
            },
            Value::Int(i) => self.err(format!("{what} is negative ({i})")),
            _ => self.err(format!("{what} is not an int")),
        }
    }

    fn usize_tuple(&self, id: Id, what: &str) -> Result<Vec<usize>, PtError> {
        let Value::Tuple(items) = &self.arena[id] else {
            return self.err(format!("{what} is {}, expected a tuple", self.describe(id)));
        };
        items
            .iter()
            .map(|&i| self.as_usize(&self.arena[i], what))
            .collect()
    }

    /// REDUCE: the only callables are the tensor rebuild function and
    /// `collections.OrderedDict`; other globals yield an opaque object.
    fn call(&self, func: Id, args: Id) -> Result<Value, PtError> {
        let Value::Tuple(argv) = &self.arena[args] else {
            return self.err(format!(
                "REDUCE arguments are {}, expected a tuple",
                self.describe(args)
            ));
        };
        let Value::Global { module, name } = &self.arena[func] else {
            return self.err(format!("REDUCE calls {}", self.describe(func)));
        };
        match (module.as_str(), name.as_str()) {
            ("torch._utils", "_rebuild_tensor_v2") => self.rebuild_tensor(argv),
            ("collections", "OrderedDict") => match argv[..] {
                [] => Ok(Value::Dict(Vec::new())),
                // OrderedDict(existing_dict) copies it.
                [a] if matches!(self.arena[a], Value::Dict(_)) => Ok(self.arena[a].clone()),
                _ => self.err("collections.OrderedDict called with unsupported arguments"),
            },
            _ => Ok(Value::Opaque {
                class: format!("{module}.{name}"),
            }),
        }
    }

    /// `_rebuild_tensor_v2(storage, storage_offset, size, stride,
    /// requires_grad, backward_hooks[, metadata])`.
    fn rebuild_tensor(&self, argv: &[Id]) -> Result<Value, PtError> {
        if !(6..=7).contains(&argv.len()) {
            return self.err(format!(
                "_rebuild_tensor_v2 takes 6 or 7 arguments, got {}",
                argv.len()
            ));
        }
        let Value::Storage {
            dtype,
            key,
            location,
            numel,
        } = &self.arena[argv[0]]
        else {
            return self.err(format!(
                "_rebuild_tensor_v2 storage argument is {}",
                self.describe(argv[0])
            ));
        };
        let storage_offset = self.as_usize(&self.arena[argv[1]], "storage offset")?;
        let shape = self.usize_tuple(argv[2], "size")?;
        let stride = self.usize_tuple(argv[3], "stride")?;
        if shape.len() != stride.len() {
            return self.err(format!(
                "size {shape:?} and stride {stride:?} have different lengths"
            ));
        }
        if !matches!(self.arena[argv[4]], Value::Bool(_)) {
            return self.err("requires_grad is not a bool");
        }
        Ok(Value::Tensor(Box::new(TensorInfo {
            dtype: *dtype,
            shape,
            stride,
            storage_offset,
            storage_key: key.clone(),
            storage_numel: *numel,
            location: location.clone(),
            prefix: String::new(),
        })))
    }

    /// One-line, non-recursive description of an object, for errors.
    fn describe(&self, id: Id) -> String {
        fn plural(n: usize, one: &str) -> String {
            if n == 1 {
                format!("1 {one}")
            } else {
                format!("{n} {one}s")
            }
        }
        match &self.arena[id] {
            Value::None => "None".into(),
            Value::Bool(b) => format!("bool {}", if *b { "True" } else { "False" }),
            Value::Int(i) => format!("int {i}"),
            Value::BigInt(n) => format!("an int of {n} bytes"),
            Value::Float(f) => format!("float {f}"),
            Value::Str(s) => {
                let short: String = s.chars().take(40).collect();
                let more = if short.len() < s.len() { "..." } else { "" };
                format!("str {short:?}{more}")
            }
            Value::Bytes(b) => format!("bytes of length {}", b.len()),
            Value::Tuple(v) => format!("a tuple with {}", plural(v.len(), "item")),
            Value::List(v) => format!("a list with {}", plural(v.len(), "item")),
            Value::Dict(v) => format!("a dict with {}", plural(v.len(), "key")),
            Value::Global { module, name } => format!("the global {module}.{name}"),
            Value::Storage { dtype, numel, .. } => {
                format!("a bare torch.{} of {numel} elements", dtype.storage_class())
            }
            Value::Tensor(t) => format!("a {} tensor of shape {:?}", t.dtype, t.shape),
            Value::Opaque { class } => format!("an object built by {class}"),
        }
    }
}

/// Equality for hashable scalar keys; composite keys never compare equal.
fn scalar_key_eq(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::None, Value::None) => true,
        (Value::Bool(x), Value::Bool(y)) => x == y,
        (Value::Int(x), Value::Int(y)) => x == y,
        (Value::Str(x), Value::Str(y)) => x == y,
        (Value::Bytes(x), Value::Bytes(y)) => x == y,
        _ => false,
    }
}

/// Decodes a little-endian two's-complement integer of up to 8 bytes
/// (LONG1); `None` when it needs more than 64 bits.
fn le_signed(b: &[u8]) -> Option<i64> {
    if b.is_empty() {
        return Some(0);
    }
    let negative = b[b.len() - 1] & 0x80 != 0;
    let fill = if negative { 0xff } else { 0x00 };
    // Longer encodings are fine as long as the extra bytes are pure sign
    // extension.
    let (low, high) = b.split_at(b.len().min(8));
    if high.iter().any(|&x| x != fill) {
        return None;
    }
    let mut buf = [fill; 8];
    buf[..low.len()].copy_from_slice(low);
    let v = i64::from_le_bytes(buf);
    // The sign of the 8-byte value must agree with the encoded sign.
    if (v < 0) != negative {
        return None;
    }
    Some(v)
}

/// Names of well-known opcodes we do not implement, for error messages.
fn opcode_name(op: u8) -> &'static str {
    match op {
        b'I' => "INT",
        b'L' => "LONG",
        b'F' => "FLOAT",
        b'S' => "STRING",
        b'V' => "UNICODE",
        b'P' => "PERSID",
        b'g' => "GET",
        b'p' => "PUT",
        b'l' => "LIST",
        b'd' => "DICT",
        b'i' => "INST",
        b'o' => "OBJ",
        b'0' => "POP",
        b'1' => "POP_MARK",
        b'2' => "DUP",
        0x82 => "EXT1",
        0x83 => "EXT2",
        0x84 => "EXT4",
        0x8b => "LONG4",
        0x8d => "BINUNICODE8",
        0x8e => "BINBYTES8",
        0x8f => "EMPTY_SET",
        0x90 => "ADDITEMS",
        0x91 => "FROZENSET",
        0x92 => "NEWOBJ_EX",
        0x93 => "STACK_GLOBAL",
        0x96 => "BYTEARRAY8",
        0x97 => "NEXT_BUFFER",
        0x98 => "READONLY_BUFFER",
        _ => "not a pickle opcode",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::io::Write;
    use std::path::PathBuf;

    fn datasets() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/datasets")
    }

    fn real_clips() -> Vec<PathBuf> {
        fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
            let Ok(rd) = std::fs::read_dir(dir) else {
                return;
            };
            for e in rd.flatten() {
                let p = e.path();
                if p.is_dir() {
                    walk(&p, out);
                } else if p.extension().is_some_and(|x| x == "pt") {
                    out.push(p);
                }
            }
        }
        let mut v = Vec::new();
        walk(&datasets(), &mut v);
        v.sort();
        v
    }

    const RUN_CLIP: &str = "ballplay/run/013_018pickle_run_4.pt";

    // ---- pickle builder mirroring what torch.save writes ------------------

    /// Emits opcodes; `put` memoises with BINPUT like torch's pickler does.
    #[derive(Default)]
    struct Pk(Vec<u8>, u8);

    impl Pk {
        fn op(&mut self, b: &[u8]) -> &mut Self {
            self.0.extend_from_slice(b);
            self
        }
        fn put(&mut self) -> &mut Self {
            let k = self.1;
            self.1 += 1;
            self.op(&[b'q', k])
        }
        fn global(&mut self, module: &str, name: &str) -> &mut Self {
            self.op(format!("c{module}\n{name}\n").as_bytes()).put()
        }
        fn unicode(&mut self, s: &str) -> &mut Self {
            self.op(b"X")
                .op(&(s.len() as u32).to_le_bytes())
                .op(s.as_bytes())
                .put()
        }
        fn int(&mut self, v: usize) -> &mut Self {
            if v < 256 {
                self.op(&[b'K', v as u8])
            } else if v < 65536 {
                self.op(b"M").op(&(v as u16).to_le_bytes())
            } else if v <= i32::MAX as usize {
                self.op(b"J").op(&(v as i32).to_le_bytes())
            } else {
                // LONG1 with 8 bytes, as pickle does for big ints.
                self.op(&[0x8a, 8]).op(&(v as i64).to_le_bytes())
            }
        }
        fn tuple(&mut self, vals: &[usize]) -> &mut Self {
            self.op(b"(");
            for &v in vals {
                self.int(v);
            }
            self.op(b"t").put()
        }
    }

    fn tensor_pickle(
        class: &str,
        key: &str,
        numel: usize,
        offset: usize,
        shape: &[usize],
        stride: &[usize],
    ) -> Vec<u8> {
        let mut p = Pk::default();
        p.op(&[0x80, 2])
            .global("torch._utils", "_rebuild_tensor_v2")
            .op(b"((")
            .unicode("storage")
            .global("torch", class)
            .unicode(key)
            .unicode("cuda:0")
            .int(numel)
            .op(b"t")
            .put()
            .op(b"Q")
            .int(offset)
            .tuple(shape)
            .tuple(stride)
            .op(&[0x89])
            .global("collections", "OrderedDict")
            .op(b")R")
            .put()
            .op(b"t")
            .put()
            .op(b"R")
            .put()
            .op(b".");
        p.0
    }

    fn zip_of(entries: &[(&str, &[u8])]) -> Vec<u8> {
        let mut w = zip::ZipWriter::new(Cursor::new(Vec::new()));
        let opts = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored);
        for (name, data) in entries {
            w.start_file(*name, opts).unwrap();
            w.write_all(data).unwrap();
        }
        w.finish().unwrap().into_inner()
    }

    fn pt_of(prefix: &str, pkl: &[u8], key: &str, storage: &[u8]) -> Vec<u8> {
        zip_of(&[
            (&format!("{prefix}/data.pkl"), pkl),
            (&format!("{prefix}/data/{key}"), storage),
            (&format!("{prefix}/version"), b"3\n"),
        ])
    }

    fn f32_bytes(v: impl IntoIterator<Item = f32>) -> Vec<u8> {
        v.into_iter().flat_map(f32::to_le_bytes).collect()
    }

    fn pickle_err(data: &[u8]) -> (usize, String) {
        match unpickle_tensor(data) {
            Err(PtError::Pickle { offset, msg }) => (offset, msg),
            other => panic!("expected a pickle error, got {other:?}"),
        }
    }

    // ---- real data --------------------------------------------------------

    #[test]
    fn every_real_clip_reads() {
        let clips = real_clips();
        assert_eq!(clips.len(), 83, "expected 83 clips under {:?}", datasets());
        for p in &clips {
            let m = read_f32_matrix_path(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            assert_eq!(m.rows * m.cols, m.data.len(), "{}", p.display());
            assert!(
                [337, 409, 415].contains(&m.cols),
                "{}: {}",
                p.display(),
                m.cols
            );
            assert!(m.rows > 0);
            assert_eq!(m.info.dtype, DType::F32);
            assert_eq!(m.info.shape, vec![m.rows, m.cols]);
            assert_eq!(m.info.storage_numel, m.data.len());
            assert!(!m.info.prefix.is_empty());
            assert!(m.data.iter().all(|x| x.is_finite()), "{}", p.display());
            let info = read_tensor_info(&std::fs::read(p).unwrap()).unwrap();
            assert_eq!(info, m.info);
        }
    }

    /// Values read with Python's zipfile + struct from
    /// ballplay/run/013_018pickle_run_4.pt (`archive/data/0`, 27297 floats).
    #[test]
    fn run_clip_matches_python() {
        let m = read_f32_matrix_path(&datasets().join(RUN_CLIP)).unwrap();
        assert_eq!((m.rows, m.cols), (81, 337));
        assert_eq!(m.info.prefix, "archive");
        assert_eq!(m.info.storage_key, "0");
        assert_eq!(m.info.location, "cuda:0");
        assert_eq!(m.info.stride, vec![337, 1]);
        assert_eq!(m.info.storage_offset, 0);
        assert_eq!(m.data[0].to_bits(), 0xbf5e15f8); // -0.8675227165222168
        assert_eq!(m.data[1].to_bits(), 0x400e4020); // 2.2226638793945312
        assert_eq!(m.row(1)[0].to_bits(), 0xbf5f8715); // -0.8731549382209778
        assert_eq!(m.row(80)[326].to_bits(), 0x3f35737b); // 0.7087933421134949
        assert_eq!(*m.data.last().unwrap(), 0.0);
        let sum: f64 = m.data.iter().map(|&x| x as f64).sum();
        assert!((sum - 467.89647197642194).abs() < 1e-9, "{sum}");
    }

    /// This clip's entries live under `006_s10_pour_cup_1650_1860/` rather
    /// than `archive/`, and its numel needs BININT (4-byte int).
    #[test]
    fn non_archive_prefix() {
        let p = datasets().join("parahome/pour_kettlecup/010_s6_pour_kettlecup_1650_1860.pt");
        let m = read_f32_matrix_path(&p).unwrap();
        assert_eq!(m.info.prefix, "006_s10_pour_cup_1650_1860");
        assert_eq!((m.rows, m.cols), (210, 415));
        assert_eq!(m.data[0].to_bits(), 0xbda18cc8); // -0.07888180017471313
    }

    #[test]
    fn truncated_real_file_is_not_zip() {
        let bytes = std::fs::read(datasets().join(RUN_CLIP)).unwrap();
        let e = read_f32_matrix(&bytes[..100]).unwrap_err();
        assert!(matches!(e, PtError::NotZip(_)), "{e}");
        // Cutting off only the central directory end is also fatal.
        let e = read_tensor_info(&bytes[..bytes.len() - 10]).unwrap_err();
        assert!(matches!(e, PtError::NotZip(_)), "{e}");
    }

    #[test]
    fn garbage_is_not_zip() {
        let garbage: Vec<u8> = (0..4096u32)
            .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
            .collect();
        assert!(matches!(read_f32_matrix(&garbage), Err(PtError::NotZip(_))));
        assert!(matches!(read_f32_matrix(b""), Err(PtError::NotZip(_))));
    }

    // ---- synthetic archives ----------------------------------------------

    #[test]
    fn strided_tensor_with_offset_is_gathered() {
        // Storage 0..20; tensor (3, 4) at offset 2 with stride (1, 5), i.e.
        // a transposed view: element (r, c) = storage[2 + r + 5c].
        let pkl = tensor_pickle("FloatStorage", "7", 20, 2, &[3, 4], &[1, 5]);
        let bytes = pt_of("my_clip", &pkl, "7", &f32_bytes((0..20).map(|i| i as f32)));
        let m = read_f32_matrix(&bytes).unwrap();
        assert_eq!((m.rows, m.cols), (3, 4));
        assert_eq!(m.info.prefix, "my_clip");
        assert_eq!(m.info.storage_key, "7");
        assert_eq!(m.info.storage_offset, 2);
        let want: Vec<f32> = (0..3)
            .flat_map(|r| (0..4).map(move |c| (2 + r + 5 * c) as f32))
            .collect();
        assert_eq!(m.data, want);
    }

    #[test]
    fn contiguous_tensor_with_offset_and_root_prefix() {
        let pkl = tensor_pickle("FloatStorage", "0", 10, 3, &[2, 3], &[3, 1]);
        let bytes = zip_of(&[
            ("data.pkl", &pkl),
            ("data/0", &f32_bytes((0..10).map(|i| i as f32 * 0.5))),
        ]);
        let m = read_f32_matrix(&bytes).unwrap();
        assert_eq!(m.info.prefix, "");
        assert_eq!(m.data, vec![1.5, 2.0, 2.5, 3.0, 3.5, 4.0]);
    }

    #[test]
    fn empty_tensor() {
        let pkl = tensor_pickle("FloatStorage", "0", 0, 0, &[0, 337], &[337, 1]);
        let m = read_f32_matrix(&pt_of("archive", &pkl, "0", &[])).unwrap();
        assert_eq!((m.rows, m.cols, m.data.len()), (0, 337, 0));
    }

    #[test]
    fn dict_at_top_level_is_not_a_tensor() {
        // {'a': 1, 'b': {}} built the way pickle does: EMPTY_DICT, MARK,
        // key/value pairs, SETITEMS.
        let mut p = Pk::default();
        p.op(&[0x80, 2, b'}'])
            .put()
            .op(b"(")
            .unicode("a")
            .int(1)
            .unicode("b")
            .op(b"}")
            .op(b"u.");
        let bytes = pt_of("archive", &p.0, "0", &[]);
        match read_f32_matrix(&bytes) {
            Err(PtError::NotATensor(what)) => assert_eq!(what, "a dict with 2 keys"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn int_and_opaque_objects_are_not_tensors() {
        let e = unpickle_tensor(&[0x80, 2, b'K', 3, b'.']).unwrap_err();
        assert_eq!(e.to_string(), "the file holds int 3, not a tensor");
        let mut p = Pk::default();
        p.op(&[0x80, 2])
            .global("numpy.core.multiarray", "_reconstruct")
            .op(b")R.");
        match unpickle_tensor(&p.0) {
            Err(PtError::NotATensor(w)) => {
                assert_eq!(w, "an object built by numpy.core.multiarray._reconstruct")
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn int64_tensor_is_a_dtype_error() {
        let pkl = tensor_pickle("LongStorage", "0", 6, 0, &[2, 3], &[3, 1]);
        let storage: Vec<u8> = (0..6i64).flat_map(i64::to_le_bytes).collect();
        let bytes = pt_of("archive", &pkl, "0", &storage);
        let info = read_tensor_info(&bytes).unwrap();
        assert_eq!(info.dtype, DType::I64);
        assert_eq!(info.shape, vec![2, 3]);
        let e = read_f32_matrix(&bytes).unwrap_err();
        assert!(matches!(e, PtError::DType(DType::I64)), "{e}");
        assert_eq!(e.to_string(), "expected a float32 tensor, found int64");
    }

    #[test]
    fn rank_3_is_a_rank_error() {
        let pkl = tensor_pickle("FloatStorage", "0", 8, 0, &[2, 2, 2], &[4, 2, 1]);
        let bytes = pt_of("archive", &pkl, "0", &f32_bytes([0.0; 8]));
        assert!(matches!(read_f32_matrix(&bytes), Err(PtError::Rank(s)) if s == [2, 2, 2]));
    }

    #[test]
    fn storage_entry_too_short() {
        let pkl = tensor_pickle("FloatStorage", "0", 6, 0, &[2, 3], &[3, 1]);
        let bytes = pt_of("archive", &pkl, "0", &f32_bytes([1.0; 5]));
        match read_f32_matrix(&bytes) {
            Err(PtError::StorageSize {
                expected_bytes,
                actual_bytes,
                ..
            }) => assert_eq!((expected_bytes, actual_bytes), (24, 20)),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn view_beyond_storage_is_out_of_bounds() {
        // Offset 5 + 2*3 elements would need 11 elements, storage has 6.
        let pkl = tensor_pickle("FloatStorage", "0", 6, 5, &[2, 3], &[3, 1]);
        let bytes = pt_of("archive", &pkl, "0", &f32_bytes([1.0; 6]));
        assert!(matches!(
            read_f32_matrix(&bytes),
            Err(PtError::OutOfBounds { max_index: 10, .. })
        ));
        // Overflowing strides must not wrap around: 4 * 2^62 = 2^64.
        let pkl = tensor_pickle("FloatStorage", "0", 6, 0, &[5, 1], &[1 << 62, 1]);
        let bytes = pt_of("archive", &pkl, "0", &f32_bytes([1.0; 6]));
        assert!(matches!(
            read_f32_matrix(&bytes),
            Err(PtError::OutOfBounds {
                max_index: usize::MAX,
                ..
            })
        ));
    }

    #[test]
    fn missing_entries() {
        let pkl = tensor_pickle("FloatStorage", "0", 6, 0, &[2, 3], &[3, 1]);
        let no_data = zip_of(&[("archive/data.pkl", &pkl)]);
        assert!(
            matches!(read_f32_matrix(&no_data), Err(PtError::MissingEntry(e)) if e == "archive/data/0")
        );
        assert!(read_tensor_info(&no_data).is_ok());
        let no_pkl = zip_of(&[("archive/data/0", &f32_bytes([0.0; 6]))]);
        assert!(matches!(
            read_tensor_info(&no_pkl),
            Err(PtError::MissingEntry(_))
        ));
        let two = zip_of(&[("a/data.pkl", &pkl), ("b/data.pkl", &pkl)]);
        assert!(matches!(
            read_tensor_info(&two),
            Err(PtError::MissingEntry(_))
        ));
    }

    // ---- pickle machine ---------------------------------------------------

    #[test]
    fn unknown_opcode() {
        let mut pkl = tensor_pickle("FloatStorage", "0", 6, 0, &[2, 3], &[3, 1]);
        // STACK_GLOBAL (protocol 4, not emitted by torch at protocol 2)
        // right after PROTO.
        pkl.insert(2, 0x93);
        let (offset, msg) = pickle_err(&pkl);
        assert_eq!(offset, 2);
        assert!(
            msg.contains("0x93") && msg.contains("STACK_GLOBAL"),
            "{msg}"
        );
        let bytes = pt_of("archive", &pkl, "0", &f32_bytes([0.0; 6]));
        let e = read_f32_matrix(&bytes).unwrap_err();
        assert!(e.to_string().starts_with("bad pickle at byte 2"), "{e}");
        let (_, msg) = pickle_err(&[0x80, 2, 0xff]);
        assert!(msg.contains("not a pickle opcode"), "{msg}");
    }

    #[test]
    fn malformed_streams() {
        // Stack underflow.
        assert!(pickle_err(&[0x80, 2, b'R']).1.contains("underflow"));
        assert!(pickle_err(b".").1.contains("underflow"));
        // Memo miss.
        assert!(pickle_err(&[b'h', 9, b'.']).1.contains("memo key 9"));
        // Truncated argument and missing STOP.
        assert!(pickle_err(&[b'X', 10, 0, 0, 0, b'a'])
            .1
            .contains("truncated"));
        assert!(pickle_err(&[b'K', 1]).1.contains("before STOP"));
        assert!(pickle_err(b"ctorch\nFloatSto").1.contains("unterminated"));
        // TUPLE without MARK; popping across a MARK.
        assert!(pickle_err(b"K\x01t.").1.contains("MARK"));
        assert!(pickle_err(b"K\x01(\x85.").1.contains("underflow"));
        // Calling a non-global, appending to a non-list.
        assert!(pickle_err(b"K\x01)R.").1.contains("REDUCE calls int 1"));
        assert!(pickle_err(b"K\x01K\x02a.").1.contains("APPEND to int 1"));
        // Unknown persistent id kinds.
        assert!(pickle_err(b"K\x01Q.").1.contains("persistent id"));
        let mut p = Pk::default();
        p.op(b"(")
            .unicode("storage")
            .global("torch", "ComplexFloatStorage");
        p.unicode("0").unicode("cpu").int(1).op(b"tQ.");
        assert!(pickle_err(&p.0).1.contains("ComplexFloatStorage"));
    }

    #[test]
    fn every_truncation_of_a_real_pickle_fails_cleanly() {
        let pkl = tensor_pickle("FloatStorage", "0", 27297, 0, &[81, 337], &[337, 1]);
        assert_eq!(unpickle_tensor(&pkl).unwrap().shape, vec![81, 337]);
        for n in 0..pkl.len() {
            assert!(
                matches!(unpickle_tensor(&pkl[..n]), Err(PtError::Pickle { .. })),
                "prefix of {n} bytes"
            );
        }
    }

    #[test]
    fn memo_shares_objects_and_longs_decode() {
        // l = []; memo[0] = l; l.append(l-via-memo); top = (l, LONG1 -2^40)
        let mut p = vec![0x80, 2, b']', b'q', 0, b'h', 0, b'a', b'h', 0];
        p.extend([0x8a, 6, 0, 0, 0, 0, 0, 0xff, 0x86, b'.']);
        let mut m = Machine::new(&p);
        let top = m.run().unwrap();
        let Value::Tuple(items) = m.arena[top].clone() else {
            panic!()
        };
        assert_eq!(m.arena[items[1]], Value::Int(-(1 << 40)));
        assert_eq!(m.describe(items[0]), "a list with 1 item");
        assert_eq!(le_signed(&[0xff; 12]), Some(-1));
        assert_eq!(le_signed(&[1, 0, 0, 0, 0, 0, 0, 0, 1]), None);
        assert_eq!(le_signed(&[0, 0, 0, 0, 0, 0, 0, 0x80, 0]), None);
    }

    #[test]
    fn deep_nesting_does_not_overflow_the_stack() {
        let mut p = vec![0x80, 2, b'N'];
        p.extend(std::iter::repeat_n(0x85, 200_000)); // TUPLE1 x 200k
        p.push(b'.');
        match unpickle_tensor(&p) {
            Err(PtError::NotATensor(w)) => assert_eq!(w, "a tuple with 1 item"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn memo_doubling_stays_linear() {
        // memo[0] = (); 40 times memo[0] = (memo[0], memo[0]): 286 bytes
        // that describe 2^40 leaves when references are copied.
        let mut p = vec![0x80, 2, b')', b'q', 0];
        for _ in 0..40 {
            p.extend([b'h', 0, b'h', 0, 0x86, b'q', 0]);
        }
        p.push(b'.');
        assert_eq!(p.len(), 286);
        match unpickle_tensor(&p) {
            Err(PtError::NotATensor(w)) => assert_eq!(w, "a tuple with 2 items"),
            other => panic!("{other:?}"),
        }
        // a 2-tuple passed to _rebuild_tensor_v2 is an error, not a panic
        let mut p = vec![0x80, 2];
        p.extend(b"ctorch._utils\n_rebuild_tensor_v2\n(K\x01K\x02tR.");
        assert!(matches!(unpickle_tensor(&p), Err(PtError::Pickle { .. })));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]

        #[test]
        fn arbitrary_bytes_never_panic(data in proptest::collection::vec(any::<u8>(), 0..256)) {
            let _ = unpickle_tensor(&data);
            let _ = read_f32_matrix(&data);
        }

        #[test]
        fn mutated_pickles_never_panic(pos in 0usize..200, byte in any::<u8>()) {
            let mut pkl = tensor_pickle("FloatStorage", "0", 6, 0, &[2, 3], &[3, 1]);
            let i = pos % pkl.len();
            pkl[i] = byte;
            let bytes = pt_of("archive", &pkl, "0", &f32_bytes([0.5; 6]));
            if let Ok(m) = read_f32_matrix(&bytes) {
                prop_assert_eq!(m.rows * m.cols, m.data.len());
            }
        }
    }
}
