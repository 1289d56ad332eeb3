//! Atomic writes and reads of the tables.
//!
//! Every output is first written to a hidden temporary file in its target
//! folder, synced, and renamed into place only once every output of the
//! stage has been written ([`Staged::commit`]; [`Outputs`] for the files of
//! one folder). A failure before that leaves the folder as it was: nothing
//! half-written, nothing already there lost. A folder that must change as
//! a whole (the trainer's checkpoint) is staged as a fresh folder and
//! swapped in ([`StagedDir`]); [`MadeDirs`] removes the folders made for
//! outputs that were then not written.

use anyhow::{anyhow, bail, Context, Result};
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

    /// A temporary file beside `dest` (tempfile's mode 0600 until
    /// [`Staged::commit`] gives it the folder's).
    fn temp_for(dest: &Path) -> Result<NamedTempFile> {
        let dir = folder_of(dest);
        tempfile::Builder::new()
            .prefix(".skillaug-")
            .suffix(".tmp")
            .tempfile_in(dir)
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

    /// Stage a file holding `bytes`.
    pub fn bytes(&mut self, dest: &Path, bytes: &[u8]) -> Result<()> {
        let mut tmp = Self::temp_for(dest)?;
        tmp.write_all(bytes)?;
        tmp.flush()?;
        self.files.push((tmp, dest.to_path_buf()));
        Ok(())
    }

    /// Stage a text file.
    pub fn text(&mut self, dest: &Path, text: &str) -> Result<()> {
        self.bytes(dest, text.as_bytes())
    }

    /// Rename every staged file into place, each with the mode a new file
    /// gets in its folder (`fresh_file_mode`), whichever writer made it
    /// (candle's safetensors writer renames a 0600 file of its own onto the
    /// temporary path).
    pub fn commit(self) -> Result<()> {
        // Everything that can fail is done for every file before the first
        // rename, so that a failure moves nothing into place.
        let mut modes: Vec<(&Path, u32)> = Vec::new();
        for (tmp, dest) in &self.files {
            if dest.is_dir() {
                bail!(
                    "cannot write {}: a folder of that name is in the way",
                    dest.display()
                );
            }
            let dir = folder_of(dest);
            let mode = match modes.iter().find(|(d, _)| *d == dir) {
                Some((_, m)) => *m,
                None => {
                    let m = fresh_file_mode(dir)?;
                    modes.push((dir, m));
                    m
                }
            };
            set_mode(tmp.path(), mode)?;
            // By path, not `tmp.as_file()`: a writer that renamed its own
            // file onto the temporary path (candle's safetensors writer)
            // left that handle on the replaced file.
            std::fs::File::open(tmp.path())
                .and_then(|f| f.sync_all())
                .with_context(|| format!("cannot sync the output for {}", dest.display()))?;
        }
        let dirs: Vec<PathBuf> = modes.iter().map(|(d, _)| d.to_path_buf()).collect();
        for (tmp, dest) in self.files {
            tmp.persist(&dest)
                .map_err(|e| anyhow!("cannot move output into {}: {}", dest.display(), e.error))?;
        }
        for dir in &dirs {
            sync_dir(dir);
        }
        Ok(())
    }
}

/// The outputs of one stage in its run folder, committed all at once. The
/// folder itself is made (and removed again when the stage fails and
/// leaves it empty) by the stage's [`OutputLock`].
pub struct Outputs {
    dir: PathBuf,
    staged: Staged,
}

impl Outputs {
    /// Stage outputs into `dir` (created if missing).
    pub fn new(dir: &Path) -> Result<Outputs> {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the output folder {}", dir.display()))?;
        Ok(Outputs {
            dir: dir.to_path_buf(),
            staged: Staged::new(),
        })
    }

    /// Stage `<dir>/<name>` as Parquet.
    pub fn parquet(
        &mut self,
        name: &str,
        batch: &RecordBatch,
        meta: &[(String, String)],
    ) -> Result<()> {
        let dest = self.dir.join(name);
        self.staged.parquet(&dest, batch, meta)
    }

    /// Stage `<dir>/<name>`, written by `write` to the temporary path it gets.
    pub fn with_path(&mut self, name: &str, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
        let dest = self.dir.join(name);
        self.staged.with_path(&dest, write)
    }

