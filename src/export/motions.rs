//! The motions skillaug holds, gathered from a run folder for playback
//! (`skillaug view`) and export (`skillaug export`): reference clips of
//! `frames.parquet`, STF samples of `stf_samples.parquet` and rollouts
//! recorded by `skillaug eval --record N`, each as one or more tracks of
//! per-frame postures at the clip's rate.

use crate::motion::state::Posture;
use crate::motion::MotionLib;
use crate::table::rollout::RolloutStep;
use anyhow::{bail, Context, Result};
use std::collections::BTreeMap;
use std::path::PathBuf;

/// Which motions to gather.
#[derive(Clone, Debug, Default)]
pub struct Selection {
    /// Run folder with clips.parquet and frames.parquet (for the names of
    /// the messages and the ingest-id check of `stf`).
    pub from: PathBuf,
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
}

/// One character's motion: a posture per frame.
#[derive(Clone, Debug)]
pub struct Track {
    /// `reference`, `STF sample`, `rollout`.
    pub name: String,
    /// Per frame (`None`: a missing frame; players hold the last posture).
    pub frames: Vec<Option<Posture>>,
    /// Per frame: masked (no reward target); empty: none.
    pub masked: Vec<bool>,
    /// Per frame: the step's SM reward (rollouts; NaN: none).
    pub value: Option<Vec<f32>>,
}

