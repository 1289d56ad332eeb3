//! `skillaug view`: one self-contained HTML page ([`crate::view`]) that plays
//! back, from a run folder's ingested clips:
//!
//! * reference clips of `frames.parquet` (`--clip`, `--skill`; all clips
//!   when nothing else is asked for); missing frames are held and marked;
//! * STF samples of `stf_samples.parquet` (`--stf FILE`, `--traj K`): the
//!   start state, then the reference frames it tracks, the masked steps
//!   (inserted states s∅ and missing frames) marked in red;
//! * rollouts recorded by `skillaug eval --record N` (`--rollouts FILE|DIR`,
//!   `--trial K`), each beside its reference, on one clock.

use crate::motion::state::Posture;
use crate::motion::MotionLib;
use crate::sim::mjcf::Model;
use crate::table::rollout::RolloutStep;
use crate::view::{self, Item, ObjectView, Scene};
use anyhow::{bail, Context, Result};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// What to put on the page.
#[derive(Clone, Debug, Default)]
pub struct ViewRequest {
    /// Run folder with clips.parquet and frames.parquet.
    pub from: PathBuf,
    /// Data root (MJCF and object meshes); `None`: the default.
    pub data_root: Option<PathBuf>,
    /// Clips by name or id.
    pub clips: Vec<String>,
    /// Every clip of these skills.
    pub skills: Vec<String>,
    /// An stf_samples.parquet file.
    pub stf: Option<PathBuf>,
    /// Trajectory ids of `stf` (empty: the first `max_items`).
    pub trajs: Vec<u32>,
    /// An eval_rollouts.parquet file or the eval folder holding one.
    pub rollouts: Option<PathBuf>,
    /// Trials of `rollouts` (empty: all, up to `max_items` per cell).
    pub trials: Vec<u32>,
    /// At most this many items of each kind chosen by default.
    pub max_items: usize,
    /// The page to write.
    pub out: PathBuf,
}

/// Objects of the library's clips as one mesh pool; per clip, its indices.
struct Objects {
    pool: Vec<ObjectView>,
    names: Vec<String>,
}

impl Objects {
    fn of(&mut self, names: &[String], root: &Path) -> Result<Vec<usize>> {
        names
            .iter()
            .map(|n| {
                if let Some(k) = self.names.iter().position(|m| m == n) {
                    return Ok(k);
                }
                let spec = crate::sim::objects::ObjectSpec::load(n, root)?;
                self.pool.push(view::object_view(&spec));
                self.names.push(n.clone());
                Ok(self.pool.len() - 1)
            })
            .collect()
    }
}

fn clip_id(lib: &MotionLib, key: &str) -> Result<usize> {
    if let Some(i) = lib.clips.iter().position(|c| c.name == key) {
        return Ok(i);
    }
    if let Ok(i) = key.parse::<usize>() {
        if i < lib.clips.len() {
            return Ok(i);
        }
    }
    bail!(
        "no clip `{key}` in this run folder (give a clip name or id; `skillaug inspect clips.parquet` lists them)"
    )
}

/// Posture of a reference frame (`None`: missing or out of range).
fn frame(lib: &MotionLib, clip: u32, f: u32) -> Option<Posture> {
    lib.state(clip as usize, f as usize).map(|s| s.posture())
}

