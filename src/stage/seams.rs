//! `skillaug seams`: where each clip's reference continues when training
//! carries an episode past the clip's end ([`crate::augment::seam`]): per
//! clip its last valid frame, the most similar frame of the same skill
//! (root x, y and heading aligned), the similarity β and the masked states
//! N that Eq. 20 puts at the seam (`[sample-stf]` τ, N_max and rule). With
//! `train.seam_leave_search_s` the clips are first cut where training
//! leaves them, and `last` is that frame. With `train.reference_hand =
//! "on-ball"` the ball clips' pushing hands are first put on their ball
//! ([`crate::sim::hand_path`]), and with `train.reference_ball =
//! "simulated"` their flights simulated ([`crate::sim::ball_path`]), as
//! training does.

use super::Common;
use crate::augment::{n_masked, seam};
use anyhow::Result;

/// Run the command: print the table.
pub fn run(common: &Common) -> Result<()> {
    let cfg: crate::rl::config::TrainConfig = common.settings("train")?;
    let stf: crate::augment::settings::StfConfig = common.settings("sample-stf")?;
    let (p, _) = stf.params()?;
    let input = common.input_dir();
    let mut lib = crate::table::load_library(input)?;
    let fps = lib.clips.first().map_or(60.0, |c| c.fps as f64);
    if cfg.reference_ball == crate::sim::ball_path::ReferenceBall::Simulated
        || cfg.reference_hand == crate::sim::hand_path::ReferenceHand::OnBall
    {
        repair_ball_clips(&mut lib, common, &cfg)?;
    }
    if cfg.seam_leave_search_s > 0.0 {
        let all: Vec<usize> = (0..lib.clips.len()).collect();
        seam::cut_at_leave_frames(
            &mut lib,
            &all,
            cfg.seam_min_loop_s,
            cfg.seam_leave_search_s,
            fps,
        );
    }
    let (seams, min_loop) = seam::training_seams(&lib, cfg.seam_min_loop_s, fps);
    println!(
        "{:<16} {:<34} {:>5}   {:<34} {:>5} {:>10} {:>3}",
        "skill", "clip", "last", "continues in", "frame", "beta", "N"
    );
    for (c, s) in seams.iter().enumerate() {
        let row = &lib.clips[c];
        match s {
            Some(s) => println!(
                "{:<16} {:<34} {:>5}   {:<34} {:>5} {:>10.4} {:>3}",
                row.skill,
                row.name,
                s.last,
                lib.clips[s.to_clip as usize].name,
                s.to_frame,
                s.beta,
                n_masked(s.beta, p.tau, p.n_max, p.mask_rule)
                    .map_or("-".to_string(), |n| n.to_string())
            ),
            None => println!(
                "{:<16} {:<34}   no seam (no frame of the skill at least {min_loop} frames from an end)",
                row.skill, row.name
            ),
        }
    }
    Ok(())
}

/// The ball clips of `lib` (object 0 the ball; every group of clips with
/// the same objects in one world) with their pushing hands and their
/// flights changed as training changes them
/// ([`crate::rl::trainer::reference_hands`], then
/// [`crate::rl::trainer::reference_flights`]; each only when its setting
/// is on); clips without a ball keep theirs.
///
/// # Errors
/// A model or object that cannot be loaded; ball clips without a push
/// window, or none of whose flights could be simulated.
fn repair_ball_clips(
    lib: &mut crate::motion::MotionLib,
    common: &Common,
    cfg: &crate::rl::config::TrainConfig,
) -> Result<()> {
    use crate::rl::trainer::{reference_flights, reference_hands, training_objects, training_sim};
    let root = crate::dataset::data_root(common.args.data_root.as_deref())?;
    let model = crate::sim::mjcf::Model::for_skeleton(&root, lib.skeleton)?;
    let mut groups: Vec<(Vec<String>, Vec<usize>)> = Vec::new();
    for (c, row) in lib.clips.iter().enumerate() {
        if row.objects.first().is_none_or(|o| o != "ball") {
            continue;
        }
        match groups.iter_mut().find(|(o, _)| *o == row.objects) {
            Some((_, clips)) => clips.push(c),
            None => groups.push((row.objects.clone(), vec![c])),
        }
    }
    for (names, clips) in groups {
        let objects = training_objects(&names, &root, cfg)?;
        let sim = training_sim(lib.clips[clips[0]].fps as f64, cfg);
        reference_hands(lib, &clips, &model, &objects, cfg)?;
        reference_flights(lib, &clips, &model, &objects, &sim, cfg)?;
    }
    Ok(())
}
