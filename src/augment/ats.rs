//! Adaptive Trajectory Sampling (paper Section 4.5, Eq. 8; reference code:
//! Ingrid789/SkillMimic-V2 `skillmimic/utils/motion_data_handler.py` and
//! `skillmimic/env/tasks/skillmimic1_reweight.py`): where an episode starts.
//!
//! * **Start frames.** A clip's allowed start frames are its valid frames in
//!   `[2, F - 2]` (as in `motion_data_handler.py`: the first two and the last
//!   frame are never start frames); a clip with no valid frame there may start
//!   at any valid frame. Missing frames always get weight zero. The same set is
//!   what the STF connection (Eq. 6) searches ([`start_frames`]).
//! * **Frame weights** (Eq. 8): p_i ∝ exp(-lambda_s r̄_i) over the allowed
//!   start frames of a clip, where r̄_i is the mean reward of rollouts started
//!   at frame i. lambda_s = 0 gives exactly uniform weights over the allowed
//!   frames. The paper averages r̄_i over the rest of the clip; the trainer
//!   (like the reference code, `skillmimic1_reweight.py`) records the mean
//!   reward of its horizon-long episodes started at i ([`Ats::record`]).
//! * **Never-visited frames.** The paper is silent; the reference code keeps
//!   M = 0 for them (`skillmimic1_reweight.py`), i.e. the *highest* weight, so
//!   unexplored start frames are tried first. skillaug does the same: an
//!   unvisited frame counts as reward 0.
//! * **Class weights** (lambda_c): P_c ∝ exp(-lambda_c C_c), C_c = mean over
//!   the class's clips of R_i, R_i = mean of r̄ over the clip's allowed frames
//!   (the reference code, `_reweight_clip_sampling_rate_vectorized` in
//!   `motion_data_handler.py`, uses a one-step snapshot of the current rewards
//!   instead). With no rewards every class gets the same weight.
//! * **Clip weights within a class**: P_{i|c} ∝ exp(-lambda_i R_i). The paper
//!   does not mention an intra-class term: `lambda_i = 0` (default) is uniform
//!   within the class; the reference code uses `lambda_i = 5`.
//! * **Updates**: [`Update::Mean`] keeps a running mean per (clip, frame);
//!   [`Update::Halving`] is the reference code's M <- (M + r) / 2
//!   (`skillmimic1_reweight.py`).
//!
//! Pure code: the weights are computed once ([`Ats::weights`]) and sampled
//! many times ([`AtsWeights`]); the trainer re-computes them after updates.

use crate::motion::{ClipFrames, MotionLib};
use rand::Rng;
use serde::{Deserialize, Serialize};

/// How [`Ats::record`] folds a new episode reward into a frame's statistic.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Update {
    /// Running mean of every recorded reward.
    #[default]
    Mean,
    /// Reference code: M <- (M + r) / 2, starting from M = 0.
    Halving,
}

/// ATS settings (Table 7).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AtsParams {
    /// Frame-level exponent lambda_s (Eq. 8; 10).
    pub lambda_s: f64,
    /// Inter-class exponent lambda_c (5).
    pub lambda_c: f64,
    /// Intra-class clip exponent (0 = uniform within a class; reference code 5).
    pub lambda_i: f64,
    /// Update rule of [`Ats::record`].
    pub update: Update,
}

impl Default for AtsParams {
    fn default() -> Self {
        AtsParams {
            lambda_s: 10.0,
            lambda_c: 5.0,
            lambda_i: 0.0,
            update: Update::Mean,
        }
    }
}

/// Allowed start frames of a clip (also the frames Eq. 6 may connect to):
/// valid frames in `[2, F - 2]`, or every valid frame if that leaves none.
pub fn start_frames(c: &ClipFrames) -> Vec<bool> {
    let inner: Vec<bool> = (0..c.frames)
        .map(|i| c.valid[i] && i >= 2 && i + 2 <= c.frames)
        .collect();
    if inner.iter().any(|v| *v) {
        inner
    } else {
        c.valid.clone()
    }
}

