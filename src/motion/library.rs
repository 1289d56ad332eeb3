//! A motion library: every ingested clip with its per-frame state, as later
//! stages use it (loaded from a run folder by [`crate::table::load_library`]).

use super::clip::ClipFrames;
use super::layout::Skeleton;
use super::state::State;
use anyhow::{bail, Result};

/// Slots of the skill condition c: a one-hot of the class id (64 in
/// SkillMimic's observation, Section 4 of the SkillMimic-V2 paper's
/// appendix; `rl::humanoid` builds it). A class id must be below this.
pub const CONDITION_SLOTS: usize = 64;

/// Why a clip cannot be used, or `None` when it can: a clip needs two
/// consecutive valid frames (one transition, from which its velocities,
/// its training references and the history encoder's windows are made).
pub fn unusable(c: &ClipFrames) -> Option<String> {
    let valid = c.valid_frames();
    if valid == 0 {
        return Some(format!(
            "no valid frame (all {} rows are zero or missing)",
            c.frames
        ));
    }
    if !(1..c.frames).any(|i| c.valid[i] && c.valid[i - 1]) {
        return Some(format!(
            "{valid} valid frame(s) of {} and no two consecutive ones; a clip needs at least one \
             pair of consecutive valid frames",
            c.frames
        ));
    }
    None
}

/// The class rule every stage applies (ingest on its clip list, later
/// stages on `clips.parquet`): each class id is below
/// [`CONDITION_SLOTS`], and class ids and skills correspond one to one,
/// so that the condition tells every skill apart. `clips` yields
/// (clip name, skill, class id).
///
/// # Errors
/// Names the clip whose class does not fit, or the two skills (and a
/// clip of each) that share a class, or the two classes of one skill.
pub fn check_classes<'a>(clips: impl IntoIterator<Item = (&'a str, &'a str, u32)>) -> Result<()> {
    use std::collections::BTreeMap;
    let mut by_class: BTreeMap<u32, (&str, &str)> = BTreeMap::new();
    let mut by_skill: BTreeMap<&str, (u32, &str)> = BTreeMap::new();
    let mut faults = Vec::new();
    for (name, skill, class) in clips {
        if class as usize >= CONDITION_SLOTS {
            faults.push(format!(
                "clip {name} (skill {skill}): class id {class} does not fit the {CONDITION_SLOTS}-slot \
                 skill condition (ids 0-{})",
                CONDITION_SLOTS - 1
            ));
            continue;
        }
        let (other, other_name) = *by_class.entry(class).or_insert((skill, name));
        if other != skill {
            faults.push(format!(
                "class id {class} is given to two skills, {other} (clip {other_name}) and {skill} \
                 (clip {name}): the skill condition could not tell them apart"
            ));
        }
        let (other, other_name) = *by_skill.entry(skill).or_insert((class, name));
        if other != class {
            faults.push(format!(
                "skill {skill} has two class ids, {other} (clip {other_name}) and {class} (clip \
                 {name})"
            ));
        }
    }
    if !faults.is_empty() {
        bail!(
            "{}\n(each skill needs its own class id below {CONDITION_SLOTS}, the same for all its \
             clips: a folder clip's class is the first three characters of its file name, a \
             manifest clip's its `class` key)",
            faults.join("\n")
        );
    }
    Ok(())
}

/// One clip's description (a row of the `clips` table; `skillaug schema
/// clips` gives each column's meaning and units).
#[derive(Debug, Clone)]
pub struct ClipRow {
    /// Clip id: its index in the run folder's clip list.
    pub clip_id: u32,
    /// Clip name (the file stem).
    pub name: String,
    /// Dataset name.
    pub dataset: String,
    /// Skill.
    pub skill: String,
    /// Class id (the condition slot, below [`CONDITION_SLOTS`]).
    pub class: u16,
    /// Human label (DF, Layup, Place-Book, ...).
    pub label: String,
    /// Source path of the clip file.
    pub source: String,
    /// sha256 of the clip file, hex.
    pub sha256: String,
    /// Frames F.
    pub frames: u32,
    /// Valid (not missing) frames.
    pub valid_frames: u32,
    /// Frame rate, Hz.
    pub fps: f32,
    /// Tensor layout (D337, D409, D415).
    pub layout: String,
    /// Humanoid model name.
    pub skeleton: String,
    /// Names of the objects in the clip's state, in order.
    pub objects: Vec<String>,
}

