//! The charts of `skillaug plot`, assembled from skillaug tables (the
//! series come from [`crate::table::series`]; [`super`] draws them):
//!
//! * `train_metrics`: a line per run of a metric column over samples
//!   (default `mean_sm_reward`);
//! * `he_loss`: the history encoder's loss over optimiser steps (default
//!   `total`);
//! * `stg_edges`: the histogram of the masked-state counts N (Eq. 20) of
//!   the graph's edges, a bar per N and a series per file;
//! * `eval_summary`: a bar per cell (metric, from, to) with its 95 % Wilson
//!   interval, a series per method label.

use super::{write_bars_png, write_png, BarChart, BarSeries, Chart, Series};
use crate::table::series::{curve_of, eval_bars, n_histogram, smooth, EvalBar};
use anyhow::{bail, Result};
use std::path::{Path, PathBuf};

/// How to draw: the choices of `skillaug plot` besides its inputs.
#[derive(Clone, Debug, Default)]
pub struct FigureOptions {
    /// Column to draw (curves; default per table kind).
    pub metric: Option<String>,
    /// Moving average over this many points (curves; 0 or 1: none).
    pub smooth: usize,
    /// Horizontal goal lines (curves).
    pub goals: Vec<f64>,
    /// Title (default per table kind).
    pub title: Option<String>,
}

/// A chart of either kind.
pub enum Figure {
    /// Lines over samples or steps.
    Lines(Chart),
    /// Grouped bars.
    Bars(BarChart),
}

impl Figure {
    /// Write the chart as a PNG at `path`.
    ///
    /// # Errors
    /// As [`write_png`] and [`write_bars_png`].
    pub fn write_png(&self, path: &Path) -> Result<()> {
        match self {
            Figure::Lines(c) => write_png(c, path),
            Figure::Bars(c) => write_bars_png(c, path),
        }
    }
}

/// The chart of tables of one kind `kind` (their `skillaug.table`):
/// `inputs` are (table file, series label) pairs.
///
/// # Errors
/// A kind `plot` does not draw, or a table that cannot be read.
pub fn figure(kind: &str, inputs: &[(PathBuf, String)], opt: &FigureOptions) -> Result<Figure> {
    Ok(match kind {
        "train_metrics" | "he_loss" => Figure::Lines(curves(kind, inputs, opt)?),
        "stg_edges" => Figure::Bars(n_histograms(inputs, opt)?),
        "eval_summary" => Figure::Bars(eval_summaries(inputs, opt)?),
        other => {
            bail!(
            "plot draws train_metrics, he_loss, stg_edges and eval_summary tables; {} is `{other}`",
            inputs.first().map_or(String::new(), |i| i.0.display().to_string())
        )
        }
    })
}

/// A line per table of a metric over samples (`train_metrics`) or
/// optimiser steps (`he_loss`), smoothed by a moving average.
fn curves(kind: &str, inputs: &[(PathBuf, String)], opt: &FigureOptions) -> Result<Chart> {
    let (x, default, xl) = if kind == "he_loss" {
        ("step", "total", "optimiser step")
    } else {
        ("samples", "mean_sm_reward", "samples")
    };
    let metric = opt.metric.as_deref().unwrap_or(default);
    let mut series = Vec::new();
    for (file, label) in inputs {
        series.push(Series {
            label: label.clone(),
            points: smooth(&curve_of(file, x, metric)?, opt.smooth),
        });
    }
    Ok(Chart {
        title: opt.title.as_deref().unwrap_or(metric).to_string(),
        x_label: xl.into(),
        y_label: if opt.smooth > 1 {
            format!("{metric} (mean of {})", opt.smooth)
        } else {
            metric.to_string()
        },
        series,
        hlines: opt.goals.iter().map(|g| (*g, format!("{g}"))).collect(),
    })
}

/// Edges per masked-state count N: a bar per N (0 to the largest in any
/// table), a series per table.
fn n_histograms(inputs: &[(PathBuf, String)], opt: &FigureOptions) -> Result<BarChart> {
    let hists: Vec<Vec<(u32, u32)>> = inputs
        .iter()
        .map(|(f, _)| n_histogram(f))
        .collect::<Result<_>>()?;
    let top = hists.iter().flatten().map(|h| h.0).max().unwrap_or(0);
    Ok(BarChart {
        title: opt
            .title
            .as_deref()
            .unwrap_or("STG masked states per edge")
            .to_string(),
        x_label: "masked states N (Eq. 20)".into(),
        y_label: "edges".into(),
        categories: (0..=top).map(|n| n.to_string()).collect(),
        series: hists
            .iter()
            .zip(inputs)
            .map(|(h, (_, label))| BarSeries {
                label: label.clone(),
                values: (0..=top)
                    .map(|n| {
                        let c = h.iter().find(|x| x.0 == n).map_or(0, |x| x.1);
                        (c as f64, None)
                    })
                    .collect(),
            })
            .collect(),
    })
}

/// A bar per eval cell (in the order the tables list them), a series per
/// method label, whiskers at the Wilson interval.
fn eval_summaries(inputs: &[(PathBuf, String)], opt: &FigureOptions) -> Result<BarChart> {
    let mut bars: Vec<EvalBar> = Vec::new();
    for (f, _) in inputs {
        bars.extend(eval_bars(f)?);
    }
    let mut cats: Vec<String> = Vec::new();
    let mut labels: Vec<String> = Vec::new();
    for b in &bars {
        if !cats.contains(&b.cell) {
            cats.push(b.cell.clone());
        }
        if !labels.contains(&b.label) {
            labels.push(b.label.clone());
        }
    }
    let series = labels
        .iter()
        .map(|l| BarSeries {
            label: l.clone(),
            values: cats
                .iter()
                .map(|cat| {
                    bars.iter()
                        .find(|b| &b.label == l && &b.cell == cat)
                        .map_or((f64::NAN, None), |b| (b.value, b.interval))
                })
                .collect(),
        })
        .collect();
    Ok(BarChart {
        title: opt.title.as_deref().unwrap_or("eval summary").to_string(),
        x_label: "cell (SR / TSR / NSR: success rate with 95 % interval; NR: mean SM reward)"
            .into(),
        y_label: "value".into(),
        categories: cats,
        series,
    })
}