/// Per-clip, per-frame mean rewards of rollouts started at each frame, with
/// the allowed start frames.
#[derive(Clone, Debug)]
pub struct Ats {
    class: Vec<u32>,
    allowed: Vec<Vec<bool>>,
    /// Mean reward; NaN = never visited.
    mean: Vec<Vec<f64>>,
    visits: Vec<Vec<u64>>,
}

/// Weights computed from an [`Ats`] table, ready to sample.
#[derive(Clone, Debug, PartialEq)]
pub struct AtsWeights {
    /// Probability of each clip (P_c P_{i|c}; 0 for a clip that cannot start).
    pub clip: Vec<f64>,
    /// Per clip, the probability of each frame (sums to 1 over its allowed frames).
    pub frames: Vec<Vec<f64>>,
    /// Per class (ascending id): the class weight P_c.
    pub class: Vec<(u32, f64)>,
}

/// Index drawn from non-negative `w` with probability proportional to `w`
/// (`None` if every weight is zero). One uniform draw.
pub fn pick<R: Rng>(w: &[f64], rng: &mut R) -> Option<usize> {
    let total: f64 = w.iter().filter(|x| **x > 0.0).sum();
    if total.is_nan() || total <= 0.0 {
        return None;
    }
    let u = rng.random::<f64>() * total;
    let mut acc = 0.0;
    let mut last = None;
    for (i, &x) in w.iter().enumerate() {
        if x > 0.0 {
            acc += x;
            last = Some(i);
            if u < acc {
                return last;
            }
        }
    }
    last
}

/// exp(-lambda (r - min r)) normalised to sum 1 (softmax of -lambda r); an
/// empty input gives an empty output.
fn softmin(r: &[f64], lambda: f64) -> Vec<f64> {
    let lo = r.iter().copied().fold(f64::INFINITY, f64::min);
    let e: Vec<f64> = r.iter().map(|x| (-lambda * (x - lo)).exp()).collect();
    let s: f64 = e.iter().sum();
    e.into_iter().map(|x| x / s).collect()
}

impl Ats {
    /// Every clip of `lib`, nothing visited.
    pub fn new(lib: &MotionLib) -> Ats {
        Ats::from_parts(
            lib.clips.iter().map(|c| c.class as u32).collect(),
            lib.frames.iter().map(start_frames).collect(),
        )
    }

    /// The clips of `lib` for which `keep(clip)` holds, nothing visited:
    /// the others never start an episode (skills left out of a run).
    pub fn for_clips(lib: &MotionLib, keep: impl Fn(usize) -> bool) -> Ats {
        let mut ats = Ats::new(lib);
        for c in (0..lib.clips.len()).filter(|c| !keep(*c)) {
            ats.disable_clip(c);
        }
        ats
    }

    /// From each clip's class and allowed start frames.
    pub fn from_parts(class: Vec<u32>, allowed: Vec<Vec<bool>>) -> Ats {
        assert_eq!(class.len(), allowed.len(), "one class per clip");
        let mean = allowed.iter().map(|a| vec![f64::NAN; a.len()]).collect();
        let visits = allowed.iter().map(|a| vec![0; a.len()]).collect();
        Ats {
            class,
            allowed,
            mean,
            visits,
        }
    }

    /// Number of clips.
    pub fn clips(&self) -> usize {
        self.class.len()
    }

    /// The allowed start frames of `clip`.
    pub fn allowed(&self, clip: usize) -> &[bool] {
        &self.allowed[clip]
    }

    /// Never start in `clip` (e.g. a skill left out of a run).
    pub fn disable_clip(&mut self, clip: usize) {
        self.allowed[clip].iter_mut().for_each(|a| *a = false);
    }

    /// Set the mean reward of (clip, frame) as if visited once (a rewards
    /// table). Out-of-range indices are ignored.
    pub fn set_mean(&mut self, clip: usize, frame: usize, reward: f64) {
        if let Some(m) = self.mean.get_mut(clip).and_then(|m| m.get_mut(frame)) {
            *m = reward;
            self.visits[clip][frame] = 1;
        }
    }