/// The ingested clips of one run folder.
#[derive(Debug, Clone)]
pub struct MotionLib {
    /// Skeleton shared by every clip.
    pub skeleton: Skeleton,
    /// One row per clip, indexed by clip_id.
    pub clips: Vec<ClipRow>,
    /// Per-frame state of each clip, indexed by clip_id.
    pub frames: Vec<ClipFrames>,
}

impl MotionLib {
    /// Check what every later stage needs before it starts: every clip
    /// usable ([`unusable`]) and the class rule ([`check_classes`]).
    /// `source` names where the clips came from, for the messages.
    ///
    /// # Errors
    /// Lists every unusable clip by name and skill, or the class fault.
    pub fn check(&self, source: &str) -> Result<()> {
        let bad: Vec<String> = self
            .clips
            .iter()
            .zip(&self.frames)
            .filter_map(|(c, f)| {
                unusable(f).map(|why| format!("clip {} (skill {}): {why}", c.name, c.skill))
            })
            .collect();
        if !bad.is_empty() {
            bail!(
                "{source}: {} clip(s) cannot be used; ingest again without them (`skillaug ingest` \
                 refuses such clips, `--skip-bad` leaves them out):\n  {}",
                bad.len(),
                bad.join("\n  ")
            );
        }
        check_classes(
            self.clips
                .iter()
                .map(|c| (c.name.as_str(), c.skill.as_str(), c.class as u32)),
        )
        .map_err(|e| anyhow::anyhow!("{source}: {e}"))
    }

    /// The state of frame `frame` of clip `clip` (`None` if missing).
    pub fn state(&self, clip: usize, frame: usize) -> Option<State> {
        self.frames.get(clip)?.state(frame)
    }

    /// Distinct skills in clip order of first appearance.
    pub fn skills(&self) -> Vec<String> {
        let mut v: Vec<String> = Vec::new();
        for c in &self.clips {
            if !v.contains(&c.skill) {
                v.push(c.skill.clone());
            }
        }
        v
    }

    /// Clip ids of `skill`.
    pub fn clips_of(&self, skill: &str) -> Vec<usize> {
        (0..self.clips.len())
            .filter(|i| self.clips[*i].skill == skill)
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn class_rule_refuses_large_ids_and_shared_classes() {
        assert!(check_classes([("a", "run", 13), ("b", "run", 13), ("c", "lrun", 11)]).is_ok());
        let e = check_classes([("099_x", "x", 99)]).unwrap_err().to_string();
        assert!(
            e.contains("099_x") && e.contains("99") && e.contains("64"),
            "{e}"
        );
        assert!(check_classes([("a", "s", 63)]).is_ok());
        assert!(check_classes([("a", "s", 64)]).is_err());
        let e = check_classes([("a", "run", 13), ("b", "walk", 13)])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("run") && e.contains("walk") && e.contains("13"),
            "{e}"
        );
        let e = check_classes([("a", "run", 13), ("b", "run", 14)])
            .unwrap_err()
            .to_string();
        assert!(e.contains("two class ids"), "{e}");
    }

    #[test]
    fn a_clip_needs_two_consecutive_valid_frames() {
        let mut c = ClipFrames {
            frames: 5,
            valid: vec![false; 5],
            ..Default::default()
        };
        assert!(unusable(&c).unwrap().contains("no valid frame"));
        c.valid = vec![true, false, true, false, true];
        assert!(unusable(&c).unwrap().contains("no two consecutive"));
        c.valid = vec![false, false, true, true, false];
        assert!(unusable(&c).is_none());
    }
}