/// One clip, STF trajectory or trial.
#[derive(Clone, Debug)]
pub struct Motion {
    /// Title (`clip 3: 013_018pickle_run_4`).
    pub title: String,
    /// A name usable as a file stem (`clip-013_018pickle_run_4`,
    /// `stf-12`, `sr-run-run-trial-0`).
    pub stem: String,
    /// Skill label.
    pub skill: String,
    /// One line of details.
    pub note: String,
    /// Frame rate, Hz.
    pub fps: f64,
    /// Object names, in state order.
    pub objects: Vec<String>,
    /// One or more characters on one clock (a rollout, then its reference).
    pub tracks: Vec<Track>,
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

fn safe(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '_' || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Gather the motions `sel` asks for from `lib` (the clips of `sel.from`).
///
/// # Errors
/// An unknown clip, skill, trajectory or trial (named), an STF file of
/// another ingest run, a rollouts table without recorded steps.
pub fn gather(lib: &MotionLib, sel: &Selection) -> Result<Vec<Motion>> {
    let max = sel.max_items.max(1);
    let mut items = Vec::new();

    let mut clips: Vec<usize> = sel
        .clips
        .iter()
        .map(|c| clip_id(lib, c))
        .collect::<Result<_>>()?;
    for s in &sel.skills {
        let of = lib.clips_of(s);
        if of.is_empty() {
            bail!(
                "no clip of skill `{s}` in {} (its skills: {})",
                sel.from.display(),
                lib.skills().join(", ")
            );
        }
        clips.extend(of);
    }
    if clips.is_empty() && sel.stf.is_none() && sel.rollouts.is_none() {
        clips = (0..lib.clips.len()).collect();
    }
    // each clip once, in the order asked (a --clip may also be in a --skill)
    let mut seen = std::collections::HashSet::new();
    clips.retain(|c| seen.insert(*c));
    for c in clips {
        let row = &lib.clips[c];
        let fr = &lib.frames[c];
        let poses: Vec<Option<Posture>> = (0..fr.frames)
            .map(|i| frame(lib, c as u32, i as u32))
            .collect();
        items.push(Motion {
            title: format!("clip {}: {}", row.clip_id, row.name),
            stem: format!("clip-{}", safe(&row.name)),
            skill: format!("{} ({})", row.skill, row.label),
            note: format!(
                "{} frames at {} fps, {} missing",
                row.frames,
                row.fps,
                row.frames - row.valid_frames
            ),
            fps: row.fps as f64,
            objects: row.objects.clone(),
            tracks: vec![Track {
                name: "reference".into(),
                frames: poses,
                masked: Vec::new(),
                value: None,
            }],
        });
    }

    if let Some(p) = &sel.stf {
        let trajs = crate::table::stf::read_trajectories(p)?;
        crate::table::check_ingest_id(
            p,
            &crate::table::ingest_id(&sel.from.join("clips.parquet"))?,
            "sample-stf",
        )?;
        let chosen: Vec<_> = if sel.trajs.is_empty() {
            trajs.iter().take(max).collect()
        } else {
            sel.trajs
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
            // missing reference frames stay `None`
            let mut poses = vec![Some(t.start.clone())];
            let mut masked = vec![false];
            let mut clip = None;
            for st in &t.steps {
                if let Some((c, _)) = st.reference {
                    clip = Some(lib.clips.get(c as usize).with_context(|| {
                        format!(
                            "{}: trajectory {} names clip {c}, which {} lacks",
                            p.display(),
                            t.traj_id,
                            sel.from.display()
                        )
                    })?);
                }
                poses.push(st.reference.and_then(|(c, f)| frame(lib, c, f)));
                masked.push(st.masked);
            }
            let row = clip.unwrap_or(&lib.clips[0]);
            items.push(Motion {
                title: format!("STF trajectory {} ({})", t.traj_id, t.start_kind),
                stem: format!("stf-{}", t.traj_id),
                skill: t.target_skill.clone(),
                note: format!(
                    "start {}, beta {:.3}, {} masked states",
                    t.start_kind, t.beta, t.n_masked
                ),
                fps: row.fps as f64,
                objects: row.objects.clone(),
                tracks: vec![Track {
                    name: "STF sample".into(),
                    frames: poses,
                    masked,
                    value: None,
                }],
            });
        }
    }

    if let Some(p) = &sel.rollouts {
        let file = if p.is_dir() {
            p.join("eval_rollouts.parquet")
        } else {
            p.clone()
        };
        let steps = crate::table::rollout::read(&file)?;
        // the references are clip ids of the evaluated run's clips
        crate::table::check_ingest_id(
            &file,
            &crate::table::ingest_id(&sel.from.join("clips.parquet"))?,
            "eval --record N",
        )?;
        if steps.is_empty() {
            bail!(
                "{}: no recorded steps (run `skillaug eval --record N`)",
                file.display()
            );
        }
        let mut trials: BTreeMap<(String, String, String, u32), Vec<&RolloutStep>> =
            BTreeMap::new();
        for s in &steps {
            if sel.trials.is_empty() || sel.trials.contains(&s.trial) {
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
                sel.trials
            );
        }
        let mut per_cell: BTreeMap<(String, String, String), usize> = BTreeMap::new();
        for ((metric, from, to, trial), mut st) in trials {
            let n = per_cell
                .entry((metric.clone(), from.clone(), to.clone()))
                .or_default();
            if sel.trials.is_empty() && *n >= max {
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
                .map(|s| s.reference.and_then(|(c, f)| frame(lib, c, f)))
                .collect();
            let clip = st.iter().find_map(|s| s.reference).map(|r| r.0 as usize);
            let row = clip.and_then(|c| lib.clips.get(c)).unwrap_or(&lib.clips[0]);
            let mut tracks = vec![Track {
                name: "rollout".into(),
                frames: sim,
                masked: st.iter().map(|s| s.masked).collect(),
                value: Some(value),
            }];
            if refs.iter().any(Option::is_some) {
                tracks.push(Track {
                    name: "reference".into(),
                    frames: refs,
                    masked: Vec::new(),
                    value: None,
                });
            }
            let scored: Vec<f64> = st.iter().filter_map(|s| s.sm_reward).collect();
            items.push(Motion {
                title: format!("{metric} {from}->{to} trial {trial}"),
                stem: format!("{metric}-{}-{}-trial-{trial}", safe(&from), safe(&to)),
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
                fps: row.fps as f64,
                objects: row.objects.clone(),
                tracks,
            });
        }
    }
    Ok(items)
}