    /// Stage `<dir>/<name>` (and the files beside it that go with it) by
    /// `stage`, a writer that stages into a [`Staged`] set itself (such as
    /// [`crate::rl::Agent::stage`]); it gets the set and the destination.
    pub fn with_staged(
        &mut self,
        name: &str,
        stage: impl FnOnce(&mut Staged, &Path) -> Result<()>,
    ) -> Result<()> {
        let dest = self.dir.join(name);
        stage(&mut self.staged, &dest)
    }

    /// Stage `<dir>/<name>` as text.
    pub fn text(&mut self, name: &str, text: &str) -> Result<()> {
        let dest = self.dir.join(name);
        self.staged.text(&dest, text)
    }

    /// Move every staged output into place.
    pub fn commit(self) -> Result<()> {
        self.staged.commit()
    }
}

/// A folder of outputs replaced as a whole. Its files are staged (as by
/// [`Staged`]: temporary file, synced, the mode a new file gets) in the
/// fresh folder `<dest>.tmp/`; [`StagedDir::commit`] moves each to its name
/// there, syncs that folder, renames the folder `dest` held before to
/// `<dest>.old`, renames `<dest>.tmp` to `dest`, syncs the parent and only
/// then removes `<dest>.old`. A reader that finds no `dest` should read
/// `<dest>.old` (a swap cut short between its two renames). A staged folder
/// dropped without a commit is removed, and a `<dest>.tmp` left behind by a
/// killed process is removed by the next [`StagedDir::new`].
pub struct StagedDir {
    dest: PathBuf,
    tmp: PathBuf,
    staged: Staged,
    committed: bool,
}

impl StagedDir {
    /// Start a new version of folder `dest` (its parent is created if
    /// missing).
    ///
    /// # Errors
    /// When `<dest>.tmp` cannot be removed or created.
    pub fn new(dest: &Path) -> Result<StagedDir> {
        let tmp = with_suffix(dest, ".tmp");
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp)
                .with_context(|| format!("cannot remove {}", tmp.display()))?;
        }
        std::fs::create_dir_all(&tmp)
            .with_context(|| format!("cannot create {}", tmp.display()))?;
        Ok(StagedDir {
            dest: dest.to_path_buf(),
            tmp,
            staged: Staged::new(),
            committed: false,
        })
    }

    /// Stage file `name` of the folder holding `bytes`.
    pub fn bytes(&mut self, name: &str, bytes: &[u8]) -> Result<()> {
        let dest = self.tmp.join(name);
        self.staged.bytes(&dest, bytes)
    }

    /// Stage file `name` of the folder (and the files beside it that go
    /// with it) by `stage`, as [`Outputs::with_staged`].
    pub fn with_staged(
        &mut self,
        name: &str,
        stage: impl FnOnce(&mut Staged, &Path) -> Result<()>,
    ) -> Result<()> {
        let dest = self.tmp.join(name);
        stage(&mut self.staged, &dest)
    }

    /// Put the staged folder in place of `dest` (see [`StagedDir`]).
    pub fn commit(mut self) -> Result<()> {
        std::mem::take(&mut self.staged).commit()?;
        let old = with_suffix(&self.dest, ".old");
        let at = |p: &Path| format!("cannot write {}", p.display());
        if self.dest.exists() {
            if old.exists() {
                std::fs::remove_dir_all(&old).with_context(|| at(&old))?;
            }
            std::fs::rename(&self.dest, &old).with_context(|| at(&old))?;
        }
        std::fs::rename(&self.tmp, &self.dest).with_context(|| at(&self.dest))?;
        self.committed = true;
        sync_dir(folder_of(&self.dest));
        if old.exists() {
            std::fs::remove_dir_all(&old).with_context(|| at(&old))?;
        }
        Ok(())
    }
}

impl Drop for StagedDir {
    fn drop(&mut self) {
        if !self.committed {
            drop(std::mem::take(&mut self.staged));
            let _ = std::fs::remove_dir_all(&self.tmp);
        }
    }
}

/// `path` with `suffix` appended to its last component.
fn with_suffix(path: &Path, suffix: &str) -> PathBuf {
    let mut s = path.as_os_str().to_os_string();
    s.push(suffix);
    PathBuf::from(s)
}

/// Folders made for outputs ([`MadeDirs::dir`]), to be removed again when
/// the outputs are not written after all ([`MadeDirs::remove`]).
#[derive(Default)]
pub struct MadeDirs {
    made: Vec<PathBuf>,
}

