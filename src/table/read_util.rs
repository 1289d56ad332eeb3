//! Helpers for reading the tables back with clear errors.

use super::io::ReadTable;
use anyhow::{anyhow, bail, Result};
use arrow::array::{Array, ArrayRef, AsArray, FixedSizeListArray, ListArray};
use arrow::datatypes::Float32Type;
use arrow::record_batch::RecordBatch;
use std::path::Path;

/// Require the `skillaug.table` metadata to say `want`.
pub fn check_table(t: &ReadTable, path: &Path, want: &str) -> Result<()> {
    match t.meta("skillaug.table") {
        Some(k) if k == want => Ok(()),
        Some(k) => bail!("{}: is a `{k}` table, expected `{want}`", path.display()),
        None => bail!(
            "{}: not a skillaug table (no skillaug.table metadata)",
            path.display()
        ),
    }
}

/// Column `name` of `b`.
pub fn col<'a>(b: &'a RecordBatch, name: &str, path: &Path) -> Result<&'a ArrayRef> {
    b.column_by_name(name)
        .ok_or_else(|| anyhow!("{}: missing column `{name}`", path.display()))
}

/// A string column.
pub fn strs(b: &RecordBatch, name: &str, path: &Path) -> Result<Vec<String>> {
    let a = col(b, name, path)?
        .as_string_opt::<i32>()
        .ok_or_else(|| anyhow!("{}: column `{name}` is not a string column", path.display()))?;
    Ok((0..a.len()).map(|i| a.value(i).to_string()).collect())
}

/// A `List<Utf8>` column.
pub fn list_strs(b: &RecordBatch, name: &str, path: &Path) -> Result<Vec<Vec<String>>> {
    let l = col(b, name, path)?
        .as_list_opt::<i32>()
        .ok_or_else(|| anyhow!("{}: column `{name}` is not a list column", path.display()))?;
    Ok((0..l.len())
        .map(|i| {
            let v = l.value(i);
            let s = v.as_string::<i32>();
            (0..s.len()).map(|k| s.value(k).to_string()).collect()
        })
        .collect())
}

/// Row `i` of a float list column (fixed or variable size); `None` if null.
pub fn f32_row(a: &ArrayRef, i: usize) -> Option<Vec<f32>> {
    if a.is_null(i) {
        return None;
    }
    let v = if let Some(l) = a.as_any().downcast_ref::<FixedSizeListArray>() {
        l.value(i)
    } else {
        a.as_any().downcast_ref::<ListArray>()?.value(i)
    };
    Some(v.as_primitive::<Float32Type>().values().to_vec())
}
