//! `skillaug plot`: figures from skillaug tables as PNG files. The kind of
//! figure follows the table (its `skillaug.table` metadata; a run folder
//! stands for its `train_metrics.parquet`): lines for `train_metrics` (any
//! metric column over samples: `mean_sm_reward`, `mean_episode_length`,
//! `samples_per_s`, `fall_rate`, ...) and `he_loss`, bars for `stg_edges`
//! and `eval_summary` ([`crate::plot::figures`]).

use crate::plot::figures::{figure, FigureOptions};
use crate::table::series::resolve;
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
    let inputs: Vec<(PathBuf, String)> = kinds
        .iter()
        .enumerate()
        .map(|(i, (file, _))| (file.clone(), label_of(i)))
        .collect();
    let opt = FigureOptions {
        metric: req.metric.map(str::to_string),
        smooth: req.smooth,
        goals: req.goals.to_vec(),
        title: req.title.map(str::to_string),
    };
    figure(&kind, &inputs, &opt)?.write_png(req.out)?;
    println!("wrote {}", req.out.display());
    Ok(())
}
