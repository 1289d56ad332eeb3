//! Column builders: [`TableRow`] derives a small table's columns, schema and
//! record batches from its row struct; [`F32Rows`] builds the wide float
//! columns of the frames table over flat buffers, cheaper and more explicit
//! than the generic Arrow builders.

use super::ColumnSpec;
use arrow::array::{ArrayRef, BooleanArray, FixedSizeListArray, Float32Array, ListArray};
use arrow::buffer::{NullBuffer, OffsetBuffer};
use arrow::datatypes::{DataType, Field};
use arrow::record_batch::RecordBatch;
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

/// The Rust type of one column's values: its Arrow type, whether the
/// column may hold nulls and how a column of such values becomes an array.
/// Implemented for the types the small tables use; the wide float columns
/// of the frames, STF and rollout tables are built with [`F32Rows`].
pub trait CellValue: Sized {
    /// Whether the column may hold nulls (the `Option` types).
    const NULLABLE: bool = false;
    /// Arrow type of the column.
    fn data_type() -> DataType;
    /// The array of a column's values, row order kept.
    fn array(values: Vec<Self>) -> ArrayRef;
}

macro_rules! primitive_cells {
    ($($t:ty => $dtype:ident, $array:ident;)*) => {
        $(
            impl CellValue for $t {
                fn data_type() -> DataType {
                    DataType::$dtype
                }
                fn array(values: Vec<Self>) -> ArrayRef {
                    Arc::new(arrow::array::$array::from(values))
                }
            }

            impl CellValue for Option<$t> {
                const NULLABLE: bool = true;
                fn data_type() -> DataType {
                    DataType::$dtype
                }
                fn array(values: Vec<Self>) -> ArrayRef {
                    Arc::new(arrow::array::$array::from(values))
                }
            }
        )*
    };
}

primitive_cells! {
    u32 => UInt32, UInt32Array;
    u64 => UInt64, UInt64Array;
    f32 => Float32, Float32Array;
    f64 => Float64, Float64Array;
    bool => Boolean, BooleanArray;
}

macro_rules! string_cells {
    ($($t:ty),*) => {$(
        impl CellValue for $t {
            fn data_type() -> DataType {
                DataType::Utf8
            }
            fn array(values: Vec<Self>) -> ArrayRef {
                Arc::new(arrow::array::StringArray::from_iter_values(values))
            }
        }
    )*};
}

string_cells!(String, &'static str);

/// `List<Utf8>` with non-null items ([`super::str_list`]).
impl CellValue for Vec<String> {
    fn data_type() -> DataType {
        super::str_list()
    }
    fn array(values: Vec<Self>) -> ArrayRef {
        use arrow::array::{ListBuilder, StringBuilder};
        let mut b = ListBuilder::new(StringBuilder::new()).with_field(Arc::new(Field::new(
            "item",
            DataType::Utf8,
            false,
        )));
        for row in values {
            for s in row {
                b.values().append_value(s);
            }
            b.append(true);
        }
        Arc::new(b.finish())
    }
}

/// `List<UInt32>` with non-null items ([`super::u32_list`]).
impl CellValue for Vec<u32> {
    fn data_type() -> DataType {
        super::u32_list()
    }
    fn array(values: Vec<Self>) -> ArrayRef {
        use arrow::array::{ListBuilder, UInt32Builder};
        let mut b = ListBuilder::new(UInt32Builder::new()).with_field(Arc::new(Field::new(
            "item",
            DataType::UInt32,
            false,
        )));
        for row in values {
            b.values().append_slice(&row);
            b.append(true);
        }
        Arc::new(b.finish())
    }
}

/// `FixedSizeList<Float32, N>` with non-null items ([`super::f32_fixed`]).
impl<const N: usize> CellValue for [f32; N] {
    fn data_type() -> DataType {
        super::f32_fixed(N as i32)
    }
    fn array(values: Vec<Self>) -> ArrayRef {
        // the nullable column's builder writes no null buffer when every
        // row is set: the same array
        Option::<[f32; N]>::array(values.into_iter().map(Some).collect())
    }
}

/// `List<Float32>` with non-null items ([`super::f32_list`]).
impl CellValue for Vec<f32> {
    fn data_type() -> DataType {
        super::f32_list()
    }
    fn array(values: Vec<Self>) -> ArrayRef {
        Option::<Vec<f32>>::array(values.into_iter().map(Some).collect())
    }
}

/// Nullable `FixedSizeList<Float32, N>` (a null row stores N ignored values).
impl<const N: usize> CellValue for Option<[f32; N]> {
    const NULLABLE: bool = true;
    fn data_type() -> DataType {
        super::f32_fixed(N as i32)
    }
    fn array(values: Vec<Self>) -> ArrayRef {
        let mut b = F32Rows::fixed(N);
        for row in &values {
            b.push(row.as_ref().map(|r| &r[..]));
        }
        b.finish()
    }
}

/// Nullable `List<Float32>`.
impl CellValue for Option<Vec<f32>> {
    const NULLABLE: bool = true;
    fn data_type() -> DataType {
        super::f32_list()
    }
    fn array(values: Vec<Self>) -> ArrayRef {
        let mut b = F32Rows::list();
        for row in &values {
            b.push(row.as_deref());
        }
        b.finish()
    }
}

/// One column of a table whose rows are `R`: its documentation
/// ([`ColumnSpec`]) and how its value is read from a row, kept together so
/// that the schema, the `skillaug schema` text and the written arrays come
/// from one list.
pub struct Column<R> {
    /// Name, Arrow type, nullability and meaning.
    pub spec: ColumnSpec,
    array: ColumnArray<R>,
}

/// How a [`Column`] turns a table's rows into its array.
type ColumnArray<R> = Box<dyn Fn(&[R]) -> ArrayRef>;

impl<R: 'static> Column<R> {
    /// The column `name` (meaning `doc`) whose value in a row is `get(row)`;
    /// type and nullability follow from the value type.
    pub fn new<V: CellValue>(
        name: &'static str,
        doc: &'static str,
        get: impl Fn(&R) -> V + 'static,
    ) -> Column<R> {
        Column {
            spec: ColumnSpec::new(name, V::data_type(), V::NULLABLE, doc),
            array: Box::new(move |rows| V::array(rows.iter().map(&get).collect())),
        }
    }
}

