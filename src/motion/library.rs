//! A motion library: every ingested clip with its per-frame state, as later
//! stages use it (loaded from a run folder by [`crate::table::load_library`]).

use super::clip::ClipFrames;
use super::layout::Skeleton;
use super::state::State;
use crate::table::clips::ClipRow;

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
