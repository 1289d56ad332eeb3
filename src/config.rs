//! Recipes and settings.
//!
//! A recipe is a TOML file in `stages/` with one table per stage
//! (`[ingest]`, ...). Each stage's settings resolve as
//! struct defaults < recipe table < `--set stage.key=value`, in that order.
//! An unknown stage table or key is an error that names the key and where it
//! came from (the recipe file or the `--set` argument). The resolved settings
//! are written beside the stage's outputs as `<stage>.resolved.toml`.

use anyhow::{anyhow, bail, Context, Result};
use serde::{de::DeserializeOwned, Serialize};
use std::path::{Path, PathBuf};

/// Stage tables a recipe may hold.
pub const STAGES: &[&str] = &[
    "ingest",
    "build-stg",
    "sample-stf",
    "pretrain-he",
    "train",
    "eval",
    "run",
    "check-ball",
];

/// A parsed recipe (empty when no file is given).
#[derive(Debug, Default, Clone)]
pub struct Recipe {
    /// Where it was read from.
    pub path: Option<PathBuf>,
    /// Its top-level tables.
    pub table: toml::Table,
}

impl Recipe {
    /// Read and check a recipe file: TOML, and only known stage tables.
    pub fn load(path: &Path) -> Result<Recipe> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read recipe {}", path.display()))?;
        let table: toml::Table = text
            .parse()
            .with_context(|| format!("recipe {} is not valid TOML", path.display()))?;
        for (k, v) in &table {
            if !STAGES.contains(&k.as_str()) {
                bail!(
                    "recipe {}: unknown stage table `[{k}]` (known: {})",
                    path.display(),
                    STAGES.join(", ")
                );
            }
            if !v.is_table() {
                bail!("recipe {}: `{k}` must be a table", path.display());
            }
        }
        Ok(Recipe {
            path: Some(path.to_path_buf()),
            table,
        })
    }

    fn source(&self) -> String {
        match &self.path {
            Some(p) => format!("recipe {}", p.display()),
            None => "the defaults".into(),
        }
    }
}

/// One `--set stage.key=value` override. The value is parsed as a TOML value
/// (`3`, `1e-5`, `true`, `"text"`, `[1, 2]`); anything that is not valid TOML
/// is taken as a plain string.
#[derive(Debug, Clone)]
pub struct SetArg {
    /// The argument as given.
    pub raw: String,
    /// Dotted key path, starting with the stage.
    pub path: Vec<String>,
    /// Parsed value.
    pub value: toml::Value,
}

impl std::str::FromStr for SetArg {
    type Err = anyhow::Error;
    fn from_str(raw: &str) -> Result<SetArg> {
        SetArg::parse_for(raw, STAGES)
    }
}

impl SetArg {
    /// Parse `raw`, whose first key must be one of `known`.
    pub fn parse_for(raw: &str, known: &[&str]) -> Result<SetArg> {
        let (key, value) = raw
            .split_once('=')
            .ok_or_else(|| anyhow!("--set {raw}: expected STAGE.KEY=VALUE"))?;
        let path: Vec<String> = key.trim().split('.').map(str::to_string).collect();
        if path.len() < 2 || path.iter().any(|p| p.is_empty()) {
            bail!("--set {raw}: the key must be STAGE.KEY, e.g. ingest.fps=60");
        }
        if !known.contains(&path[0].as_str()) {
            bail!(
                "--set {raw}: unknown stage `{}` (known: {})",
                path[0],
                known.join(", ")
            );
        }
        let value = format!("v = {}", value.trim())
            .parse::<toml::Table>()
            .ok()
            .and_then(|mut t| t.remove("v"))
            .unwrap_or_else(|| toml::Value::String(value.trim().to_string()));
        Ok(SetArg {
            raw: raw.to_string(),
            path,
            value,
        })
    }
}

/// Range checks of a stage's resolved settings, run by [`resolve`] so that
/// every stage that reads a table refuses a value that makes no sense
/// before any work, with a message naming the key (`sim.physics_hz`).
pub trait Validate {
    /// Check every numeric setting (finite, in range) and their
    /// combinations; `stage` is the table's name for the messages.
    ///
    /// # Errors
    /// The first setting out of range, named `stage.key` with its value.
    fn validate(&self, stage: &str) -> Result<()>;
}

