//! The per-cell summary of an evaluation (`eval_summary.parquet`): success
//! counts and rates with their 95 % Wilson intervals, the mean SM reward per
//! step for NR, and the share of trials still standing at the steps of
//! [`STANDING_AT`]; and its plain text table.

use crate::table::eval::{Metric, Standing, SummaryRow, TrialRow, STANDING_AT};
use anyhow::{Context, Result};
use polars::prelude::{col, len, DataFrame, IntoLazy, NamedFrom, Series, SortMultipleOptions};

/// Wilson score interval of `k` successes in `n` trials at 95 %.
pub fn wilson(k: usize, n: usize) -> (f64, f64) {
    if n == 0 {
        return (f64::NAN, f64::NAN);
    }
    let z = 1.959_963_984_540_054_f64;
    let (n, p) = (n as f64, k as f64 / n as f64);
    let d = 1.0 + z * z / n;
    let c = (p + z * z / (2.0 * n)) / d;
    let h = z * ((p * (1.0 - p) / n + z * z / (4.0 * n * n)).sqrt()) / d;
    // exact ends (rounding would leave p = 1 just outside its own interval)
    ((c - h).clamp(0.0, p), (c + h).clamp(p, 1.0))
}

/// Per cell (metric, from, to): trial count, successes and the mean SM
/// reward per step (a polars group-by), then the rate and its Wilson interval.
pub fn summarise(label: &str, rows: &[TrialRow]) -> Result<Vec<SummaryRow>> {
    let strs = |f: &dyn Fn(&TrialRow) -> String| rows.iter().map(f).collect::<Vec<String>>();
    let df = DataFrame::new(
        rows.len(),
        vec![
            Series::new("metric".into(), strs(&|r| r.metric.to_string())).into(),
            Series::new("from".into(), strs(&|r| r.from.clone())).into(),
            Series::new("to".into(), strs(&|r| r.to.clone())).into(),
            Series::new(
                "ok".into(),
                rows.iter()
                    .map(|r| r.success.unwrap_or(false) as u32)
                    .collect::<Vec<u32>>(),
            )
            .into(),
            Series::new(
                "sm".into(),
                rows.iter()
                    .map(|r| (!r.mean_sm.is_nan()).then_some(r.mean_sm))
                    .collect::<Vec<Option<f64>>>(),
            )
            .into(),
        ],
    )?;
    let g = df
        .lazy()
        .group_by([col("metric"), col("from"), col("to")])
        .agg([
            len().alias("n"),
            col("ok").sum().alias("k"),
            col("sm").mean().alias("sm"),
        ])
        .sort(["metric", "from", "to"], SortMultipleOptions::default())
        .collect()
        .context("eval summary")?;
    use crate::table::io::{frame_f64s, frame_strs, frame_u32s};
    let (m, f, t) = (
        frame_strs(&g, "metric")?,
        frame_strs(&g, "from")?,
        frame_strs(&g, "to")?,
    );
    let (n, k) = (frame_u32s(&g, "n")?, frame_u32s(&g, "k")?);
    let sm = frame_f64s(&g, "sm")?;
    let mut out = Vec::with_capacity(m.len());
    for i in 0..m.len() {
        let metric = Metric::from_name(&m[i]).context("eval summary: a metric of no trial")?;
        let nr = metric == Metric::Nr;
        let (lo, hi) = if nr {
            (f64::NAN, f64::NAN)
        } else {
            wilson(k[i] as usize, n[i] as usize)
        };
        let cell: Vec<&TrialRow> = rows
            .iter()
            .filter(|r| r.metric == metric && r.from == f[i] && r.to == t[i])
            .collect();
        let standing = STANDING_AT.map(|Standing { at, .. }| {
            if nr || cell.is_empty() || cell.iter().any(|r| r.steps < at) {
                return f64::NAN;
            }
            let up = cell
                .iter()
                .filter(|r| r.down_step.is_none_or(|d| d > at))
                .count();
            up as f64 / cell.len() as f64
        });
        out.push(SummaryRow {
            standing,
            label: label.to_string(),
            metric,
            from: f[i].clone(),
            to: t[i].clone(),
            trials: n[i],
            trial_steps: cell.iter().map(|r| r.steps).max().unwrap_or(0),
            successes: if nr { 0 } else { k[i] },
            value: if nr {
                sm[i]
            } else {
                k[i] as f64 / n[i].max(1) as f64
            },
            lo,
            hi,
        });
    }
    Ok(out)
}

/// A plain text table of a summary.
pub fn render(rows: &[SummaryRow]) -> String {
    let mut s = format!(
        "{:<10} {:<6} {:<16} {:<16} {:>7} {:>6} {:>9} {:>17}  standing at {}\n",
        "method",
        "metric",
        "from",
        "to",
        "trials",
        "steps",
        "value",
        "95% interval",
        STANDING_AT.map(|s| s.at.to_string()).join("/")
    );
    for r in rows {
        let (v, ci) = if r.metric == Metric::Nr {
            (format!("{:.3}", r.value), String::new())
        } else {
            (
                format!("{:.1}%", 100.0 * r.value),
                format!("[{:.1}, {:.1}]%", 100.0 * r.lo, 100.0 * r.hi),
            )
        };
        let standing: Vec<String> = r
            .standing
            .iter()
            .filter(|x| !x.is_nan())
            .map(|x| format!("{:.0}%", 100.0 * x))
            .collect();
        s += &format!(
            "{:<10} {:<6} {:<16} {:<16} {:>7} {:>6} {:>9} {:>17}  {}\n",
            r.label,
            r.metric,
            r.from,
            r.to,
            r.trials,
            r.trial_steps,
            v,
            ci,
            standing.join(" / ")
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wilson_intervals_match_known_values() {
        let (lo, hi) = wilson(8, 10);
        assert!(
            (lo - 0.4902).abs() < 1e-3 && (hi - 0.9433).abs() < 1e-3,
            "{lo} {hi}"
        );
        let (lo, hi) = wilson(0, 8);
        assert!(lo == 0.0 && (hi - 0.3244).abs() < 1e-3);
        assert!(wilson(0, 0).0.is_nan());
    }

    #[test]
    fn the_text_table_names_its_standing_steps() {
        assert!(render(&[]).ends_with("standing at 100/200/400/600\n"));
    }
}
