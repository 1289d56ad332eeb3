//! Command-line definitions (clap). One subcommand per stage, plus helpers.

use crate::nn::DeviceName;
use crate::rl::humanoid::Method;
use clap::{Args, Parser, Subcommand, ValueEnum};
use std::path::PathBuf;

/// skillaug: robust interaction skills from sparse, noisy demonstrations.
#[derive(Debug, Parser)]
#[command(name = "skillaug", version, about, long_about = None)]
pub struct Cli {
    /// The stage or helper to run.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run a whole experiment from one recipe: every stage, each method, then the report
    Run(RunArgs),
    /// Read motion clips (.pt) into clips.parquet and frames.parquet
    Ingest(IngestArgs),
    /// Build the Stitched Trajectory Graph between skills (stg_edges.parquet)
    BuildStg(BuildStgArgs),
    /// Sample State Transition Field trajectories with ATS weights (stf_samples.parquet)
    SampleStf(SampleStfArgs),
    /// Pre-train the history encoder by behaviour cloning (he.safetensors)
    PretrainHe(PretrainHeArgs),
    /// Train a skill policy with PPO on the simulated humanoid (train_metrics.parquet, policy.safetensors)
    Train(TrainArgs),
    /// Forward kinematics of the MJCF humanoid against the clips' body positions
    CheckFk(StageArgs),
    /// What the clips' contact flag measures: simulated contact rules against it, frame by frame
    CheckContact(StageArgs),
    /// Whether the clips' own motion keeps their ball: the humanoid replayed frame by frame, the ball simulated
    CheckBall(StageArgs),
    /// Where each clip's reference continues past its end in training (loop seams and their similarity)
    Seams(StageArgs),
    /// Summarise a skillaug Parquet file: rows, clips, skills, frames, value ranges
    Inspect(InspectArgs),
    /// Print a table's schema, one field per line
    Schema(SchemaArgs),
    /// Evaluate a trained policy: SR, TSR, epsilon-NSR and NR (eval_summary.parquet)
    Eval(EvalArgs),
    /// Render eval summaries as tables shaped like the paper's (terminal and Markdown)
    Report(ReportArgs),
    /// Plot a table as a PNG: training or HE loss curves, STG N-histogram, eval bar chart
    Plot(PlotArgs),
    /// Write one HTML page that plays back clips, STF samples and recorded rollouts
    View(ViewArgs),
    /// Export motion (BVH, glTF binary) or a trained policy (ONNX)
    Export(ExportArgs),
    /// Run a benchmark and print its figures (ingest, sim, train)
    Bench(BenchArgs),
}

/// Flags every stage takes, so stages chain on one run folder.
#[derive(Debug, Clone, Args)]
pub struct StageArgs {
    /// Run folder the stage reads from and writes to.
    #[arg(long, value_name = "DIR", default_value = "runs/default")]
    pub out: PathBuf,
    /// Dataset manifest: a name in datasets/ (ballplay, ballplay-m, locomotion, parahome) or a .toml path.
    #[arg(long, value_name = "NAME", conflicts_with = "from")]
    pub dataset: Option<String>,
    /// ingest, check-fk: a plain folder of .pt clips instead of a manifest (skill = parent folder name); later stages: the run folder to read (default: --out).
    #[arg(long, value_name = "DIR")]
    pub from: Option<PathBuf>,
    /// Folder holding the releases (ballplay/, ballplay-m/, locomotion/, parahome/).
    #[arg(long, value_name = "DIR", env = "SKILLAUG_DATA")]
    pub data_root: Option<PathBuf>,
    /// Recipe file (TOML, one table per stage).
    #[arg(long, value_name = "FILE")]
    pub recipe: Option<PathBuf>,
    /// Override a setting: --set stage.key=value (repeatable; wins over the recipe).
    #[arg(long, value_name = "STAGE.KEY=VALUE")]
    pub set: Vec<String>,
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Worker threads (default: all cores).
    #[arg(long, value_name = "N")]
    pub threads: Option<usize>,
    /// No progress bar and no summary.
    #[arg(long, short)]
    pub quiet: bool,
}

