//! Helpers for reading the tables back with clear errors.

use super::io::ReadTable;
use anyhow::{anyhow, bail, Result};
use arrow::array::{Array, ArrayRef, AsArray, FixedSizeListArray, ListArray};
use arrow::datatypes::{DataType, Float32Type};
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

/// A UInt32 column with its nulls.
pub fn opt_u32s(b: &RecordBatch, name: &str, path: &Path) -> Result<Vec<Option<u32>>> {
    let a = col(b, name, path)?
        .as_primitive_opt::<arrow::datatypes::UInt32Type>()
        .ok_or_else(|| anyhow!("{}: column `{name}` is not UInt32", path.display()))?;
    Ok((0..a.len())
        .map(|i| a.is_valid(i).then(|| a.value(i)))
        .collect())
}

/// A Float32 column with its nulls; all `None` when the batch lacks the
/// column (one added after tables were written with this schema version).
pub fn opt_f32s_if_present(b: &RecordBatch, name: &str, path: &Path) -> Result<Vec<Option<f32>>> {
    let Some(a) = b.column_by_name(name) else {
        return Ok(vec![None; b.num_rows()]);
    };
    let a = a
        .as_primitive_opt::<Float32Type>()
        .ok_or_else(|| anyhow!("{}: column `{name}` is not Float32", path.display()))?;
    Ok((0..a.len())
        .map(|i| a.is_valid(i).then(|| a.value(i)))
        .collect())
}

/// A `FixedSizeList<Float32, 3>` column with its null rows; all `None`
/// when the batch lacks the column (as [`opt_f32s_if_present`]). A row of
/// another length is an error naming the column.
pub fn opt_f32x3s_if_present(
    b: &RecordBatch,
    name: &str,
    path: &Path,
) -> Result<Vec<Option<[f32; 3]>>> {
    let Some(a) = b.column_by_name(name) else {
        return Ok(vec![None; b.num_rows()]);
    };
    let fits = matches!(a.data_type(), DataType::FixedSizeList(f, 3) if f.data_type() == &DataType::Float32);
    if !fits {
        bail!(
            "{}: column `{name}` is {}, not FixedSizeList<Float32, 3>",
            path.display(),
            a.data_type()
        );
    }
    (0..a.len())
        .map(|i| {
            f32_row(a, i)
                .map(|v| {
                    <[f32; 3]>::try_from(v).map_err(|_| {
                        anyhow!("{}: row {i}: `{name}` is not 3 floats", path.display())
                    })
                })
                .transpose()
        })
        .collect()
}

/// A Boolean column with its nulls; all `None` when the batch lacks the
/// column (as [`opt_f32s_if_present`]).
pub fn opt_bools_if_present(b: &RecordBatch, name: &str, path: &Path) -> Result<Vec<Option<bool>>> {
    let Some(a) = b.column_by_name(name) else {
        return Ok(vec![None; b.num_rows()]);
    };
    let a = a
        .as_boolean_opt()
        .ok_or_else(|| anyhow!("{}: column `{name}` is not Boolean", path.display()))?;
    Ok((0..a.len())
        .map(|i| a.is_valid(i).then(|| a.value(i)))
        .collect())
}

/// A Boolean column (nulls as false).
pub fn bools(b: &RecordBatch, name: &str, path: &Path) -> Result<Vec<bool>> {
    let a = col(b, name, path)?
        .as_boolean_opt()
        .ok_or_else(|| anyhow!("{}: column `{name}` is not Boolean", path.display()))?;
    Ok((0..a.len()).map(|i| a.is_valid(i) && a.value(i)).collect())
}

/// The posture columns (`root_pos`, `root_rot`, `joint_rot`, `obj_pos`,
/// `obj_rot`) of row `i`; `None` where `root_pos` is null.
pub fn posture_row(
    b: &RecordBatch,
    path: &Path,
    i: usize,
) -> Result<Option<crate::motion::state::Posture>> {
    let row = |name: &str| -> Result<Option<Vec<f32>>> { Ok(f32_row(col(b, name, path)?, i)) };
    let Some(root_pos) = row("root_pos")? else {
        return Ok(None);
    };
    let bad = |what: &str| {
        anyhow!(
            "{}: row {i}: `{what}` is null or of the wrong length",
            path.display()
        )
    };
    let need = |name: &str| row(name)?.ok_or_else(|| bad(name));
    Ok(Some(crate::motion::state::Posture {
        root_pos: root_pos.try_into().map_err(|_| bad("root_pos"))?,
        root_rot: need("root_rot")?.try_into().map_err(|_| bad("root_rot"))?,
        joint_rot: need("joint_rot")?,
        obj_pos: need("obj_pos")?,
        obj_rot: need("obj_rot")?,
    }))
}