/// Build the scene and write the page; returns the number of items.
pub fn run(req: &ViewRequest) -> Result<usize> {
    let lib = crate::table::load_library(&req.from)?;
    let root = crate::dataset::data_root(req.data_root.as_deref())?;
    let model = Model::for_skeleton(&root, lib.skeleton)?;
    let mut objs = Objects {
        pool: Vec::new(),
        names: Vec::new(),
    };
    let nob = lib.frames.first().map_or(0, |f| f.n_objects);
    let max = req.max_items.max(1);
    let mut items = Vec::new();

    let mut clips: Vec<usize> = req
        .clips
        .iter()
        .map(|c| clip_id(&lib, c))
        .collect::<Result<_>>()?;
    for s in &req.skills {
        let of = lib.clips_of(s);
        if of.is_empty() {
            bail!(
                "no clip of skill `{s}` in {} (its skills: {})",
                req.from.display(),
                lib.skills().join(", ")
            );
        }
        clips.extend(of);
    }
    if clips.is_empty() && req.stf.is_none() && req.rollouts.is_none() {
        clips = (0..lib.clips.len()).collect();
    }
    // each clip once, in the order asked (a --clip may also be in a --skill)
    let mut seen = std::collections::HashSet::new();
    clips.retain(|c| seen.insert(*c));
    for c in clips {
        let row = &lib.clips[c];
        let fr = &lib.frames[c];
        let poses: Vec<Option<Posture>> = (0..fr.frames)
            .map(|i| frame(&lib, c as u32, i as u32))
            .collect();
        items.push(Item {
            title: format!("clip {}: {}", row.clip_id, row.name),
            skill: format!("{} ({})", row.skill, row.label),
            note: format!(
                "{} frames at {} fps, {} missing",
                row.frames,
                row.fps,
                row.frames - row.valid_frames
            ),
            fps: row.fps as f64,
            objects: objs.of(&row.objects, &root)?,
            actors: vec![view::actor("reference", &model, nob, &poses, &[], None)?],
        });
    }

    if let Some(p) = &req.stf {
        let trajs = crate::table::stf::read_trajectories(p)?;
        crate::table::check_ingest_id(
            p,
            &crate::table::ingest_id(&req.from.join("clips.parquet"))?,
            "sample-stf",
        )?;
        let chosen: Vec<_> = if req.trajs.is_empty() {
            trajs.iter().take(max).collect()
        } else {
            req.trajs
                .iter()
                .map(|k| {
                    trajs.iter().find(|t| t.traj_id == *k).with_context(|| {
                        format!(
                            "{}: no trajectory {k} ({} in the file)",
                            p.display(),
                            trajs.len()
                        )
                    })
                })
                .collect::<Result<_>>()?
        };
        for t in chosen {
            // missing reference frames stay `None`: the actor holds the
            // last pose and marks them
            let mut poses = vec![Some(t.start.clone())];
            let mut masked = vec![false];
            let mut clip = None;
            for (m, r) in &t.steps {
                if let Some((c, _)) = r {
                    clip = Some(lib.clips.get(*c as usize).with_context(|| {
                        format!(
                            "{}: trajectory {} names clip {c}, which {} lacks",
                            p.display(),
                            t.traj_id,
                            req.from.display()
                        )
                    })?);
                }
                poses.push(r.and_then(|(c, f)| frame(&lib, c, f)));
                masked.push(*m);
            }
            let row = clip.unwrap_or(&lib.clips[0]);
            let (fps, obj_names) = (row.fps as f64, &row.objects);
            items.push(Item {
                title: format!("STF trajectory {} ({})", t.traj_id, t.start_kind),
                skill: t.target_skill.clone(),
                note: format!(
                    "start {}, beta {:.3}, {} masked states",
                    t.start_kind, t.beta, t.n_masked
                ),
                fps,
                objects: objs.of(obj_names, &root)?,
                actors: vec![view::actor(
                    "STF sample",
                    &model,
                    nob,
                    &poses,
                    &masked,
                    None,
                )?],
            });
        }
    }

    if let Some(p) = &req.rollouts {
        let file = if p.is_dir() {
            p.join("eval_rollouts.parquet")
        } else {
            p.clone()
        };
        let steps = crate::table::rollout::read(&file)?;
        if steps.is_empty() {
            bail!(
                "{}: no recorded steps (run `skillaug eval --record N`)",
                file.display()
            );
        }
        let mut trials: BTreeMap<(String, String, String, u32), Vec<&RolloutStep>> =
            BTreeMap::new();
        for s in &steps {
            if req.trials.is_empty() || req.trials.contains(&s.trial) {
                trials
                    .entry((s.metric.clone(), s.from.clone(), s.to.clone(), s.trial))
                    .or_default()
                    .push(s);
            }
        }
        if trials.is_empty() {
            bail!(
                "{}: none of the trials {:?} was recorded",
                file.display(),
                req.trials
            );
        }
        let mut per_cell: BTreeMap<(String, String, String), usize> = BTreeMap::new();
        for ((metric, from, to, trial), mut st) in trials {
            let n = per_cell
                .entry((metric.clone(), from.clone(), to.clone()))
                .or_default();
            if req.trials.is_empty() && *n >= max {
                continue;
            }
            *n += 1;
            st.sort_by_key(|s| s.step);
            let sim: Vec<Option<Posture>> = st.iter().map(|s| Some(s.posture.clone())).collect();
            let value: Vec<f32> = st
                .iter()
                .map(|s| s.sm_reward.map_or(f32::NAN, |v| v as f32))
                .collect();
            let refs: Vec<Option<Posture>> = st
                .iter()
                .map(|s| s.reference.and_then(|(c, f)| frame(&lib, c, f)))
                .collect();
            let clip = st.iter().find_map(|s| s.reference).map(|r| r.0 as usize);
            let (fps, obj_names) = match clip.and_then(|c| lib.clips.get(c)) {
                Some(r) => (r.fps as f64, r.objects.clone()),
                None => (lib.clips[0].fps as f64, lib.clips[0].objects.clone()),
            };
            let mut actors = vec![view::actor(
                "rollout",
                &model,
                nob,
                &sim,
                &st.iter().map(|s| s.masked).collect::<Vec<_>>(),
                Some(("SM", &value)),
            )?];
            if refs.iter().any(Option::is_some) {
                // a missing reference frame is drawn held and masked
                actors.push(view::actor("reference", &model, nob, &refs, &[], None)?);
            }
            let scored: Vec<f64> = st.iter().filter_map(|s| s.sm_reward).collect();
            items.push(Item {
                title: format!("{metric} {from}->{to} trial {trial}"),
                skill: if from == to {
                    from.clone()
                } else {
                    format!("{from} -> {to}")
                },
                note: format!(
                    "{} steps, mean SM {:.3}",
                    st.len(),
                    scored.iter().sum::<f64>() / scored.len().max(1) as f64
                ),
                fps,
                objects: objs.of(&obj_names, &root)?,
                actors,
            });
        }
    }

    let scene = Scene {
        title: format!("{} ({})", req.from.display(), lib.clips[0].dataset),
        bodies: view::bodies(&model)?,
        objects: objs.pool,
        items,
    };
    view::write(&scene, &req.out)?;
    Ok(scene.items.len())
}