impl MadeDirs {
    /// Nothing made yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Create folder `dir` and its missing parents, noting each one made.
    ///
    /// # Errors
    /// When a folder cannot be created.
    pub fn dir(&mut self, dir: &Path) -> Result<()> {
        let mut missing = Vec::new();
        let mut d = Some(dir);
        while let Some(p) = d.filter(|p| !p.as_os_str().is_empty() && !p.exists()) {
            missing.push(p.to_path_buf());
            d = p.parent();
        }
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the output folder {}", dir.display()))?;
        self.made.extend(missing.into_iter().rev());
        Ok(())
    }

    /// [`MadeDirs::dir`] of the folder of file `path`.
    ///
    /// # Errors
    /// As [`MadeDirs::dir`].
    pub fn parent_of(&mut self, path: &Path) -> Result<()> {
        match path.parent().filter(|p| !p.as_os_str().is_empty()) {
            Some(dir) => self.dir(dir),
            None => Ok(()),
        }
    }

    /// Remove the folders made, deepest first, each only if empty (call it
    /// once the staged outputs that were to go into them are dropped).
    pub fn remove(self) {
        for dir in self.made.iter().rev() {
            let _ = std::fs::remove_dir(dir);
        }
    }
}

/// The folder of output `dest` (`.` for a bare file name).
fn folder_of(dest: &Path) -> &Path {
    dest.parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."))
}

/// The permission bits a file created now in `dir` gets (0666 less the
/// umask, or what the folder's default ACL gives), found by creating and
/// removing a probe file: the umask cannot be read without changing it.
/// 0o644 off unix (unused there).
fn fresh_file_mode(dir: &Path) -> Result<u32> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let probe = tempfile::Builder::new()
            .prefix(".skillaug-mode-")
            .permissions(std::fs::Permissions::from_mode(0o666))
            .tempfile_in(dir)
            .with_context(|| format!("cannot create a file in {}", dir.display()))?;
        Ok(probe.as_file().metadata()?.permissions().mode() & 0o777)
    }
    #[cfg(not(unix))]
    {
        let _ = dir;
        Ok(0o644)
    }
}

/// Sync folder `dir`, so that the renames into it last (unix; best
/// effort: not every file system syncs a folder, and the files in it are
/// in place whether or not it does).
fn sync_dir(dir: &Path) {
    #[cfg(unix)]
    if let Ok(f) = std::fs::File::open(dir) {
        let _ = f.sync_all();
    }
    #[cfg(not(unix))]
    let _ = dir;
}

/// Set the permission bits of `path` (a no-op off unix).
fn set_mode(path: &Path, mode: u32) -> Result<()> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode))
            .with_context(|| format!("cannot set the mode of {}", path.display()))?;
    }
    #[cfg(not(unix))]
    let _ = (path, mode);
    Ok(())
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

/// Name of the lock file a stage holds in its output folder.
pub const LOCK_FILE: &str = ".skillaug.lock";

/// An exclusive lock on an output folder, held by one stage from its start
/// to its end, so that two runs never write into one folder at once (their
/// outputs would mix). It is an advisory `flock` on `DIR/.skillaug.lock`
/// (`std::fs::File::try_lock`): the kernel releases it when the holder
/// exits, so the lock file a killed process leaves behind blocks nobody.
/// On drop the lock file is removed, and the folder too when the lock
/// created it and it is still empty (a stage that failed leaves nothing).
pub struct OutputLock {
    dir: PathBuf,
    path: PathBuf,
    created: bool,
    _file: std::fs::File,
}