    /// Fold the mean reward of an episode started at (clip, frame) into its
    /// statistic (the trainer's online update). Out-of-range indices are ignored.
    pub fn record(&mut self, clip: usize, frame: usize, episode_mean_reward: f64, update: Update) {
        let Some(m) = self.mean.get_mut(clip).and_then(|m| m.get_mut(frame)) else {
            return;
        };
        let n = &mut self.visits[clip][frame];
        let old = if m.is_nan() { 0.0 } else { *m };
        *n += 1;
        *m = match update {
            Update::Mean => old + (episode_mean_reward - old) / *n as f64,
            Update::Halving => (old + episode_mean_reward) / 2.0,
        };
    }

    /// Every visited (clip, frame) with its statistic and visit count (a
    /// checkpoint of the table; [`Ats::restore_stat`] puts them back).
    pub fn visited(&self) -> Vec<(usize, usize, f64, u64)> {
        let mut v = Vec::new();
        for (c, row) in self.mean.iter().enumerate() {
            for (f, m) in row.iter().enumerate() {
                if !m.is_nan() {
                    v.push((c, f, *m, self.visits[c][f]));
                }
            }
        }
        v
    }

    /// Set the statistic and visit count of (clip, frame) exactly.
    /// Out-of-range indices are ignored.
    pub fn restore_stat(&mut self, clip: usize, frame: usize, mean: f64, visits: u64) {
        if let Some(m) = self.mean.get_mut(clip).and_then(|m| m.get_mut(frame)) {
            *m = mean;
            self.visits[clip][frame] = visits;
        }
    }

    /// The statistic of (clip, frame); `None` if never visited.
    pub fn mean_reward(&self, clip: usize, frame: usize) -> Option<f64> {
        let m = *self.mean.get(clip)?.get(frame)?;
        (!m.is_nan()).then_some(m)
    }

    /// Times (clip, frame) was recorded.
    pub fn visits(&self, clip: usize, frame: usize) -> u64 {
        self.visits[clip][frame]
    }

    /// r̄ of a frame for weighting: its mean, 0 when never visited.
    fn r(&self, clip: usize, frame: usize) -> f64 {
        self.mean_reward(clip, frame).unwrap_or(0.0)
    }

    /// Eq. 8 over the allowed start frames of `clip` (zero elsewhere; all
    /// zero if the clip cannot start).
    pub fn frame_weights(&self, clip: usize, lambda_s: f64) -> Vec<f64> {
        let idx: Vec<usize> = (0..self.allowed[clip].len())
            .filter(|f| self.allowed[clip][*f])
            .collect();
        let r: Vec<f64> = idx.iter().map(|f| self.r(clip, *f)).collect();
        let mut w = vec![0.0; self.allowed[clip].len()];
        for (f, p) in idx.iter().zip(softmin(&r, lambda_s)) {
            w[*f] = p;
        }
        w
    }

    /// R_i: mean r̄ over the clip's allowed frames (`None` if it cannot start).
    pub fn clip_reward(&self, clip: usize) -> Option<f64> {
        let v: Vec<f64> = (0..self.allowed[clip].len())
            .filter(|f| self.allowed[clip][*f])
            .map(|f| self.r(clip, f))
            .collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    }

    /// P_c ∝ exp(-lambda_c C_c) for each class with a clip that can start,
    /// ascending class id.
    pub fn class_weights(&self, lambda_c: f64) -> Vec<(u32, f64)> {
        let mut classes: Vec<u32> = (0..self.clips())
            .filter(|c| self.clip_reward(*c).is_some())
            .map(|c| self.class[c])
            .collect();
        classes.sort_unstable();
        classes.dedup();
        let cr: Vec<f64> = classes
            .iter()
            .map(|k| {
                let r: Vec<f64> = (0..self.clips())
                    .filter(|c| self.class[*c] == *k)
                    .filter_map(|c| self.clip_reward(c))
                    .collect();
                r.iter().sum::<f64>() / r.len() as f64
            })
            .collect();
        classes.into_iter().zip(softmin(&cr, lambda_c)).collect()
    }

