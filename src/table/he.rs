//! `he_loss.parquet` and `he_embeddings.parquet`: the history encoder's
//! pre-training curve and the embedding of every reference frame.

use super::columns::F32Rows;
use super::{f32_fixed, schema_of, ColumnSpec};
use anyhow::Result;
use arrow::array::{ArrayRef, Float64Array, StringArray, UInt32Array};
use arrow::datatypes::DataType;
use arrow::record_batch::RecordBatch;
use std::sync::Arc;

/// Columns of `he_loss.parquet`.
pub fn loss_columns() -> Vec<ColumnSpec> {
    use DataType::*;
    vec![
        ColumnSpec::new("step", UInt32, false, "optimiser step, 0-based"),
        ColumnSpec::new("total", Float64, false, "loss of Eq. 23 on the step's minibatch: lambda_a * prediction + lambda_b * regulariser"),
        ColumnSpec::new("prediction", Float64, false, "mean squared error of the predicted next frame (standardised features)"),
        ColumnSpec::new("regulariser", Float64, false, "mean over the minibatch of |h|^2"),
    ]
}

/// Columns of `he_embeddings.parquet`.
pub fn embedding_columns() -> Vec<ColumnSpec> {
    use DataType::*;
    vec![
        ColumnSpec::new("clip_id", UInt32, false, "clip (clips.parquet clip_id)"),
        ColumnSpec::new(
            "frame",
            UInt32,
            false,
            "frame t; h is computed from frames [t-60, t)",
        ),
        ColumnSpec::new("skill", Utf8, false, "skill of the clip"),
        ColumnSpec::new(
            "h",
            f32_fixed(3),
            false,
            "embedding h_t of the trained, frozen encoder",
        ),
    ]
}

/// One logged optimiser step.
#[derive(Clone, Copy, Debug)]
pub struct LossRow {
    /// Step.
    pub step: u32,
    /// Total loss.
    pub total: f64,
    /// Prediction term.
    pub prediction: f64,
    /// Regulariser term.
    pub regulariser: f64,
}

/// The loss curve as a batch.
pub fn loss_batch(rows: &[LossRow]) -> Result<RecordBatch> {
    let arrays: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from_iter_values(rows.iter().map(|r| r.step))),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.total))),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.prediction),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.regulariser),
        )),
    ];
    Ok(RecordBatch::try_new(schema_of(&loss_columns()), arrays)?)
}

/// One row of `he_embeddings.parquet`.
#[derive(Clone, Debug, PartialEq)]
pub struct EmbeddingRow {
    /// Clip.
    pub clip_id: u32,
    /// Frame t.
    pub frame: u32,
    /// Skill of the clip.
    pub skill: String,
    /// Embedding h_t.
    pub h: [f32; 3],
}

/// Embeddings as a batch.
pub fn embedding_batch(rows: &[EmbeddingRow]) -> Result<RecordBatch> {
    let mut h = F32Rows::fixed(3);
    for r in rows {
        h.push(Some(&r.h));
    }
    let arrays: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from_iter_values(
            rows.iter().map(|r| r.clip_id),
        )),
        Arc::new(UInt32Array::from_iter_values(rows.iter().map(|r| r.frame))),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.skill.as_str()),
        )),
        h.finish(),
    ];
    Ok(RecordBatch::try_new(
        schema_of(&embedding_columns()),
        arrays,
    )?)
}