/// A row of a table: the struct from which the table's columns, schema and
/// record batches derive ([`specs`], [`batch`]).
pub trait TableRow: Sized + 'static {
    /// The columns in file order.
    fn columns() -> Vec<Column<Self>>;
}

/// The documented columns of the table of `R` rows.
pub fn specs<R: TableRow>() -> Vec<ColumnSpec> {
    R::columns().into_iter().map(|c| c.spec).collect()
}

/// `rows` as one record batch with the schema of [`specs`].
///
/// # Errors
/// Only if Arrow rejects the arrays (a bug: types follow from the columns).
pub fn batch<R: TableRow>(rows: &[R]) -> anyhow::Result<RecordBatch> {
    let cols = R::columns();
    let schema = super::schema_of(&cols.iter().map(|c| c.spec.clone()).collect::<Vec<_>>());
    let arrays: Vec<ArrayRef> = cols.iter().map(|c| (c.array)(rows)).collect();
    Ok(RecordBatch::try_new(schema, arrays)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow::array::{Array, AsArray};
    use arrow::datatypes::{Float64Type, UInt32Type};

    struct Probe {
        id: u32,
        score: Option<f64>,
        tags: Vec<String>,
        p: [f32; 2],
    }

    impl TableRow for Probe {
        fn columns() -> Vec<Column<Probe>> {
            vec![
                Column::new("id", "row id", |r: &Probe| r.id),
                Column::new("score", "a score or null", |r: &Probe| r.score),
                Column::new("tags", "names", |r: &Probe| r.tags.clone()),
                Column::new("p", "a point", |r: &Probe| r.p),
            ]
        }
    }

    #[test]
    fn a_row_struct_gives_the_schema_and_the_arrays_of_its_table() {
        let specs = specs::<Probe>();
        let names: Vec<&str> = specs.iter().map(|c| c.name).collect();
        assert_eq!(names, ["id", "score", "tags", "p"]);
        assert_eq!(
            specs.iter().map(|c| c.nullable).collect::<Vec<_>>(),
            [false, true, false, false]
        );
        let rows = [
            Probe {
                id: 7,
                score: None,
                tags: vec!["a".into(), "b".into()],
                p: [1.0, 2.0],
            },
            Probe {
                id: 9,
                score: Some(0.5),
                tags: vec![],
                p: [3.0, 4.0],
            },
        ];
        let b = batch(&rows).unwrap();
        assert_eq!(b.num_rows(), 2);
        assert_eq!(b.schema().field(3).data_type(), &crate::table::f32_fixed(2));
        assert_eq!(b.column(0).as_primitive::<UInt32Type>().values(), &[7, 9]);
        let score = b.column(1).as_primitive::<Float64Type>();
        assert!(score.is_null(0));
        assert_eq!(score.value(1), 0.5);
        let tags = b.column(2).as_list::<i32>();
        assert_eq!(tags.value_length(0), 2);
        assert_eq!(tags.value_length(1), 0);
        let p = b.column(3).as_fixed_size_list();
        let p1 = p.value(1);
        assert_eq!(
            p1.as_primitive::<arrow::datatypes::Float32Type>().values(),
            &[3.0, 4.0]
        );
    }
}