    /// Clip probabilities P_c P_{i|c} (zero for clips that cannot start).
    pub fn clip_weights(&self, p: &AtsParams) -> Vec<f64> {
        let cw = self.class_weights(p.lambda_c);
        let mut w = vec![0.0; self.clips()];
        for (k, pc) in cw {
            let members: Vec<usize> = (0..self.clips())
                .filter(|c| self.class[*c] == k && self.clip_reward(*c).is_some())
                .collect();
            let r: Vec<f64> = members
                .iter()
                .map(|c| self.clip_reward(*c).unwrap())
                .collect();
            for (c, pi) in members.iter().zip(softmin(&r, p.lambda_i)) {
                w[*c] = pc * pi;
            }
        }
        w
    }

    /// Every weight, ready to sample.
    pub fn weights(&self, p: &AtsParams) -> AtsWeights {
        AtsWeights {
            clip: self.clip_weights(p),
            frames: (0..self.clips())
                .map(|c| self.frame_weights(c, p.lambda_s))
                .collect(),
            class: self.class_weights(p.lambda_c),
        }
    }
}

impl AtsWeights {
    /// A clip (class by P_c, then clip by P_{i|c}); `None` if none can start.
    pub fn sample_clip<R: Rng>(&self, rng: &mut R) -> Option<usize> {
        pick(&self.clip, rng)
    }

    /// A start frame of `clip` by Eq. 8; `None` if it has none.
    pub fn sample_frame<R: Rng>(&self, clip: usize, rng: &mut R) -> Option<usize> {
        pick(self.frames.get(clip)?, rng)
    }

