//! `skillaug plot`: figures from skillaug tables as PNG files. The kind of
//! figure follows the table (its `skillaug.table` metadata):
//!
//! * `train_metrics` (or a run folder holding one): a line per run of any
//!   metric column over samples (default `mean_sm_reward`; also
//!   `mean_episode_length`, `samples_per_s`, `fall_rate`, ...);
//! * `he_loss`: the history encoder's loss over optimiser steps (default
//!   `total`; also `prediction`, `regulariser`);
//! * `stg_edges`: the histogram of the masked-state counts N (Eq. 20) of
//!   the graph's edges, a bar per N and a series per file;
//! * `eval_summary`: a bar per cell (metric, from, to) with its 95 % Wilson
//!   interval, a series per method label.
//!
//! Histograms are counted and eval summaries read with polars.

use crate::plot::{write_bars_png, write_png, BarChart, BarSeries, Chart, Series};
use anyhow::{bail, Context, Result};
use arrow::array::{Array, Float64Array};
use arrow::datatypes::DataType;
use polars::prelude::{col, len, IntoLazy, SortMultipleOptions};
use std::path::{Path, PathBuf};

/// (x, value) of `metric` against the numeric column `x` of a table.
pub fn curve_of(path: &Path, x: &str, metric: &str) -> Result<Vec<(f64, f64)>> {
    let t = crate::table::io::read_parquet(path)?;
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
fn smooth(v: &[(f64, f64)], k: usize) -> Vec<(f64, f64)> {
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

/// The table behind an input: a file, or a run folder's train_metrics.
fn resolve(p: &Path) -> Result<(PathBuf, String)> {
    let file = if p.is_dir() {
        p.join("train_metrics.parquet")
    } else {
        p.to_path_buf()
    };
    let meta = crate::table::io::read_metadata(&file)?;
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
    let g = crate::table::io::read_frame(path)?
        .lazy()
        .group_by([col("n_masked")])
        .agg([len().alias("edges")])
        .sort(["n_masked"], SortMultipleOptions::default())
        .collect()
        .with_context(|| format!("{}: histogram of n_masked", path.display()))?;
    let n = crate::table::io::frame_u32s(&g, "n_masked")?;
    let e = crate::table::io::frame_u32s(&g, "edges")?;
    Ok(n.into_iter().zip(e).collect())
}

/// One bar per eval cell: (label, cell, value, interval).
type Cell = (String, String, f64, Option<(f64, f64)>);

fn eval_cells(path: &Path) -> Result<Vec<Cell>> {
    use crate::table::eval::summary_frame;
    use crate::table::io::{frame_f64s, frame_strs};
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
            let iv = (lo[i].is_finite() && hi[i].is_finite()).then_some((lo[i], hi[i]));
            (label[i].clone(), name, v[i], iv)
        })
        .collect())
}

/// What to draw and how.
pub struct PlotRequest<'a> {
    /// Tables (or run folders holding train_metrics.parquet).
    pub inputs: &'a [PathBuf],
    /// Series labels, one per input (default: folder or file names).
    pub labels: &'a [String],
    /// Column to draw (curves; default per table kind).
    pub metric: Option<&'a str>,
    /// Moving average over this many points (curves).
    pub smooth: usize,
    /// Horizontal goal lines (curves).
    pub goals: &'a [f64],
    /// Title (default per table kind).
    pub title: Option<&'a str>,
    /// The PNG to write.
    pub out: &'a Path,
}

