//! Atomic writes and reads of the tables.
//!
//! Every output is first written to a hidden temporary file in its target
//! folder and renamed into place only once every output of the stage has been
//! written ([`Staged::commit`]). A failure before that leaves the folder as it
//! was: nothing half-written, nothing already there lost.

use anyhow::{anyhow, Context, Result};
use arrow::record_batch::RecordBatch;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use std::io::Write;
use std::path::{Path, PathBuf};
use tempfile::NamedTempFile;

/// Outputs written to temporary files, waiting to be renamed into place.
#[derive(Default)]
pub struct Staged {
    files: Vec<(NamedTempFile, PathBuf)>,
}

impl Staged {
    /// Nothing staged yet.
    pub fn new() -> Self {
        Self::default()
    }

    fn temp_for(dest: &Path) -> Result<NamedTempFile> {
        Self::temp_with(dest, None)
    }

    /// A temporary file beside `dest`; `mode` (unix permission bits)
    /// replaces the temporary file's 0600.
    fn temp_with(dest: &Path, mode: Option<u32>) -> Result<NamedTempFile> {
        let dir = dest
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let mut b = tempfile::Builder::new();
        b.prefix(".skillaug-").suffix(".tmp");
        #[cfg(unix)]
        if let Some(m) = mode {
            use std::os::unix::fs::PermissionsExt;
            b.permissions(std::fs::Permissions::from_mode(m));
        }
        #[cfg(not(unix))]
        let _ = mode;
        b.tempfile_in(dir)
            .with_context(|| format!("cannot create a temporary file in {}", dir.display()))
    }

    /// Stage a Parquet file holding `batch`, with `metadata` as ordered
    /// key-value pairs.
    pub fn parquet(
        &mut self,
        dest: &Path,
        batch: &RecordBatch,
        metadata: &[(String, String)],
    ) -> Result<()> {
        let tmp = Self::temp_for(dest)?;
        let props = WriterProperties::builder()
            .set_compression(Compression::ZSTD(ZstdLevel::try_new(1)?))
            .set_dictionary_enabled(false)
            .set_key_value_metadata(Some(
                metadata
                    .iter()
                    .map(|(k, v)| KeyValue::new(k.clone(), v.clone()))
                    .collect(),
            ))
            .build();
        let file = tmp.reopen()?;
        let mut w = ArrowWriter::try_new(file, batch.schema(), Some(props))?;
        w.write(batch)
            .with_context(|| format!("writing {}", dest.display()))?;
        w.close()
            .with_context(|| format!("writing {}", dest.display()))?;
        self.files.push((tmp, dest.to_path_buf()));
        Ok(())
    }

    /// Stage a file written by `write`, which gets the temporary path.
    pub fn with_path(
        &mut self,
        dest: &Path,
        write: impl FnOnce(&Path) -> Result<()>,
    ) -> Result<()> {
        let tmp = Self::temp_for(dest)?;
        write(tmp.path())?;
        self.files.push((tmp, dest.to_path_buf()));
        Ok(())
    }

    /// Stage a text file.
    pub fn text(&mut self, dest: &Path, text: &str) -> Result<()> {
        self.text_with(dest, text, None)
    }

    /// Stage a text file for others to read (a page): mode 0644.
    pub fn shared_text(&mut self, dest: &Path, text: &str) -> Result<()> {
        self.text_with(dest, text, Some(0o644))
    }

    fn text_with(&mut self, dest: &Path, text: &str, mode: Option<u32>) -> Result<()> {
        let mut tmp = Self::temp_with(dest, mode)?;
        tmp.write_all(text.as_bytes())?;
        tmp.flush()?;
        self.files.push((tmp, dest.to_path_buf()));
        Ok(())
    }

    /// Rename every staged file into place.
    pub fn commit(self) -> Result<()> {
        for (tmp, dest) in self.files {
            tmp.as_file().sync_all()?;
            tmp.persist(&dest)
                .map_err(|e| anyhow!("cannot move output into {}: {}", dest.display(), e.error))?;
        }
        Ok(())
    }
}

/// A table read back: its batches and its key-value metadata.
pub struct ReadTable {
    /// Record batches in file order.
    pub batches: Vec<RecordBatch>,
    /// Key-value metadata in file order.
    pub metadata: Vec<(String, String)>,
}

impl ReadTable {
    /// The value of metadata key `key`.
    pub fn meta(&self, key: &str) -> Option<&str> {
        self.metadata
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }

    /// Total rows.
    pub fn rows(&self) -> usize {
        self.batches.iter().map(|b| b.num_rows()).sum()
    }
}

/// Read only the key-value metadata of a Parquet file.
pub fn read_metadata(path: &Path) -> Result<Vec<(String, String)>> {
    let file =
        std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let builder = ParquetRecordBatchReaderBuilder::try_new(file)
        .with_context(|| format!("{} is not a Parquet file", path.display()))?;
    Ok(kv(builder.metadata().file_metadata().key_value_metadata()))
}

fn kv(list: Option<&Vec<KeyValue>>) -> Vec<(String, String)> {
    list.map(|v| {
        v.iter()
            .filter(|k| k.key != "ARROW:schema")
            .map(|k| (k.key.clone(), k.value.clone().unwrap_or_default()))
            .collect()
    })
    .unwrap_or_default()
}

/// Read a whole Parquet file.
pub fn read_parquet(path: &Path) -> Result<ReadTable> {
    let file =
        std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let builder = ParquetRecordBatchReaderBuilder::try_new(file)
        .with_context(|| format!("{} is not a Parquet file", path.display()))?;
    let metadata = kv(builder.metadata().file_metadata().key_value_metadata());
    let batches = builder
        .build()?
        .collect::<std::result::Result<Vec<_>, _>>()
        .with_context(|| format!("reading {}", path.display()))?;
    Ok(ReadTable { batches, metadata })
}

/// Read a whole Parquet file as a polars frame (for summaries, group-bys
/// and joins).
pub fn read_frame(path: &Path) -> Result<polars::prelude::DataFrame> {
    use polars::prelude::{ParquetReader, SerReader};
    let f = std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    ParquetReader::new(f)
        .finish()
        .with_context(|| format!("{}: cannot read as Parquet", path.display()))
}

/// A string column of a frame (nulls as "").
pub fn frame_strs(df: &polars::prelude::DataFrame, name: &str) -> Result<Vec<String>> {
    let col = df.column(name)?.str()?.clone();
    Ok((0..col.len())
        .map(|i| col.get(i).unwrap_or_default().to_string())
        .collect())
}

/// A Float64 column of a frame (nulls as NaN).
pub fn frame_f64s(df: &polars::prelude::DataFrame, name: &str) -> Result<Vec<f64>> {
    let col = df.column(name)?.f64()?.clone();
    Ok((0..col.len())
        .map(|i| col.get(i).unwrap_or(f64::NAN))
        .collect())
}

/// An integer column of a frame as u32 (cast; nulls as 0).
pub fn frame_u32s(df: &polars::prelude::DataFrame, name: &str) -> Result<Vec<u32>> {
    let col = df.column(name)?.cast(&polars::prelude::DataType::UInt32)?;
    let col = col.u32()?;
    Ok((0..col.len()).map(|i| col.get(i).unwrap_or(0)).collect())
}
