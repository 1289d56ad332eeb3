//! `skillaug plot`: training curves from one or more `train_metrics.parquet`
//! files (or run folders holding one) as a PNG line chart.

use crate::plot::{write_png, Chart, Series};
use anyhow::{bail, Context, Result};
use arrow::array::{AsArray, Float64Array};
use arrow::datatypes::UInt64Type;
use std::path::{Path, PathBuf};

/// (samples, value) of `metric` in a metrics file.
pub fn curve(path: &Path, metric: &str) -> Result<Vec<(f64, f64)>> {
    let t = crate::table::io::read_parquet(path)?;
    let mut v = Vec::new();
    for b in &t.batches {
        let s = b
            .column_by_name("samples")
            .and_then(|c| c.as_primitive_opt::<UInt64Type>())
            .with_context(|| {
                format!(
                    "{}: no u64 column `samples`: not a train_metrics table",
                    path.display()
                )
            })?;
        let m = b
            .column_by_name(metric)
            .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
            .with_context(|| {
                format!(
                    "{}: no Float64 column `{metric}` (see `skillaug schema train_metrics`)",
                    path.display()
                )
            })?;
        v.extend(
            s.values()
                .iter()
                .zip(m.values())
                .map(|(a, b)| (*a as f64, *b)),
        );
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

/// Run the command.
pub fn run(
    inputs: &[PathBuf],
    labels: &[String],
    metric: &str,
    smooth_k: usize,
    goals: &[f64],
    title: Option<&str>,
    out: &Path,
) -> Result<()> {
    if inputs.is_empty() {
        bail!("plot: give at least one train_metrics.parquet or run folder");
    }
    let mut series = Vec::new();
    for (i, p) in inputs.iter().enumerate() {
        let file = if p.is_dir() {
            p.join("train_metrics.parquet")
        } else {
            p.clone()
        };
        let pts = curve(&file, metric)?;
        let label = labels.get(i).cloned().unwrap_or_else(|| {
            p.file_name()
                .map_or("run".into(), |s| s.to_string_lossy().into_owned())
        });
        series.push(Series {
            label,
            points: smooth(&pts, smooth_k),
        });
    }
    let chart = Chart {
        title: title.unwrap_or(metric).to_string(),
        x_label: "samples".into(),
        y_label: if smooth_k > 1 {
            format!("{metric} (mean of {smooth_k})")
        } else {
            metric.to_string()
        },
        series,
        hlines: goals.iter().map(|g| (*g, format!("{g}"))).collect(),
    };
    write_png(&chart, out)?;
    println!("wrote {}", out.display());
    Ok(())
}