impl OutputLock {
    /// Lock `dir` (created if missing) for `stage`.
    ///
    /// # Errors
    /// Another live process holds the lock (the message names the folder
    /// and, when it could be read, the holder's stage and pid), or the
    /// folder or lock file cannot be created.
    pub fn acquire(dir: &Path, stage: &str) -> Result<OutputLock> {
        use std::fs::TryLockError;
        let created = !dir.exists();
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the output folder {}", dir.display()))?;
        let path = dir.join(LOCK_FILE);
        loop {
            let mut file = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false)
                .open(&path)
                .with_context(|| format!("cannot create the lock file {}", path.display()))?;
            match file.try_lock() {
                Ok(()) => {}
                Err(TryLockError::WouldBlock) => {
                    let holder = std::fs::read_to_string(&path).unwrap_or_default();
                    let holder = holder.trim();
                    bail!(
                        "{} is being written by another skillaug process{}; wait for it to end \
                         or give another --out (the lock, {}, frees itself when that process \
                         exits)",
                        dir.display(),
                        if holder.is_empty() {
                            String::new()
                        } else {
                            format!(" ({holder})")
                        },
                        path.display()
                    );
                }
                Err(TryLockError::Error(e)) => {
                    return Err(e).with_context(|| format!("cannot lock {}", path.display()))
                }
            }
            // A holder that finished removed the file it had locked; then
            // the lock taken here is on a file no one else will open: retry.
            if !Self::is_current(&file, &path) {
                continue;
            }
            file.set_len(0)?;
            writeln!(file, "skillaug {stage}, pid {}", std::process::id())?;
            return Ok(OutputLock {
                dir: dir.to_path_buf(),
                path,
                created,
                _file: file,
            });
        }
    }

    #[cfg(unix)]
    fn is_current(file: &std::fs::File, path: &Path) -> bool {
        use std::os::unix::fs::MetadataExt;
        match (file.metadata(), std::fs::metadata(path)) {
            (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
            _ => false,
        }
    }

    #[cfg(not(unix))]
    fn is_current(_file: &std::fs::File, path: &Path) -> bool {
        path.exists()
    }
}

impl Drop for OutputLock {
    fn drop(&mut self) {
        // Remove the file while still holding the lock (see `acquire`).
        let _ = std::fs::remove_file(&self.path);
        if self.created {
            let _ = std::fs::remove_dir(&self.dir);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn a_staged_folder_replaces_the_old_one_whole() {
        let tmp = tempfile::tempdir().unwrap();
        let dest = tmp.path().join("ckpt");
        let mut d = StagedDir::new(&dest).unwrap();
        d.bytes("a.bin", b"one").unwrap();
        d.bytes("stale.bin", b"x").unwrap();
        d.commit().unwrap();
        assert_eq!(names(&dest), ["a.bin", "stale.bin"]);
        // a writer that renames its own file onto the temporary path
        let mut d = StagedDir::new(&dest).unwrap();
        d.with_staged("b.bin", |staged, path| {
            staged.with_path(path, |p| {
                let own = p.with_extension("own");
                std::fs::write(&own, b"two")?;
                std::fs::rename(&own, p)?;
                Ok(())
            })
        })
        .unwrap();
        d.bytes("a.bin", b"three").unwrap();
        d.commit().unwrap();
        assert_eq!(names(&dest), ["a.bin", "b.bin"]);
        assert_eq!(std::fs::read(dest.join("a.bin")).unwrap(), b"three");
        assert_eq!(std::fs::read(dest.join("b.bin")).unwrap(), b"two");
        assert_eq!(names(tmp.path()), ["ckpt"]);
    }

    #[test]
    fn a_staged_folder_dropped_or_left_by_a_crash_goes_away() {
        let tmp = tempfile::tempdir().unwrap();
        let dest = tmp.path().join("ckpt");
        let mut d = StagedDir::new(&dest).unwrap();
        d.bytes("a.bin", b"one").unwrap();
        d.commit().unwrap();
        let mut d = StagedDir::new(&dest).unwrap();
        d.bytes("a.bin", b"two").unwrap();
        drop(d);
        assert_eq!(names(tmp.path()), ["ckpt"]);
        assert_eq!(std::fs::read(dest.join("a.bin")).unwrap(), b"one");
        // what a killed process leaves behind
        std::fs::create_dir(tmp.path().join("ckpt.tmp")).unwrap();
        std::fs::write(tmp.path().join("ckpt.tmp/junk"), b"j").unwrap();
        let d = StagedDir::new(&dest).unwrap();
        assert!(names(&tmp.path().join("ckpt.tmp")).is_empty());
        d.commit().unwrap();
        assert!(names(&dest).is_empty());
        assert_eq!(names(tmp.path()), ["ckpt"]);
    }

    #[test]
    fn folders_made_for_outputs_not_written_are_removed() {
        let tmp = tempfile::tempdir().unwrap();
        std::fs::create_dir(tmp.path().join("kept")).unwrap();
        let mut made = MadeDirs::new();
        made.dir(&tmp.path().join("kept/a/b")).unwrap();
        made.parent_of(&tmp.path().join("c/d/file.glb")).unwrap();
        assert!(tmp.path().join("c/d").is_dir());
        made.remove();
        assert_eq!(names(tmp.path()), ["kept"]);
        assert!(names(&tmp.path().join("kept")).is_empty());
    }
}
