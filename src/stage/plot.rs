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
//! The series come from [`crate::table::series`].

use crate::plot::{write_bars_png, write_png, BarChart, BarSeries, Chart, Series};
use crate::table::series::{curve_of, eval_cells, n_histogram, resolve, smooth, Cell};
use anyhow::{bail, Result};
use std::path::{Path, PathBuf};

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