impl StageArgs {
    /// Quiet arguments of a stage that ingests manifest `dataset` (with the
    /// data root `data_root`) into `out`, seed 0, no recipe.
    pub fn for_dataset(out: PathBuf, dataset: &str, data_root: Option<PathBuf>) -> StageArgs {
        StageArgs {
            out,
            dataset: Some(dataset.to_string()),
            from: None,
            data_root,
            recipe: None,
            set: Vec::new(),
            seed: 0,
            threads: None,
            quiet: true,
        }
    }
}

/// `skillaug ingest`.
#[derive(Debug, Args)]
pub struct IngestArgs {
    #[command(flatten)]
    #[allow(missing_docs)]
    pub common: StageArgs,
    /// Ingest the good clips and list the bad ones instead of failing.
    #[arg(long)]
    pub skip_bad: bool,
}

/// `skillaug inspect`.
#[derive(Debug, Args)]
pub struct InspectArgs {
    /// A Parquet file written by skillaug.
    pub file: PathBuf,
}

/// `skillaug schema`.
#[derive(Debug, Args)]
pub struct SchemaArgs {
    /// Table name.
    pub name: crate::table::Table,
}

/// The value parser of `--device`: a [`DeviceName`] (whether this build
/// has CUDA is checked when the device is opened).
fn device_name(s: &str) -> Result<DeviceName, String> {
    s.parse().map_err(|e: anyhow::Error| e.to_string())
}

/// The benchmarks of `skillaug bench`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Bench {
    /// Ingest every shipped dataset.
    Ingest,
    /// Physics steps/s and accuracy of the humanoid.
    Sim,
    /// Whole PPO iterations: samples/s and the simulation-only bound.
    Train,
    /// History-encoder embeddings per window: candle's batched convolution
    /// against the environments' per-position kernel, from scratch and for
    /// a window moved on by one frame.
    He,
}

/// `skillaug bench`.
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Benchmark.
    #[arg(value_enum)]
    pub name: Bench,
    /// Repetitions; the median is reported.
    #[arg(long, default_value_t = 5)]
    pub repeat: usize,
    /// Folder holding the releases.
    #[arg(long, value_name = "DIR", env = "SKILLAUG_DATA")]
    pub data_root: Option<PathBuf>,
    /// Physics setting for `bench sim`: --set sim.key=value (repeatable;
    /// keys of the `[sim]` table, e.g. sim.pgs_iterations=2).
    #[arg(long, value_name = "sim.KEY=VALUE")]
    pub set: Vec<String>,
    /// Device of the networks for `bench train`: cpu (default), or cuda /
    /// cuda:N with the `cuda` feature.
    #[arg(long, value_parser = device_name)]
    pub device: Option<DeviceName>,
}

/// `skillaug build-stg`.
#[derive(Debug, Args)]
pub struct BuildStgArgs {
    #[command(flatten)]
    #[allow(missing_docs)]
    pub common: StageArgs,
    /// The reference code's direction: for each frame of a skill, the best state of each other skill.
    #[arg(long)]
    pub per_target: bool,
}

/// `skillaug sample-stf`.
#[derive(Debug, Args)]
pub struct SampleStfArgs {
    #[command(flatten)]
    #[allow(missing_docs)]
    pub common: StageArgs,
}

/// `skillaug eval`.
#[derive(Debug, Args)]
pub struct EvalArgs {
    #[command(flatten)]
    #[allow(missing_docs)]
    pub common: StageArgs,
    /// Output folder of `skillaug train` (policy.safetensors, policy.meta.json).
    #[arg(long, value_name = "DIR")]
    pub policy: PathBuf,
    /// Keep the first N trials of each cell, step by step, in eval_rollouts.parquet (for `skillaug view`); overrides eval.record.
    #[arg(long, value_name = "N")]
    pub record: Option<usize>,
}

/// `skillaug run`.
#[derive(Debug, Args)]
pub struct RunArgs {
    /// The recipe (stages/*.toml) with a `[run]` table.
    #[arg(value_name = "RECIPE")]
    pub file: PathBuf,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub common: StageArgs,
}

