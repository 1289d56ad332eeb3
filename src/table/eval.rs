//! `eval_trials.parquet` (one row per trial) and `eval_summary.parquet`
//! (one row per evaluation cell) of `skillaug eval`.

use super::columns::{specs, Column, TableRow};
use super::ColumnSpec;
use anyhow::Result;
use arrow::record_batch::RecordBatch;
use polars::prelude::DataFrame;

/// An evaluation metric: the `metric` column of the eval tables.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Metric {
    /// Success rate from the skill's own frames ("sr").
    Sr,
    /// Transition success rate from another skill's frames ("tsr").
    Tsr,
    /// epsilon-neighbourhood success rate ("nsr").
    Nsr,
    /// Mean SM reward per step, no success rule ("nr").
    Nr,
}

impl Metric {
    /// Every metric.
    pub const ALL: [Metric; 4] = [Metric::Sr, Metric::Tsr, Metric::Nsr, Metric::Nr];

    /// The name in the tables and settings: "sr", "tsr", "nsr" or "nr".
    pub fn as_str(self) -> &'static str {
        match self {
            Metric::Sr => "sr",
            Metric::Tsr => "tsr",
            Metric::Nsr => "nsr",
            Metric::Nr => "nr",
        }
    }

    /// The metric named `name` ([`Metric::as_str`]), if any.
    pub fn from_name(name: &str) -> Option<Metric> {
        Metric::ALL.into_iter().find(|m| m.as_str() == name)
    }
}

impl std::fmt::Display for Metric {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // pad: the summary's text table gives the metric a width
        f.pad(self.as_str())
    }
}

/// One trial.
#[derive(Clone, Debug, PartialEq)]
pub struct TrialRow {
    /// The cell's metric.
    pub metric: Metric,
    /// Skill of the start frames.
    pub from: String,
    /// Skill of the condition and the rule.
    pub to: String,
    /// Trial index within the cell.
    pub trial: u32,
    /// Verdict of the rule (None for NR).
    pub success: Option<bool>,
    /// Policy steps.
    pub steps: u32,
    /// Mean SM reward per unmasked step (NaN when none).
    pub mean_sm: f64,
    /// Root height at the end, m.
    pub final_root_z: f32,
    /// First step at which the root was at or below the rule's standing
    /// height (None: it stood throughout, or an nr trial).
    pub down_step: Option<u32>,
    /// Highest point of object 0 over the trial's last
    /// [`LATE_APEX_STEPS`] policy steps, m (NaN without an object): for a
    /// dribble, whether the ball still bounces at the end (a ball at rest
    /// lies at its radius, 0.12 m), which the dribble rule does not ask.
    pub late_obj_apex: f32,
}

/// Steps at the end of a trial over which [`TrialRow::late_obj_apex`] is taken.
pub const LATE_APEX_STEPS: usize = 100;

/// A step at which the summary gives the fraction of trials still
/// standing, with its column of `eval_summary.parquet`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Standing {
    /// Policy steps.
    pub at: u32,
    /// Column name: `standing_{at}`.
    pub column: &'static str,
    /// Column meaning.
    pub doc: &'static str,
}

/// [`Standing`] entries of the steps given, names and meanings derived
/// from the step.
macro_rules! standing {
    ($first:literal $(, $at:literal)*) => {
        [
            Standing {
                at: $first,
                column: concat!("standing_", $first),
                doc: concat!(
                    "fraction of the trials still standing after ",
                    $first,
                    " policy steps (NaN for nr or shorter trials)"
                ),
            },
            $(Standing {
                at: $at,
                column: concat!("standing_", $at),
                doc: concat!("the same after ", $at, " steps"),
            },)*
        ]
    };
}

/// Steps at which the summary gives the fraction of trials still standing.
pub const STANDING_AT: [Standing; 4] = standing!(100, 200, 400, 600);

/// One cell.
#[derive(Clone, Debug, PartialEq)]
pub struct SummaryRow {
    /// Method label.
    pub label: String,
    /// Metric.
    pub metric: Metric,
    /// Start skill.
    pub from: String,
    /// Target skill.
    pub to: String,
    /// Trials.
    pub trials: u32,
    /// Policy steps of the cell's longest trial (the trial length).
    pub trial_steps: u32,
    /// Successes (0 for NR).
    pub successes: u32,
    /// Success rate (NR: the mean SM reward per step).
    pub value: f64,
    /// 95 % Wilson interval (NaN for NR).
    pub lo: f64,
    /// Upper end.
    pub hi: f64,
    /// Fraction of the trials still standing (root above the rule's
    /// height at every step so far) at each step of [`STANDING_AT`]; NaN for
    /// nr or when the trials are shorter.
    pub standing: [f64; STANDING_AT.len()],
}

/// A trial with its method's label: one row of `eval_trials.parquet`.
struct LabelledTrial {
    label: String,
    trial: TrialRow,
}