    /// A clip, then a start frame of it.
    pub fn sample<R: Rng>(&self, rng: &mut R) -> Option<(usize, usize)> {
        let c = self.sample_clip(rng)?;
        Some((c, self.sample_frame(c, rng)?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// Two classes: class 7 with clips 0 (10 frames) and 1 (8 frames, frame 4
    /// missing), class 3 with clip 2 (6 frames).
    fn table() -> Ats {
        let clip = |f: usize, missing: &[usize]| -> ClipFrames {
            ClipFrames {
                frames: f,
                valid: (0..f).map(|i| !missing.contains(&i)).collect(),
                ..Default::default()
            }
        };
        let clips = [clip(10, &[]), clip(8, &[4]), clip(6, &[])];
        Ats::from_parts(vec![7, 7, 3], clips.iter().map(start_frames).collect())
    }

    #[test]
    fn start_frames_are_2_to_f_minus_2_without_missing_ones() {
        let a = table();
        let on = |c: usize| -> Vec<usize> {
            (0..a.allowed(c).len())
                .filter(|f| a.allowed(c)[*f])
                .collect()
        };
        assert_eq!(on(0), [2, 3, 4, 5, 6, 7, 8]);
        assert_eq!(on(1), [2, 3, 5, 6]);
        assert_eq!(on(2), [2, 3, 4]);
        // a clip too short for the inner range may start at any valid frame
        let short = ClipFrames {
            frames: 3,
            valid: vec![true, false, true],
            ..Default::default()
        };
        assert_eq!(start_frames(&short), [true, false, true]);
    }

    #[test]
    fn lambda_zero_is_exactly_uniform_over_valid_frames() {
        let mut a = table();
        for f in 0..8 {
            a.record(1, f, f as f64 / 10.0, Update::Mean);
        }
        let w = a.frame_weights(1, 0.0);
        assert_eq!(w, [0.0, 0.0, 0.25, 0.25, 0.0, 0.25, 0.25, 0.0]);
        let w = a.frame_weights(0, 0.0);
        assert!(w[2..=8].iter().all(|p| *p == 1.0 / 7.0), "{w:?}");
        assert_eq!(w[0] + w[1] + w[9], 0.0);
    }

    #[test]
    fn missing_frames_get_zero_and_larger_reward_gets_smaller_weight() {
        let mut a = table();
        a.set_mean(1, 2, 0.9);
        a.set_mean(1, 3, 0.5);
        a.set_mean(1, 4, 0.0); // missing: stays zero
        a.set_mean(1, 5, 0.1);
        // frame 6 never visited: reward 0, the highest weight
        let w = a.frame_weights(1, 10.0);
        assert_eq!(w[4], 0.0);
        assert!(w[2] < w[3] && w[3] < w[5] && w[5] < w[6], "{w:?}");
        let s: f64 = w.iter().sum();
        assert!((s - 1.0).abs() < 1e-12);
        // Eq. 8 exactly: ratios exp(-lambda (r_a - r_b))
        assert!((w[2] / w[3] - (-10.0f64 * 0.4).exp()).abs() < 1e-12);
        assert!((w[6] / w[5] - 1.0f64.exp()).abs() < 1e-12);
    }

    #[test]
    fn class_weights_follow_lambda_c_and_clips_are_uniform_within_a_class() {
        let mut a = table();
        let p = AtsParams::default();
        // no rewards: classes equal, clips uniform within their class
        assert_eq!(a.class_weights(5.0), [(3, 0.5), (7, 0.5)]);
        assert_eq!(a.clip_weights(&p), [0.25, 0.25, 0.5]);
        // class 7 does well (mean 0.6 over every allowed frame), class 3 not visited
        for f in 0..10 {
            a.set_mean(0, f, 0.6);
        }
        for f in 0..8 {
            a.set_mean(1, f, 0.6);
        }
        let cw = a.class_weights(5.0);
        let want = 1.0 / (1.0 + (-5.0f64 * 0.6).exp());
        assert_eq!(cw[0].0, 3);
        assert!((cw[0].1 - want).abs() < 1e-12, "{cw:?}");
        assert!(cw[1].1 < cw[0].1);
        // lambda_c = 0: equal again
        assert_eq!(a.class_weights(0.0), [(3, 0.5), (7, 0.5)]);
        // intra-class option: the worse clip of class 7 is preferred
        a.set_mean(0, 3, 0.0);
        let w = a.clip_weights(&AtsParams { lambda_i: 5.0, ..p });
        assert!(w[0] > w[1]);
        let w0 = a.clip_weights(&p);
        assert_eq!(w0[0], w0[1]);
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn record_is_a_running_mean_or_the_reference_halving() {
        let mut a = table();
        assert_eq!(a.mean_reward(0, 3), None);
        for r in [0.2, 0.4, 0.9] {
            a.record(0, 3, r, Update::Mean);
        }
        assert!((a.mean_reward(0, 3).unwrap() - 0.5).abs() < 1e-12);
        assert_eq!(a.visits(0, 3), 3);
        for r in [0.4, 0.8] {
            a.record(0, 4, r, Update::Halving);
        }
        // (0 + 0.4)/2 = 0.2, (0.2 + 0.8)/2 = 0.5
        assert!((a.mean_reward(0, 4).unwrap() - 0.5).abs() < 1e-12);
        a.record(9, 0, 1.0, Update::Mean); // ignored
    }

    #[test]
    fn sampling_follows_the_weights_and_skips_disabled_clips() {
        let mut a = table();
        a.disable_clip(2);
        let w = a.weights(&AtsParams::default());
        assert_eq!(w.clip[2], 0.0);
        assert_eq!(w.class, [(7, 1.0)]);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut counts = vec![vec![0u32; 10]; 3];
        for _ in 0..20000 {
            let (c, f) = w.sample(&mut rng).unwrap();
            assert!(a.allowed(c)[f], "{c} {f}");
            counts[c][f] += 1;
        }
        assert_eq!(counts[2].iter().sum::<u32>(), 0);
        // clip 0: 7 frames x 1/2 x 1/7 ≈ 1429 each
        for f in 2..=8 {
            assert!((counts[0][f] as i64 - 1429).abs() < 200, "{:?}", counts[0]);
        }
        assert_eq!(pick(&[0.0, 0.0], &mut rng), None);
        assert_eq!(pick(&[0.0, 2.0, 0.0], &mut rng), Some(1));
        let mut none = table();
        (0..3).for_each(|c| none.disable_clip(c));
        assert_eq!(none.weights(&AtsParams::default()).sample(&mut rng), None);
    }
}