/// `skillaug report`.
#[derive(Debug, Args)]
pub struct ReportArgs {
    /// eval_summary.parquet files or eval output folders.
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
    /// Add the paper's rows (Tables 1, 2 or 5) beside ours.
    #[arg(long)]
    pub with_reference: bool,
    /// Also write the table as Markdown to this file.
    #[arg(long, value_name = "FILE")]
    pub markdown: Option<PathBuf>,
}

/// `skillaug plot`.
#[derive(Debug, Args)]
pub struct PlotArgs {
    /// Tables of one kind: train_metrics (or run folders holding one), he_loss, stg_edges or eval_summary.
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
    /// Output PNG.
    #[arg(long, default_value = "curve.png")]
    pub out: PathBuf,
    /// Column to draw for curves (default: mean_sm_reward for train_metrics, total for he_loss).
    #[arg(long)]
    pub metric: Option<String>,
    /// Legend labels, one per input (default: folder names).
    #[arg(long)]
    pub label: Vec<String>,
    /// Moving average over this many iterations.
    #[arg(long, default_value_t = 1)]
    pub smooth: usize,
    /// Horizontal goal lines.
    #[arg(long)]
    pub goal: Vec<f64>,
    /// Chart title (default: the metric).
    #[arg(long)]
    pub title: Option<String>,
}

/// `skillaug view`.
#[derive(Debug, Args)]
pub struct ViewArgs {
    /// Run folder with clips.parquet and frames.parquet.
    #[arg(long, value_name = "DIR", default_value = "runs/default")]
    pub from: PathBuf,
    /// Folder holding the releases and assets (MJCF, object meshes).
    #[arg(long, value_name = "DIR", env = "SKILLAUG_DATA")]
    pub data_root: Option<PathBuf>,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub motions: MotionArgs,
    /// The page to write.
    #[arg(long, value_name = "FILE", default_value = "view.html")]
    pub out: PathBuf,
}

/// Which motions of a run folder `view` and `export` take.
#[derive(Debug, Clone, Args)]
pub struct MotionArgs {
    /// A reference clip by name or id (repeatable).
    #[arg(long, value_name = "NAME|ID")]
    pub clip: Vec<String>,
    /// Every clip of a skill (repeatable).
    #[arg(long, value_name = "SKILL")]
    pub skill: Vec<String>,
    /// STF samples (stf_samples.parquet).
    #[arg(long, value_name = "FILE")]
    pub stf: Option<PathBuf>,
    /// Trajectory ids of --stf (repeatable; default the first --max).
    #[arg(long, value_name = "K", requires = "stf")]
    pub traj: Vec<u32>,
    /// Rollouts recorded by `skillaug eval --record N` (the eval folder or its eval_rollouts.parquet).
    #[arg(long, value_name = "FILE|DIR")]
    pub rollouts: Option<PathBuf>,
    /// Trials of --rollouts (repeatable; default the first --max of each cell).
    #[arg(long, value_name = "K", requires = "rollouts")]
    pub trial: Vec<u32>,
    /// STF trajectories, and trials per cell, chosen by default (clips: all of them).
    #[arg(long, default_value_t = 8)]
    pub max: usize,
}

impl MotionArgs {
    /// The selection of run folder `from` (every clip when nothing is named).
    pub fn selection(&self, from: &std::path::Path) -> crate::export::motions::Selection {
        crate::export::motions::Selection {
            from: from.to_path_buf(),
            clips: self.clip.clone(),
            skills: self.skill.clone(),
            stf: self.stf.clone(),
            trajs: self.traj.clone(),
            rollouts: self.rollouts.clone(),
            trials: self.trial.clone(),
            max_items: self.max,
        }
    }
}