impl TableRow for LabelledTrial {
    fn columns() -> Vec<Column<LabelledTrial>> {
        type R = LabelledTrial;
        vec![
            Column::new("label", "method label of the evaluated policy (e.g. SM+STG+STF+ATS+HE)", |r: &R| r.label.clone()),
            Column::new("metric", "sr, tsr, nsr (epsilon-NSR) or nr", |r: &R| r.trial.metric.as_str()),
            Column::new("from_skill", "skill whose reference frames start the trial", |r: &R| r.trial.from.clone()),
            Column::new("to_skill", "skill of the condition and of the success rule", |r: &R| r.trial.to.clone()),
            Column::new("trial", "trial index within the cell", |r: &R| r.trial.trial),
            Column::new("success", "verdict of the success rule (null for nr)", |r: &R| r.trial.success),
            Column::new("steps", "policy steps of the trial", |r: &R| r.trial.steps),
            Column::new("mean_sm", "mean SM reward per step with a reference frame (NaN if none)", |r: &R| r.trial.mean_sm),
            Column::new("final_root_z", "root height at the end of the trial, m", |r: &R| r.trial.final_root_z),
            Column::new("down_step", "first policy step at which the root was at or below the rule's standing height (0.5 m; 0.7 for getup and run_no_object); null if it stood throughout or for nr", |r: &R| r.trial.down_step),
            Column::new("late_obj_apex", "highest point of object 0 over the last 100 policy steps of the trial, m (NaN without an object; a ball at rest lies at 0.12 m)", |r: &R| r.trial.late_obj_apex),
        ]
    }
}

impl TableRow for SummaryRow {
    fn columns() -> Vec<Column<SummaryRow>> {
        type R = SummaryRow;
        let mut v = vec![
            Column::new("label", "method label", |r: &R| r.label.clone()),
            Column::new("metric", "sr, tsr, nsr or nr", |r: &R| r.metric.as_str()),
            Column::new("from_skill", "start skill", |r: &R| r.from.clone()),
            Column::new("to_skill", "condition / rule skill", |r: &R| r.to.clone()),
            Column::new("trials", "trials in the cell", |r: &R| r.trials),
            Column::new("trial_steps", "policy steps of the cell's longest trial (the trial length); a trial shorter than its success rule's phases is never a success", |r: &R| r.trial_steps),
            Column::new("successes", "successful trials (0 for nr)", |r: &R| r.successes),
            Column::new("value", "success rate in [0, 1]; for nr the mean SM reward per step", |r: &R| r.value),
            Column::new("ci_low", "95 % Wilson interval, lower end (NaN for nr)", |r: &R| r.lo),
            Column::new("ci_high", "95 % Wilson interval, upper end (NaN for nr)", |r: &R| r.hi),
        ];
        for (k, s) in STANDING_AT.iter().enumerate() {
            v.push(Column::new(s.column, s.doc, move |r: &R| r.standing[k]));
        }
        v
    }
}

/// Columns of `eval_trials.parquet`.
pub fn trial_columns() -> Vec<ColumnSpec> {
    specs::<LabelledTrial>()
}

/// Columns of `eval_summary.parquet`.
pub fn summary_columns() -> Vec<ColumnSpec> {
    specs::<SummaryRow>()
}

/// The trials of the method `label` as a record batch.
pub fn trials_batch(label: &str, rows: &[TrialRow]) -> Result<RecordBatch> {
    let rows: Vec<LabelledTrial> = rows
        .iter()
        .map(|t| LabelledTrial {
            label: label.to_string(),
            trial: t.clone(),
        })
        .collect();
    super::columns::batch(&rows)
}

/// The summary as a record batch.
pub fn summary_batch(rows: &[SummaryRow]) -> Result<RecordBatch> {
    super::columns::batch(rows)
}

/// An `eval_summary` file as a polars frame, its columns checked.
pub fn summary_frame(path: &std::path::Path) -> Result<DataFrame> {
    let df = super::io::read_frame(path)?;
    // the standing fractions and the trial length came later: summaries
    // without them still read
    for c in summary_columns()
        .into_iter()
        .filter(|c| !STANDING_AT.iter().any(|s| s.column == c.name) && c.name != "trial_steps")
    {
        if df.column(c.name).is_err() {
            anyhow::bail!(
                "{}: no column `{}`: not an eval_summary table",
                path.display(),
                c.name
            );
        }
    }
    Ok(df)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metrics_are_named_as_in_the_tables_and_pad_in_text() {
        for m in Metric::ALL {
            assert_eq!(Metric::from_name(m.as_str()), Some(m));
        }
        assert_eq!(Metric::from_name("xsr"), None);
        assert_eq!(
            format!("{:<6}|{:>4}", Metric::Nr, Metric::Sr),
            "nr    |  sr"
        );
    }

    #[test]
    fn standing_columns_follow_their_steps() {
        let names: Vec<&str> = STANDING_AT.iter().map(|s| s.column).collect();
        assert_eq!(
            names,
            [
                "standing_100",
                "standing_200",
                "standing_400",
                "standing_600"
            ]
        );
        let cols = summary_columns();
        assert_eq!(
            &cols[cols.len() - STANDING_AT.len()..][0].name,
            &"standing_100"
        );
    }
}