/// Run the command.
pub fn run(req: &PlotRequest<'_>) -> Result<()> {
    if req.inputs.is_empty() {
        bail!("plot: give at least one skillaug table or run folder");
    }
    let mut kinds = Vec::new();
    for p in req.inputs {
        kinds.push(resolve(p)?);
    }
    let kind = kinds[0].1.clone();
    if let Some((f, k)) = kinds.iter().find(|(_, k)| *k != kind) {
        bail!(
            "{} is a `{k}` table and {} a `{kind}` table: plot tables of one kind together",
            f.display(),
            kinds[0].0.display()
        );
    }
    let label_of = |i: usize| -> String {
        req.labels.get(i).cloned().unwrap_or_else(|| {
            let p = &req.inputs[i];
            let p = if p.is_dir() {
                p.as_path()
            } else {
                p.parent().unwrap_or(p)
            };
            p.file_name()
                .map_or("run".into(), |s| s.to_string_lossy().into_owned())
        })
    };
    match kind.as_str() {
        "train_metrics" | "he_loss" => {
            let (x, default, xl) = if kind == "he_loss" {
                ("step", "total", "optimiser step")
            } else {
                ("samples", "mean_sm_reward", "samples")
            };
            let metric = req.metric.unwrap_or(default);
            let mut series = Vec::new();
            for (i, (file, _)) in kinds.iter().enumerate() {
                series.push(Series {
                    label: label_of(i),
                    points: smooth(&curve_of(file, x, metric)?, req.smooth),
                });
            }
            let chart = Chart {
                title: req.title.unwrap_or(metric).to_string(),
                x_label: xl.into(),
                y_label: if req.smooth > 1 {
                    format!("{metric} (mean of {})", req.smooth)
                } else {
                    metric.to_string()
                },
                series,
                hlines: req.goals.iter().map(|g| (*g, format!("{g}"))).collect(),
            };
            write_png(&chart, req.out)?;
        }
        "stg_edges" => {
            let hists: Vec<Vec<(u32, u32)>> = kinds
                .iter()
                .map(|(f, _)| n_histogram(f))
                .collect::<Result<_>>()?;
            let top = hists.iter().flatten().map(|h| h.0).max().unwrap_or(0);
            let chart = BarChart {
                title: req
                    .title
                    .unwrap_or("STG masked states per edge")
                    .to_string(),
                x_label: "masked states N (Eq. 20)".into(),
                y_label: "edges".into(),
                categories: (0..=top).map(|n| n.to_string()).collect(),
                series: hists
                    .iter()
                    .enumerate()
                    .map(|(i, h)| BarSeries {
                        label: label_of(i),
                        values: (0..=top)
                            .map(|n| {
                                let c = h.iter().find(|x| x.0 == n).map_or(0, |x| x.1);
                                (c as f64, None)
                            })
                            .collect(),
                    })
                    .collect(),
            };
            write_bars_png(&chart, req.out)?;
        }
        "eval_summary" => {
            let mut cells: Vec<Cell> = Vec::new();
            for (f, _) in &kinds {
                cells.extend(eval_cells(f)?);
            }
            let mut cats: Vec<String> = Vec::new();
            let mut labels: Vec<String> = Vec::new();
            for c in &cells {
                if !cats.contains(&c.1) {
                    cats.push(c.1.clone());
                }
                if !labels.contains(&c.0) {
                    labels.push(c.0.clone());
                }
            }
            let series = labels
                .iter()
                .map(|l| BarSeries {
                    label: l.clone(),
                    values: cats
                        .iter()
                        .map(|cat| {
                            cells
                                .iter()
                                .find(|c| &c.0 == l && &c.1 == cat)
                                .map_or((f64::NAN, None), |c| (c.2, c.3))
                        })
                        .collect(),
                })
                .collect();
            let chart = BarChart {
                title: req.title.unwrap_or("eval summary").to_string(),
                x_label:
                    "cell (SR / TSR / NSR: success rate with 95 % interval; NR: mean SM reward)"
                        .into(),
                y_label: "value".into(),
                categories: cats,
                series,
            };
            write_bars_png(&chart, req.out)?;
        }
        other => bail!(
            "plot draws train_metrics, he_loss, stg_edges and eval_summary tables; {} is `{other}`",
            kinds[0].0.display()
        ),
    }
    println!("wrote {}", req.out.display());
    Ok(())
}
