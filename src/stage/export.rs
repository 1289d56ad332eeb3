//! `skillaug export`: motions of a run folder as BVH files and one glTF
//! binary file ([`crate::export`]), or a trained policy as an ONNX model.
//! Every file is staged and moved into place only when all were written.

use crate::cli::ExportArgs;
use crate::export::bvh::{self, Units};
use crate::export::motions::gather;
use crate::export::{gltf, onnx};
use crate::sim::mjcf::Model;
use crate::table::io::{MadeDirs, Staged};
use anyhow::{bail, Context, Result};
use std::path::PathBuf;
use std::time::Instant;

/// Run the command.
pub fn run(a: &ExportArgs) -> Result<()> {
    let mut made = MadeDirs::new();
    let r = export(a, &mut made);
    if r.is_err() {
        // the staged files removed themselves; folders made for them go too
        made.remove();
    }
    r
}

fn export(a: &ExportArgs, made: &mut MadeDirs) -> Result<()> {
    let started = Instant::now();
    let motion = a.bvh.is_some() || a.gltf.is_some();
    // --onnx with --bvh or --gltf is refused by clap (`conflicts_with_all`)
    if !motion && a.onnx.is_none() {
        bail!(
            "export: give --bvh DIR and/or --gltf FILE (motion of --from RUN), or --policy DIR --onnx FILE"
        );
    }
    if a.onnx.is_none() && a.policy.is_some() {
        bail!("export: --policy goes with --onnx FILE; motion (--bvh, --gltf) is another command");
    }
    let mut staged = Staged::new();
    let mut written: Vec<(PathBuf, usize)> = Vec::new();
    if let Some(out) = &a.onnx {
        let Some(policy) = &a.policy else {
            bail!("export --onnx needs --policy TRAIN_DIR (the output folder of `skillaug train`)");
        };
        let bytes = onnx::policy_to_onnx(policy)?;
        made.parent_of(out)?;
        staged.bytes(out, &bytes)?;
        written.push((out.clone(), bytes.len()));
    } else {
        let Some(from) = &a.from else {
            bail!("export --bvh/--gltf needs --from RUN (a run folder with clips.parquet)");
        };
        let units: Units = a.units;
        let lib = crate::table::load_library(from)?;
        let root = crate::dataset::data_root(a.data_root.as_deref())?;
        let model = Model::for_skeleton(&root, lib.skeleton)?;
        // like `view`: every clip when nothing is named
        let sel = a.motions.selection(from);
        let motions = gather(&lib, &sel)?;
        if motions.is_empty() {
            bail!("export: nothing to export: give --clip, --skill, --stf or --rollouts");
        }
        if let Some(dir) = &a.bvh {
            made.dir(dir)?;
            for m in &motions {
                for t in &m.tracks {
                    let name = if m.tracks.len() > 1 {
                        format!("{}-{}.bvh", m.stem, t.name.replace(' ', "_"))
                    } else {
                        format!("{}.bvh", m.stem)
                    };
                    let text = bvh::to_bvh(&model, t, m.fps, units)
                        .with_context(|| format!("{} ({})", m.title, t.name))?;
                    let path = dir.join(name);
                    staged.text(&path, &text)?;
                    written.push((path, text.len()));
                }
            }
        }
        if let Some(path) = &a.gltf {
            let mut names: Vec<String> = Vec::new();
            for m in &motions {
                for o in &m.objects {
                    if !names.contains(o) {
                        names.push(o.clone());
                    }
                }
            }
            let objects = names
                .iter()
                .map(|n| crate::sim::ObjectSpec::load(n, &root))
                .collect::<Result<Vec<_>>>()?;
            let bytes = gltf::to_glb(&model, &objects, &motions)?;
            made.parent_of(path)?;
            staged.bytes(path, &bytes)?;
            written.push((path.clone(), bytes.len()));
        }
    }
    staged.commit()?;
    if !a.quiet {
        for (p, n) in &written {
            println!("wrote {} ({n} bytes)", p.display());
        }
        println!(
            "exported {} file(s) in {:.2} s",
            written.len(),
            started.elapsed().as_secs_f64()
        );
    }
    Ok(())
}
