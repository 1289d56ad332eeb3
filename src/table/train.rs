//! `train_metrics.parquet`: one row per PPO iteration of `skillaug train`.

use super::columns::{specs, Column, TableRow};
use super::ColumnSpec;
use anyhow::Result;
use arrow::record_batch::RecordBatch;
use serde::{Deserialize, Serialize};

/// Declares [`Metrics`] (one named `f64` field per metric column),
/// [`METRICS`] (name and meaning of each, in column order) and their
/// conversions from one list, so that a column, its schema entry and the
/// field the trainer fills cannot drift apart.
macro_rules! metrics {
    ($($name:ident: $doc:literal,)*) => {
        /// One iteration's metrics, by name (the Float64 columns of
        /// `train_metrics.parquet` after `iteration` and `samples`).
        #[derive(Clone, Debug, Default, PartialEq)]
        pub struct Metrics {
            $(#[doc = $doc] pub $name: f64,)*
        }

        /// The Float64 metric columns after `iteration` and `samples`, in
        /// order: (name, meaning).
        pub const METRICS: &[(&str, &str)] = &[$((stringify!($name), $doc),)*];

        impl Metrics {
            /// The values in [`METRICS`] order.
            pub fn values(&self) -> Vec<f64> {
                vec![$(self.$name,)*]
            }

            /// From values in [`METRICS`] order (`None` for another count).
            pub fn from_values(v: &[f64]) -> Option<Metrics> {
                let mut it = v.iter().copied();
                let m = Metrics { $($name: it.next()?,)* };
                it.next().is_none().then_some(m)
            }

            /// The value of metric `name` (`None` for an unknown name).
            pub fn get(&self, name: &str) -> Option<f64> {
                match name {
                    $(stringify!($name) => Some(self.$name),)*
                    _ => None,
                }
            }
        }
    };
}

metrics! {
    mean_reward: "mean training reward per unmasked step of the iteration's rollout (SM or DM)",
    mean_sm_reward: "mean SM reward per unmasked step (the common yardstick for every method)",
    fall_rate: "fraction of the episodes finished in the iteration that ended by a fall",
    episodes: "episodes finished in the iteration",
    mean_episode_length: "mean length of those episodes, policy steps",
    mean_return: "mean undiscounted return of those episodes (NaN if none)",
    masked_frac: "fraction of steps that were masked (no reward of their own)",
    stg_start_frac: "fraction of the iteration's starts from the Stitched Trajectory Graph (NaN without starts)",
    noised_start_frac: "fraction of the iteration's starts from an epsilon-neighbourhood (NaN without starts)",
    mean_n_masked: "mean masked-state count N of the iteration's starts (NaN without starts)",
    policy_loss: "clipped surrogate loss, mean over minibatches",
    value_loss: "value loss (squared error), mean over minibatches",
    bounds_loss: "bounds loss on the action mean",
    clip_frac: "fraction of samples whose ratio left [1 - eps, 1 + eps]",
    approx_kl: "approximate KL divergence old to new policy",
    lr: "learning rate after the update (the adaptive rate with train.ppo.kl_threshold)",
    mean_sm_body: "mean SM body factor r_b per unmasked step",
    mean_sm_object: "mean SM object factor r_o per unmasked step",
    mean_sm_rel: "mean SM relative-motion factor r_rel per unmasked step",
    mean_sm_contact: "mean SM contact-graph factor r_cg per unmasked step",
    lost_rate: "fraction of the finished episodes ended by a tracking failure (key points or ball too far)",
    lost_object_rate: "fraction of the finished episodes ended because the ball left the character while the reference kept it",
    sim_start_frac: "fraction of the iteration's starts from states rollouts reached (train.sim_start_prob; NaN without starts)",
    continued_frac: "fraction of the finished episodes whose reference continued past a clip's end (NaN if none finished)",
    samples_per_s: "end-to-end samples per second of the iteration",
    sim_s: "seconds in the environment (physics, observation, reward, resets)",
    act_s: "seconds in policy and value inference during the rollout",
    update_s: "seconds in the PPO update",
}

/// One iteration's row (kept in checkpoints as JSON, its metrics as a list
/// in [`METRICS`] order with NaN as null).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(into = "RowRepr", try_from = "RowRepr")]
pub struct MetricRow {
    /// Iteration, from 1.
    pub iteration: u64,
    /// Samples collected so far, including this iteration.
    pub samples: u64,
    /// The metrics.
    pub metrics: Metrics,
}

impl MetricRow {
    /// The row as one log line (what `skillaug train` prints per iteration
    /// when it has no terminal for a progress bar).
    pub fn log_line(&self) -> String {
        let m = &self.metrics;
        format!(
            "iter {:>5} samples {:>9} reward {:.4} sm {:.4} len {:5.1} falls {:5.1}% {:.0} samples/s (sim {:.1} s, act {:.1} s, update {:.1} s)",
            self.iteration,
            self.samples,
            m.mean_reward,
            m.mean_sm_reward,
            m.mean_episode_length,
            100.0 * m.fall_rate,
            m.samples_per_s,
            m.sim_s,
            m.act_s,
            m.update_s
        )
    }
}

#[derive(Serialize, Deserialize)]
struct RowRepr {
    iteration: u64,
    samples: u64,
    #[serde(with = "nan_as_null")]
    values: Vec<f64>,
}

impl From<MetricRow> for RowRepr {
    fn from(r: MetricRow) -> RowRepr {
        RowRepr {
            iteration: r.iteration,
            samples: r.samples,
            values: r.metrics.values(),
        }
    }
}

impl TryFrom<RowRepr> for MetricRow {
    type Error = String;
    fn try_from(r: RowRepr) -> Result<MetricRow, String> {
        let n = r.values.len();
        Ok(MetricRow {
            iteration: r.iteration,
            samples: r.samples,
            metrics: Metrics::from_values(&r.values).ok_or_else(|| {
                format!(
                    "a metrics row of {n} values, expected {} (a checkpoint of another version)",
                    METRICS.len()
                )
            })?,
        })
    }
}

/// JSON has no NaN: store it as null (checkpoints keep the metric rows).
mod nan_as_null {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(v: &[f64], s: S) -> Result<S::Ok, S::Error> {
        let o: Vec<Option<f64>> = v.iter().map(|x| (!x.is_nan()).then_some(*x)).collect();
        o.serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
        let o: Vec<Option<f64>> = Vec::deserialize(d)?;
        Ok(o.into_iter().map(|x| x.unwrap_or(f64::NAN)).collect())
    }
}

impl MetricRow {
    /// The value of metric `name` (None for an unknown name).
    pub fn get(&self, name: &str) -> Option<f64> {
        self.metrics.get(name)
    }
}

impl TableRow for MetricRow {
    fn columns() -> Vec<Column<MetricRow>> {
        let mut v = vec![
            Column::new("iteration", "PPO iteration, from 1", |r: &MetricRow| {
                r.iteration
            }),
            Column::new(
                "samples",
                "samples collected so far (environment steps over all environments)",
                |r: &MetricRow| r.samples,
            ),
        ];
        for &(name, doc) in METRICS {
            v.push(Column::new(name, doc, move |r: &MetricRow| {
                r.metrics.get(name).unwrap_or(f64::NAN)
            }));
        }
        v
    }
}

/// Columns of `train_metrics.parquet`.
pub fn columns() -> Vec<ColumnSpec> {
    specs::<MetricRow>()
}

/// The record batch of `rows`.
pub fn batch(rows: &[MetricRow]) -> Result<RecordBatch> {
    super::columns::batch(rows)
}