/// `skillaug export`: motion (`--from RUN` and what to take, into `--bvh
/// DIR` and/or `--gltf FILE`) or a policy (`--policy TRAIN_DIR --onnx FILE`).
#[derive(Debug, Args)]
pub struct ExportArgs {
    /// Run folder with clips.parquet and frames.parquet (motion export).
    #[arg(long, value_name = "DIR")]
    pub from: Option<PathBuf>,
    /// Folder holding the releases and assets (MJCF, object meshes).
    #[arg(long, value_name = "DIR", env = "SKILLAUG_DATA")]
    pub data_root: Option<PathBuf>,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub motions: MotionArgs,
    /// Write one BVH file per clip, trajectory or trial (and character) into this folder.
    #[arg(long, value_name = "DIR")]
    pub bvh: Option<PathBuf>,
    /// Length unit of the BVH offsets and root positions.
    #[arg(long, value_enum, default_value_t = crate::export::bvh::Units::Centimetres, requires = "bvh")]
    pub units: crate::export::bvh::Units,
    /// Write one glTF binary file (.glb) with one animation per clip, trajectory or trial.
    #[arg(long, value_name = "FILE")]
    pub gltf: Option<PathBuf>,
    /// Output folder of `skillaug train` (policy export).
    #[arg(long, value_name = "DIR", requires = "onnx")]
    pub policy: Option<PathBuf>,
    /// Write the policy as an ONNX model (with --policy; not with motion flags).
    #[arg(long, value_name = "FILE", requires = "policy", conflicts_with_all = ["from", "bvh", "gltf", "clip", "skill", "stf", "rollouts"])]
    pub onnx: Option<PathBuf>,
    /// No summary.
    #[arg(long, short)]
    pub quiet: bool,
}

/// `skillaug train`.
#[derive(Debug, Args)]
pub struct TrainArgs {
    #[command(flatten)]
    #[allow(missing_docs)]
    pub common: StageArgs,
    /// Training reward: sm (SkillMimic) or dm (DeepMimic); overrides train.method.
    #[arg(long, value_enum)]
    pub method: Option<Method>,
    /// epsilon-NSI: neighbourhood starts without the connection rule.
    #[arg(long)]
    pub nsi: bool,
    /// Starts from the Stitched Trajectory Graph (needs build-stg).
    #[arg(long)]
    pub stg: bool,
    /// State Transition Field starts (neighbourhood + connection with masked states).
    #[arg(long)]
    pub stf: bool,
    /// Adaptive Trajectory Sampling.
    #[arg(long)]
    pub ats: bool,
    /// History-encoder embedding in the observation (needs pretrain-he).
    #[arg(long)]
    pub he: bool,
    /// Compute device for the networks: cpu (default), or cuda / cuda:N with the `cuda` feature.
    #[arg(long, value_parser = device_name)]
    pub device: Option<DeviceName>,
    /// Continue from the checkpoint in --out.
    #[arg(long)]
    pub resume: bool,
}

/// `skillaug pretrain-he`.
#[derive(Debug, Args)]
pub struct PretrainHeArgs {
    #[command(flatten)]
    #[allow(missing_docs)]
    pub common: StageArgs,
    /// Compute device: cpu (default), or cuda / cuda:N with the `cuda` feature.
    #[arg(long, value_parser = device_name)]
    pub device: Option<DeviceName>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<Cli, clap::Error> {
        Cli::try_parse_from(std::iter::once("skillaug").chain(args.iter().copied()))
    }

    #[test]
    fn schema_takes_the_known_tables_and_lists_them_for_others() {
        for t in crate::table::Table::ALL {
            let Command::Schema(a) = parse(&["schema", t.name()]).unwrap().command else {
                panic!("not schema");
            };
            assert_eq!(a.name, t);
        }
        let e = parse(&["schema", "nope"]).unwrap_err();
        assert_eq!(e.kind(), clap::error::ErrorKind::InvalidValue);
        let text = e.to_string();
        assert!(
            text.contains("'nope'") && text.contains("clips, frames, stg_edges"),
            "{text}"
        );
    }

    #[test]
    fn train_takes_a_method_and_a_device() {
        let Command::Train(a) = parse(&["train", "--method", "dm", "--device", "cuda:2"])
            .unwrap()
            .command
        else {
            panic!("not train");
        };
        assert_eq!(a.method, Some(Method::Dm));
        assert_eq!(a.device, Some(DeviceName::Cuda(Some(2))));
        let e = parse(&["train", "--device", "tpu"]).unwrap_err();
        assert!(e.to_string().contains("unknown device `tpu`"), "{e}");
        assert!(parse(&["train", "--method", "xm"]).is_err());
    }
}