/// Checks of single settings for [`Validate`] implementations: each names
/// the key as `stage.key` and says what the value must be.
pub struct Check<'a> {
    stage: &'a str,
}

impl<'a> Check<'a> {
    /// Checks of the settings of table `stage`.
    pub fn new(stage: &'a str) -> Check<'a> {
        Check { stage }
    }

    /// `value` is finite and in `[lo, hi]`.
    pub fn range(&self, key: &str, value: f64, lo: f64, hi: f64) -> Result<()> {
        if !(value.is_finite() && value >= lo && value <= hi) {
            bail!(
                "{}.{key} = {value}: must be a finite number in [{lo}, {hi}]",
                self.stage
            );
        }
        Ok(())
    }

    /// `value` is finite and > 0.
    pub fn positive(&self, key: &str, value: f64) -> Result<()> {
        if !(value.is_finite() && value > 0.0) {
            bail!(
                "{}.{key} = {value}: must be a finite number > 0",
                self.stage
            );
        }
        Ok(())
    }

    /// `value` is finite and >= 0.
    pub fn non_negative(&self, key: &str, value: f64) -> Result<()> {
        if !(value.is_finite() && value >= 0.0) {
            bail!(
                "{}.{key} = {value}: must be a finite number >= 0",
                self.stage
            );
        }
        Ok(())
    }

    /// `value` is finite.
    pub fn finite(&self, key: &str, value: f64) -> Result<()> {
        if !value.is_finite() {
            bail!("{}.{key} = {value}: must be a finite number", self.stage);
        }
        Ok(())
    }

    /// A count `value` in `[lo, hi]`.
    pub fn count(&self, key: &str, value: u64, lo: u64, hi: u64) -> Result<()> {
        if !(lo..=hi).contains(&value) {
            bail!(
                "{}.{key} = {value}: must be an integer in [{lo}, {hi}]",
                self.stage
            );
        }
        Ok(())
    }

    /// A condition on several keys; `what` says which and why.
    pub fn holds(&self, ok: bool, what: impl FnOnce() -> String) -> Result<()> {
        if !ok {
            bail!("{}.{}", self.stage, what());
        }
        Ok(())
    }
}

/// Resolve the settings of `stage`: defaults < recipe < `--set`, then
/// [`Validate::validate`].
pub fn resolve<T>(recipe: &Recipe, stage: &str, sets: &[SetArg]) -> Result<T>
where
    T: Serialize + DeserializeOwned + Default + Validate,
{
    let mut table = recipe
        .table
        .get(stage)
        .and_then(|v| v.as_table())
        .cloned()
        .unwrap_or_default();
    // Check the recipe alone first, so an unknown key is blamed on the file.
    toml::Value::Table(table.clone())
        .try_into::<T>()
        .map_err(|e| anyhow!("{}: [{stage}]: {}", recipe.source(), e.message()))?;
    for s in sets.iter().filter(|s| s.path[0] == stage) {
        let mut t = &mut table;
        for p in &s.path[1..s.path.len() - 1] {
            t = t
                .entry(p.clone())
                .or_insert_with(|| toml::Value::Table(Default::default()))
                .as_table_mut()
                .ok_or_else(|| anyhow!("--set {}: `{p}` is not a table", s.raw))?;
        }
        t.insert(s.path.last().unwrap().clone(), s.value.clone());
        toml::Value::Table(table.clone())
            .try_into::<T>()
            .map_err(|e| anyhow!("--set {}: {}", s.raw, e.message()))?;
    }
    let t: T = toml::Value::Table(table)
        .try_into::<T>()
        .map_err(|e| anyhow!("[{stage}]: {}", e.message()))?;
    t.validate(stage)
        .map_err(|e| anyhow!("{e} (settings from {} and --set)", recipe.source()))?;
    Ok(t)
}

/// The TOML text of `<stage>.resolved.toml`: the run's common settings and the
/// stage's resolved table.
pub fn resolved_toml<T: Serialize>(
    stage: &str,
    settings: &T,
    common: &toml::Table,
) -> Result<String> {
    let mut doc = toml::Table::new();
    doc.insert("run".into(), toml::Value::Table(common.clone()));
    doc.insert(stage.into(), toml::Value::try_from(settings)?);
    Ok(format!(
        "# Settings used by `skillaug {stage}` (defaults < recipe < --set).\n{}",
        toml::to_string(&doc)?
    ))
}

/// A short, stable hash of a resolved settings text (hex, 16 digits).
pub fn hash_text(text: &str) -> String {
    use sha2::{Digest, Sha256};
    hex::encode(&Sha256::digest(text.as_bytes())[..8])
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Serialize, Deserialize, Debug, PartialEq)]
    #[serde(default, deny_unknown_fields)]
    struct Demo {
        fps: f64,
        name: String,
        flag: bool,
    }
    impl Validate for Demo {
        fn validate(&self, stage: &str) -> Result<()> {
            Check::new(stage).positive("fps", self.fps)
        }
    }
    impl Default for Demo {
        fn default() -> Self {
            Demo {
                fps: 60.0,
                name: "a".into(),
                flag: false,
            }
        }
    }

    fn recipe(text: &str) -> Recipe {
        Recipe {
            path: Some("stages/x.toml".into()),
            table: text.parse().unwrap(),
        }
    }

    #[test]
    fn precedence_is_defaults_recipe_set() {
        let r = recipe("[ingest]\nfps = 30.0\nname = \"r\"\n");
        let sets: Vec<SetArg> = vec!["ingest.name=cli".parse().unwrap()];
        let d: Demo = resolve(&r, "ingest", &sets).unwrap();
        assert_eq!(
            d,
            Demo {
                fps: 30.0,
                name: "cli".into(),
                flag: false
            }
        );
        let d: Demo = resolve(&Recipe::default(), "ingest", &[]).unwrap();
        assert_eq!(d, Demo::default());
    }

    #[test]
    fn unknown_keys_name_the_key_and_the_source() {
        let r = recipe("[ingest]\nfpss = 30.0\n");
        let e = resolve::<Demo>(&r, "ingest", &[]).unwrap_err().to_string();
        assert!(e.contains("fpss") && e.contains("stages/x.toml"), "{e}");
        let sets: Vec<SetArg> = vec!["ingest.bogus=1".parse().unwrap()];
        let e = resolve::<Demo>(&Recipe::default(), "ingest", &sets)
            .unwrap_err()
            .to_string();
        assert!(e.contains("bogus") && e.contains("--set"), "{e}");
        assert!("nostage.x=1".parse::<SetArg>().is_err());
        assert!("ingest=1".parse::<SetArg>().is_err());
    }

    #[test]
    fn out_of_range_values_name_the_key_and_the_source() {
        for bad in ["0", "-1", "inf", "nan"] {
            let sets: Vec<SetArg> = vec![format!("ingest.fps={bad}").parse().unwrap()];
            let e = format!(
                "{:#}",
                resolve::<Demo>(&recipe(""), "ingest", &sets).unwrap_err()
            );
            assert!(
                e.contains("ingest.fps") && e.contains("stages/x.toml") && e.contains("> 0"),
                "{e}"
            );
        }
        let c = Check::new("sim");
        assert!(c.range("x", 0.5, 0.0, 1.0).is_ok());
        assert!(c.range("x", 1.5, 0.0, 1.0).is_err());
        assert!(c.non_negative("x", 0.0).is_ok());
        assert!(c
            .count("n", 0, 1, 10)
            .unwrap_err()
            .to_string()
            .contains("sim.n = 0"));
    }

    #[test]
    fn set_values_are_typed_or_strings() {
        let s: SetArg = "ingest.flag=true".parse().unwrap();
        assert_eq!(s.value, toml::Value::Boolean(true));
        let s: SetArg = "ingest.name=pickup-4".parse().unwrap();
        assert_eq!(s.value, toml::Value::String("pickup-4".into()));
    }
}
