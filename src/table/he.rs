//! `he_loss.parquet` and `he_embeddings.parquet`: the history encoder's
//! pre-training curve and the embedding of every reference frame.

use super::columns::{specs, Column, TableRow};
use super::ColumnSpec;
use anyhow::Result;
use arrow::record_batch::RecordBatch;

/// One logged optimiser step: a row of `he_loss.parquet`.
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

impl TableRow for LossRow {
    fn columns() -> Vec<Column<LossRow>> {
        vec![
            Column::new("step", "optimiser step, 0-based", |r: &LossRow| r.step),
            Column::new("total", "loss of Eq. 23 on the step's minibatch: lambda_a * prediction + lambda_b * regulariser", |r: &LossRow| r.total),
            Column::new("prediction", "mean squared error of the predicted next frame (standardised features)", |r: &LossRow| r.prediction),
            Column::new("regulariser", "mean over the minibatch of |h|^2", |r: &LossRow| r.regulariser),
        ]
    }
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

impl TableRow for EmbeddingRow {
    fn columns() -> Vec<Column<EmbeddingRow>> {
        vec![
            Column::new(
                "clip_id",
                "clip (clips.parquet clip_id)",
                |r: &EmbeddingRow| r.clip_id,
            ),
            Column::new(
                "frame",
                "frame t; h is computed from frames [t-60, t)",
                |r: &EmbeddingRow| r.frame,
            ),
            Column::new("skill", "skill of the clip", |r: &EmbeddingRow| {
                r.skill.clone()
            }),
            Column::new(
                "h",
                "embedding h_t of the trained, frozen encoder",
                |r: &EmbeddingRow| r.h,
            ),
        ]
    }
}

/// Columns of `he_loss.parquet`.
pub fn loss_columns() -> Vec<ColumnSpec> {
    specs::<LossRow>()
}

/// Columns of `he_embeddings.parquet`.
pub fn embedding_columns() -> Vec<ColumnSpec> {
    specs::<EmbeddingRow>()
}

/// The loss curve as a batch.
pub fn loss_batch(rows: &[LossRow]) -> Result<RecordBatch> {
    super::columns::batch(rows)
}

/// Embeddings as a batch.
pub fn embedding_batch(rows: &[EmbeddingRow]) -> Result<RecordBatch> {
    super::columns::batch(rows)
}
