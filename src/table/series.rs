//! The series a figure of `skillaug plot` draws, read from skillaug tables:
//! a metric against another column (curves), the masked-state histogram of
//! the STG edges (counted with polars) and the cells of an eval summary.

use anyhow::{Context, Result};
use arrow::array::{Array, Float64Array};
use arrow::datatypes::DataType;
use polars::prelude::{col, len, IntoLazy, SortMultipleOptions};
use std::path::{Path, PathBuf};

/// (x, value) of `metric` against the numeric column `x` of a table.
pub fn curve_of(path: &Path, x: &str, metric: &str) -> Result<Vec<(f64, f64)>> {
    let t = super::io::read_parquet(path)?;
    let mut v = Vec::new();
    let f64s = |a: &std::sync::Arc<dyn Array>, name: &str| -> Result<Vec<f64>> {
        let c = arrow::compute::cast(a, &DataType::Float64)
            .with_context(|| format!("{}: column `{name}` is not numeric", path.display()))?;
        let c = c
            .as_any()
            .downcast_ref::<Float64Array>()
            .expect("cast to f64");
        Ok((0..c.len())
            .map(|i| if c.is_null(i) { f64::NAN } else { c.value(i) })
            .collect())
    };
    for b in &t.batches {
        let col = |name: &str| {
            b.column_by_name(name).with_context(|| {
                let kind = t.meta("skillaug.table").unwrap_or("unknown");
                let cols: Vec<String> = b
                    .schema()
                    .fields()
                    .iter()
                    .filter(|f| f.data_type().is_numeric())
                    .map(|f| f.name().clone())
                    .collect();
                format!(
                    "{}: no column `{name}` in this `{kind}` table (numeric columns: {})",
                    path.display(),
                    cols.join(", ")
                )
            })
        };
        let xs = f64s(col(x)?, x)?;
        let ys = f64s(col(metric)?, metric)?;
        v.extend(xs.into_iter().zip(ys));
    }
    Ok(v)
}

/// Moving average over `k` points (k <= 1: unchanged).
pub fn smooth(v: &[(f64, f64)], k: usize) -> Vec<(f64, f64)> {
    if k <= 1 {
        return v.to_vec();
    }
    (0..v.len())
        .map(|i| {
            let lo = i.saturating_sub(k - 1);
            let w = &v[lo..=i];
            (v[i].0, w.iter().map(|p| p.1).sum::<f64>() / w.len() as f64)
        })
        .collect()
}

/// The table behind an input: a file, or a run folder's train_metrics,
/// with its kind (`skillaug.table` metadata).
///
/// # Errors
/// A file that cannot be read or is not a skillaug table.
pub fn resolve(p: &Path) -> Result<(PathBuf, String)> {
    let file = if p.is_dir() {
        p.join("train_metrics.parquet")
    } else {
        p.to_path_buf()
    };
    let meta = super::io::read_metadata(&file)?;
    let kind = meta
        .iter()
        .find(|(k, _)| k == "skillaug.table")
        .map(|(_, v)| v.clone())
        .with_context(|| {
            format!(
                "{}: not a skillaug table (no skillaug.table metadata)",
                file.display()
            )
        })?;
    Ok((file, kind))
}

/// Edge counts per masked-state count N, ascending N.
pub fn n_histogram(path: &Path) -> Result<Vec<(u32, u32)>> {
    let g = super::io::read_frame(path)?
        .lazy()
        .group_by([col("n_masked")])
        .agg([len().alias("edges")])
        .sort(["n_masked"], SortMultipleOptions::default())
        .collect()
        .with_context(|| format!("{}: histogram of n_masked", path.display()))?;
    let n = super::io::frame_u32s(&g, "n_masked")?;
    let e = super::io::frame_u32s(&g, "edges")?;
    Ok(n.into_iter().zip(e).collect())
}

/// One eval cell as a bar.
#[derive(Clone, Debug, PartialEq)]
pub struct EvalBar {
    /// Method label (the series).
    pub label: String,
    /// The cell: `metric from` or `metric from>to` (the category).
    pub cell: String,
    /// Success rate, or NR's mean SM reward per step.
    pub value: f64,
    /// The 95 % Wilson interval (none for NR).
    pub interval: Option<(f64, f64)>,
}

/// The cells of an eval summary, one bar each.
///
/// # Errors
/// A file that is not an eval summary.
pub fn eval_bars(path: &Path) -> Result<Vec<EvalBar>> {
    use super::eval::summary_frame;
    use super::io::{frame_f64s, frame_strs};
    let df = summary_frame(path)?;
    let s = |c: &str| frame_strs(&df, c);
    let f = |c: &str| frame_f64s(&df, c);
    let (label, metric) = (s("label")?, s("metric")?);
    let (from, to) = (s("from_skill")?, s("to_skill")?);
    let (v, lo, hi) = (f("value")?, f("ci_low")?, f("ci_high")?);
    Ok((0..df.height())
        .map(|i| {
            let name = if from[i] == to[i] {
                format!("{} {}", metric[i], from[i])
            } else {
                format!("{} {}>{}", metric[i], from[i], to[i])
            };
            EvalBar {
                label: label[i].clone(),
                cell: name,
                value: v[i],
                interval: (lo[i].is_finite() && hi[i].is_finite()).then_some((lo[i], hi[i])),
            }
        })
        .collect())
}
