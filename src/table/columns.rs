//! Column builders over flat buffers: cheaper and more explicit than the
//! generic Arrow builders for the wide float columns of the frames table.

use arrow::array::{ArrayRef, BooleanArray, FixedSizeListArray, Float32Array, ListArray};
use arrow::buffer::{NullBuffer, OffsetBuffer};
use arrow::datatypes::{DataType, Field};
use std::sync::Arc;

/// A nullable `List<Float32>` or `FixedSizeList<Float32, n>` column.
#[derive(Debug, Default)]
pub struct F32Rows {
    fixed: Option<usize>,
    values: Vec<f32>,
    lengths: Vec<usize>,
    valid: Vec<bool>,
}

impl F32Rows {
    /// A variable-length list column.
    pub fn list() -> Self {
        Self::default()
    }

    /// A fixed-size list column of `n` values per row.
    pub fn fixed(n: usize) -> Self {
        F32Rows {
            fixed: Some(n),
            ..Self::default()
        }
    }

    /// Append one row; `None` is a null row.
    pub fn push(&mut self, row: Option<&[f32]>) {
        match (row, self.fixed) {
            (Some(r), Some(n)) => {
                assert_eq!(r.len(), n, "fixed-size row of the wrong length");
                self.values.extend_from_slice(r);
                self.lengths.push(n);
            }
            (Some(r), None) => {
                self.values.extend_from_slice(r);
                self.lengths.push(r.len());
            }
            // A fixed-size list still stores n (ignored) values for a null row.
            (None, Some(n)) => {
                self.values.extend(std::iter::repeat_n(0.0, n));
                self.lengths.push(n);
            }
            (None, None) => self.lengths.push(0),
        }
        self.valid.push(row.is_some());
    }

    /// The finished Arrow array.
    pub fn finish(self) -> ArrayRef {
        let item = Arc::new(Field::new("item", DataType::Float32, false));
        let values = Arc::new(Float32Array::from(self.values));
        let nulls = if self.valid.iter().all(|v| *v) {
            None
        } else {
            Some(NullBuffer::from(self.valid))
        };
        match self.fixed {
            Some(n) => Arc::new(
                FixedSizeListArray::try_new(item, n as i32, values, nulls)
                    .expect("consistent fixed-size list"),
            ),
            None => Arc::new(
                ListArray::try_new(
                    item,
                    OffsetBuffer::from_lengths(self.lengths),
                    values,
                    nulls,
                )
                .expect("consistent list"),
            ),
        }
    }
}

/// A nullable boolean column.
pub fn bools(values: Vec<Option<bool>>) -> ArrayRef {
    Arc::new(BooleanArray::from(values))
}
