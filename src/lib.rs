//! skillaug: a data toolkit and trainer for robust interaction skills learned
//! from sparse, noisy motion-capture clips (the SkillMimic-V2 method on top of
//! SkillMimic's reinforcement learning from interaction demonstrations).
//!
//! Pure domain code lives in [`motion`]; [`pt`] reads PyTorch clip files;
//! [`table`] is the only code that touches Arrow/Parquet; [`stage`] holds one
//! thin file per subcommand.
#![warn(missing_docs)]

pub mod augment;
pub mod cli;
pub mod config;
pub mod dataset;
pub mod eval;
pub mod export;
pub mod ingest;
pub mod motion;
pub mod nn;
pub mod pipeline;
pub mod plot;
pub mod progress;
pub mod pt;
pub mod random;
pub mod reward;
pub mod rl;
pub mod sim;
pub mod stage;
pub mod table;
pub mod view;

use anyhow::Result;
use cli::{Cli, Command};

/// Run one parsed command line.
pub fn run(cli: Cli) -> Result<()> {
    if let Some(n) = rl::comm::launcher_size().filter(|n| *n > 1) {
        if !matches!(cli.command, Command::Train(_)) {
            anyhow::bail!(
                "started as one of {n} processes (mpirun or srun): only `skillaug train` runs \
                 over MPI ranks; run this command as one process"
            );
        }
    }
    match cli.command {
        Command::Run(a) => stage::run::run(&a.file, a.common),
        Command::Ingest(a) => stage::ingest::run(&stage::Common::new(a.common)?, a.skip_bad),
        Command::BuildStg(a) => stage::build_stg::run(&stage::Common::new(a.common)?, a.per_target),
        Command::SampleStf(a) => stage::sample_stf::run(&stage::Common::new(a.common)?),
        Command::PretrainHe(a) => stage::pretrain_he::run(&stage::Common::new(a.common)?, a.device),
        Command::Train(a) => {
            let sw = rl::config::Switches {
                method: a.method,
                nsi: a.nsi,
                stg: a.stg,
                stf: a.stf,
                ats: a.ats,
                he: a.he,
                device: a.device,
                resume: a.resume,
                ..Default::default()
            };
            stage::train::run(&stage::Common::new(a.common)?, &sw)
        }
        Command::Eval(a) => {
            let mut common = a.common;
            if let Some(n) = a.record {
                common.set.push(format!("eval.record={n}"));
            }
            stage::eval::run(&stage::Common::new(common)?, &a.policy)
        }
        Command::Report(a) => {
            stage::report::run(&a.inputs, a.with_reference, a.markdown.as_deref())
        }
        Command::Plot(a) => stage::plot::run(&stage::plot::PlotRequest {
            inputs: &a.inputs,
            labels: &a.label,
            metric: a.metric.as_deref(),
            smooth: a.smooth,
            goals: &a.goal,
            title: a.title.as_deref(),
            out: &a.out,
        }),
        Command::View(a) => {
            let n = stage::view::run(&stage::view::ViewRequest {
                select: a.motions.selection(&a.from),
                data_root: a.data_root,
                out: a.out.clone(),
            })?;
            println!("wrote {} ({n} items)", a.out.display());
            Ok(())
        }
        Command::CheckFk(a) => stage::check_fk::run(&stage::Common::new(a)?),
        Command::CheckContact(a) => stage::check_contact::run(&stage::Common::new(a)?),
        Command::CheckBall(a) => stage::check_ball::run(&stage::Common::new(a)?),
        Command::Seams(a) => stage::seams::run(&stage::Common::new(a)?),
        Command::Inspect(a) => stage::inspect::run(&a.file),
        Command::Schema(a) => {
            stage::schema::run(a.name);
            Ok(())
        }
        Command::Export(a) => stage::export::run(&a),
        Command::Bench(a) => stage::bench::run(
            a.name,
            a.repeat,
            a.data_root,
            &a.set,
            a.device.unwrap_or_default(),
        ),
    }
}
