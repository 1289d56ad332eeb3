//! Success rules per skill (the released metric files, Ingrid789/SkillMimic-V2
//! `skillmimic/metric/*_metric.py`; the paper gives only their names). Each
//! rule sees one [`Probe`] per policy step of a trial, with the step index n
//! from 0, and decides success at the
//! end.
//!
//! | skill | per-step condition | success |
//! |---|---|---|
//! | run, lrun, rrun (dribbles) | z_r > 0.5, ‖p_b − p_r‖ < 1.5, abs(v_b,z) > 1e-5 | true at least once for n < 100 and at every n ≥ 100 |
//! | layup, turnlayup | n < 300: z_r > 0.5, p_b,z > 1.8; n ≥ 300: z_r > 0.5, abs(v_b,z) > 1e-5 | first at least once, second at every step |
//! | shot* | n < 300: z_r > 0.5, abs(p_b,z − target) < 0.2; n ≥ 300: z_r > 0.5 | once, then always |
//! | pick* | z_r > 0.5, ‖p_b − p_r‖ < 0.5 | more than 60 steps |
//! | getup, getup_chair | z_r > 0.7, ‖v_r‖ < 1 | more than 60 steps |
//! | run_no_object | z_r > 0.7, ‖v_r‖ > 1 | fraction of steps > 0.8 |
//! | place_* | z_r > 0.5, wrist distance < thr (0.35 pan, else 0.2), p_o,z > 0.9 | more than 60 steps |
//! | drink_cup | z_r > 0.5, wrist distance < 0.2, p_o,z > 1.2 | more than 30 steps |
//! | pour_kettle | z_r > 0.5, wrist distance < 0.2, p_o,z > 1.0 | strictly between 30 and 100 steps |
//! | pour_kettlecup | both objects: wrist distance < 0.2, p_o,z > 0.9; z_r > 0.5 | strictly between 30 and 100 steps |
//!
//! The reference Jumpshot/Setshot rules (with a bug that counts standing
//! as success) have no clips here and are not offered.

use crate::rl::humanoid::Probe;
use serde::{Deserialize, Serialize};

/// A success rule.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Rule {
    /// Dribbles (run, lrun, rrun).
    Run,
    /// Layups.
    Layup,
    /// Shots, with the target ball height (the reference ball height at the
    /// highest frame of the skill's first clip).
    Shot {
        /// Target height, m.
        target_z: f32,
    },
    /// Ball pickup.
    Pickup,
    /// Getting up (also from a chair).
    Getup,
    /// Running without a ball.
    RunNoObject,
    /// Placing an object, with the wrist threshold.
    Place {
        /// Wrist distance threshold, m.
        thr: f32,
    },
    /// Drinking from a cup.
    Drink,
    /// Pouring from a kettle.
    Pour,
    /// Pouring from a kettle into a cup.
    MultiPour,
}

impl Rule {
    /// The rule of `skill` (`shot_target` is used by shots); `None` for a
    /// skill without one.
    pub fn of_skill(skill: &str, shot_target: f32) -> Option<Rule> {
        Some(match skill {
            "run" | "lrun" | "rrun" => Rule::Run,
            "layup" | "turnlayup" => Rule::Layup,
            s if s.starts_with("shot") => Rule::Shot {
                target_z: shot_target,
            },
            s if s.starts_with("pick") => Rule::Pickup,
            "getup" | "getup_chair" => Rule::Getup,
            "run_no_object" => Rule::RunNoObject,
            "place_pan" => Rule::Place { thr: 0.35 },
            "place_kettle" | "place_book" => Rule::Place { thr: 0.2 },
            "drink_cup" => Rule::Drink,
            "pour_kettle" => Rule::Pour,
            "pour_kettlecup" => Rule::MultiPour,
            _ => return None,
        })
    }

    /// The root height above which the rule counts the character as
    /// standing, m (0.7 for getting up and running without a ball, 0.5 for
    /// the rest, as the success rules of Ingrid789/SkillMimic-V2
    /// `skillmimic/metric/`).
    pub fn stand_height(self) -> f32 {
        match self {
            Rule::Getup | Rule::RunNoObject => 0.7,
            _ => 0.5,
        }
    }

    /// The shortest trial on which the rule can reach a verdict, policy
    /// steps: one step past the phase boundary for the phase rules (a
    /// dribble's late condition starts at step 100, a layup's and a shot's
    /// at 300), one more than the counted steps for the counting rules. A
    /// shorter trial is never a success ([`Judge::success`]).
    pub fn min_steps(self) -> usize {
        if let Some(late) = self.late_from() {
            return late + 1;
        }
        match self {
            Rule::Pickup | Rule::Getup | Rule::Place { .. } => 61,
            Rule::Drink | Rule::Pour | Rule::MultiPour => 31,
            _ => 1,
        }
    }

    /// The step from which a phase rule checks its late condition (`None`
    /// for the other rules).
    fn late_from(self) -> Option<usize> {
        match self {
            Rule::Run => Some(100),
            Rule::Layup | Rule::Shot { .. } => Some(300),
            _ => None,
        }
    }

    /// The trial length the reference evaluates this rule over, policy
    /// steps (600 = 10 s; ParaHome rules are bounded by their buffers).
    pub fn trial_steps(self) -> usize {
        match self {
            Rule::Place { .. } | Rule::Drink => 200,
            Rule::Pour | Rule::MultiPour => 400,
            _ => 600,
        }
    }
}

fn dist(a: [f32; 3], b: [f32; 3]) -> f32 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn norm(v: [f32; 3]) -> f32 {
    dist(v, [0.0; 3])
}

fn wrist_dist(p: &Probe, o: [f32; 3]) -> f32 {
    p.wrists
        .iter()
        .map(|w| dist(*w, o))
        .fold(f32::INFINITY, f32::min)
}

/// One trial being judged.
#[derive(Clone, Debug, PartialEq)]
pub struct Judge {
    rule: Rule,
    n: usize,
    count: usize,
    early: bool,
    late_ok: bool,
    down: Option<usize>,
}

impl Judge {
    /// A fresh trial.
    pub fn new(rule: Rule) -> Judge {
        Judge {
            rule,
            n: 0,
            count: 0,
            early: false,
            late_ok: true,
            down: None,
        }
    }

    /// The first step (1 = after the first policy step) whose root was at
    /// or below the rule's [`Rule::stand_height`]; `None` while it stood.
    pub fn down_step(&self) -> Option<usize> {
        self.down
    }

    /// Steps seen.
    pub fn steps(&self) -> usize {
        self.n
    }

    /// Feed step n (= the number of steps fed so far).
    pub fn update(&mut self, p: &Probe) {
        let z = p.root[2];
        if self.down.is_none()
            && z.partial_cmp(&self.rule.stand_height()) != Some(std::cmp::Ordering::Greater)
        {
            self.down = Some(self.n + 1);
        }
        let ball = p.obj.first().copied().unwrap_or([f32::NAN; 3]);
        let ball_v = p.obj_vel.first().copied().unwrap_or([0.0; 3]);
        let n = self.n;
        let early_phase = self.rule.late_from().is_some_and(|late| n < late);
        match self.rule {
            Rule::Run => {
                let c = z > 0.5 && dist(ball, p.root) < 1.5 && ball_v[2].abs() > 1e-5;
                self.phases(early_phase, c, c);
            }
            Rule::Layup => {
                let early = z > 0.5 && ball[2] > 1.8;
                let late = z > 0.5 && ball_v[2].abs() > 1e-5;
                self.phases(early_phase, early, late);
            }
            Rule::Shot { target_z } => {
                let early = z > 0.5 && (ball[2] - target_z).abs() < 0.2;
                self.phases(early_phase, early, z > 0.5);
            }
            Rule::Pickup => self.count_if(z > 0.5 && dist(ball, p.root) < 0.5),
            Rule::Getup => self.count_if(z > 0.7 && norm(p.root_vel) < 1.0),
            Rule::RunNoObject => self.count_if(z > 0.7 && norm(p.root_vel) > 1.0),
            Rule::Place { thr } => {
                self.count_if(z > 0.5 && wrist_dist(p, ball) < thr && ball[2] > 0.9)
            }
            Rule::Drink => self.count_if(z > 0.5 && wrist_dist(p, ball) < 0.2 && ball[2] > 1.2),
            Rule::Pour => self.count_if(z > 0.5 && wrist_dist(p, ball) < 0.2 && ball[2] > 1.0),
            Rule::MultiPour => {
                let both =
                    p.obj.len() >= 2 && p.obj.iter().all(|o| wrist_dist(p, *o) < 0.2 && o[2] > 0.9);
                self.count_if(z > 0.5 && both)
            }
        }
        self.n += 1;
    }

    fn phases(&mut self, early_phase: bool, early: bool, late: bool) {
        if early_phase {
            self.early |= early;
        } else {
            self.late_ok &= late;
        }
    }

    fn count_if(&mut self, c: bool) {
        self.count += c as usize;
    }

    /// The verdict after the last step: never a success for a trial
    /// shorter than [`Rule::min_steps`] (its late phase unseen).
    pub fn success(&self) -> bool {
        if self.n < self.rule.min_steps() {
            return false;
        }
        match self.rule {
            Rule::Run | Rule::Layup | Rule::Shot { .. } => self.early && self.late_ok,
            Rule::Pickup | Rule::Getup | Rule::Place { .. } => self.count > 60,
            Rule::Drink => self.count > 30,
            Rule::Pour | Rule::MultiPour => self.count > 30 && self.count < 100,
            Rule::RunNoObject => self.n > 0 && self.count as f64 / self.n as f64 > 0.8,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn probe(root_z: f32, root_vel: f32, ball: [f32; 3], ball_vz: f32) -> Probe {
        Probe {
            root: [0.0, 0.0, root_z],
            root_vel: [root_vel, 0.0, 0.0],
            obj: vec![ball],
            obj_vel: vec![[0.0, 0.0, ball_vz]],
            wrists: vec![[0.0, 0.3, 1.0], [0.0, -0.3, 1.0]],
        }
    }

    fn judge(rule: Rule, steps: impl Iterator<Item = Probe>) -> bool {
        let mut j = Judge::new(rule);
        for p in steps {
            j.update(&p);
        }
        j.success()
    }

    #[test]
    fn a_trial_shorter_than_its_rule_is_never_a_success() {
        // a humanoid lying on the floor, the ball away and still: every
        // phase rule's late condition fails from its first late step, so
        // only a trial too short to reach it could pass
        let lying = |_n: usize| probe(0.1, 0.0, [3.0, 0.0, 0.1], 0.0);
        let standing = |_n: usize| probe(0.9, 0.0, [0.5, 0.0, 1.0], 0.0);
        for (rule, early) in [
            (Rule::Run, probe(0.9, 0.0, [0.5, 0.0, 1.0], 1.0)),
            (Rule::Layup, probe(0.9, 0.0, [0.5, 0.0, 2.0], 0.0)),
            (Rule::Shot { target_z: 1.0 }, standing(0)),
        ] {
            for steps in [1, 50, 100, rule.min_steps() - 1] {
                let seq = (0..steps).map(|n| if n == 0 { early.clone() } else { lying(n) });
                assert!(!judge(rule, seq), "{rule:?} over {steps} steps");
            }
        }
        // counting rules: a trial of fewer steps than counted cannot pass
        let held = |_n: usize| probe(0.9, 0.0, [0.2, 0.0, 1.0], 0.0);
        assert!(!judge(Rule::Pickup, (0..60).map(held)));
        assert!(judge(Rule::Pickup, (0..61).map(held)));
    }

    #[test]
    fn a_dribble_succeeds_only_if_the_ball_stays_close_and_bouncing_throughout() {
        let good = |_n: usize| probe(0.9, 2.0, [0.5, 0.0, 0.4], 1.0);
        assert!(judge(Rule::Run, (0..600).map(good)));
        // ball lost at step 400
        let lost = |n: usize| {
            if n < 400 {
                good(n)
            } else {
                probe(0.9, 2.0, [3.0, 0.0, 0.12], 0.0)
            }
        };
        assert!(!judge(Rule::Run, (0..600).map(lost)));
        // a fall after 100 steps
        let fell = |n: usize| {
            if n == 350 {
                probe(0.2, 0.0, [0.5, 0.0, 0.4], 1.0)
            } else {
                good(n)
            }
        };
        assert!(!judge(Rule::Run, (0..600).map(fell)));
        // resting ball never moves
        assert!(!judge(
            Rule::Run,
            (0..600).map(|_| probe(0.9, 2.0, [0.5, 0.0, 0.12], 0.0))
        ));
    }

    #[test]
    fn a_layup_needs_the_ball_high_early_and_dribbling_after() {
        let seq = |high: bool, late_bounce: bool| {
            (0..600).map(move |n| {
                if n == 150 && high {
                    probe(0.9, 0.0, [0.0, 0.0, 2.5], 0.5)
                } else if n >= 300 && !late_bounce {
                    probe(0.9, 0.0, [0.0, 0.0, 0.12], 0.0)
                } else {
                    probe(0.9, 0.0, [0.3, 0.0, 0.5], -1.0)
                }
            })
        };
        assert!(judge(Rule::Layup, seq(true, true)));
        assert!(!judge(Rule::Layup, seq(false, true)));
        assert!(!judge(Rule::Layup, seq(true, false)));
    }

    #[test]
    fn a_shot_must_reach_the_target_height_and_the_shooter_stay_up() {
        let r = Rule::Shot { target_z: 3.0 };
        let seq = |peak: f32, fall: bool| {
            (0..600).map(move |n| {
                let z = if fall && n > 400 { 0.3 } else { 0.9 };
                let bz = if n == 100 { peak } else { 1.0 };
                probe(z, 0.0, [0.0, 0.0, bz], 0.0)
            })
        };
        assert!(judge(r, seq(3.1, false)));
        assert!(!judge(r, seq(2.5, false)));
        assert!(!judge(r, seq(3.1, true)));
    }

    #[test]
    fn counting_rules_use_their_thresholds() {
        let hold = |k: usize| {
            (0..200).map(move |n| {
                let near = n < k;
                probe(
                    0.9,
                    0.0,
                    if near {
                        [0.2, 0.0, 0.9]
                    } else {
                        [3.0, 0.0, 0.1]
                    },
                    0.0,
                )
            })
        };
        assert!(judge(Rule::Pickup, hold(61)));
        assert!(!judge(Rule::Pickup, hold(60)));
        let up = |k: usize, v: f32| {
            (0..300).map(move |n| probe(if n < k { 0.9 } else { 0.3 }, v, [0.0; 3], 0.0))
        };
        assert!(judge(Rule::Getup, up(61, 0.5)));
        assert!(!judge(Rule::Getup, up(61, 1.5)));
        assert!(!judge(Rule::Getup, up(60, 0.5)));
        assert!(judge(Rule::RunNoObject, up(250, 2.0)));
        assert!(!judge(Rule::RunNoObject, up(200, 2.0)));
    }

    #[test]
    fn parahome_rules_measure_the_object_against_the_nearest_wrist() {
        let lifted = |k: usize, z: f32, d: f32| {
            (0..400).map(move |n| {
                let o = if n < k {
                    [0.0, 0.3 + d, z]
                } else {
                    [1.0, 1.0, 0.5]
                };
                let mut p = probe(0.9, 0.0, o, 0.0);
                p.wrists[0][2] = z; // the hand holds the object up
                p
            })
        };
        assert!(judge(Rule::Place { thr: 0.2 }, lifted(61, 1.0, 0.1)));
        assert!(!judge(Rule::Place { thr: 0.2 }, lifted(61, 1.0, 0.25)));
        assert!(judge(Rule::Place { thr: 0.35 }, lifted(61, 1.0, 0.25)));
        assert!(!judge(Rule::Place { thr: 0.2 }, lifted(61, 0.8, 0.1)));
        assert!(judge(Rule::Drink, lifted(31, 1.3, 0.1)));
        assert!(!judge(Rule::Drink, lifted(31, 1.1, 0.1)));
        assert!(judge(Rule::Pour, lifted(50, 1.1, 0.1)));
        assert!(!judge(Rule::Pour, lifted(120, 1.1, 0.1)));
        assert!(!judge(Rule::Pour, lifted(30, 1.1, 0.1)));
        // two objects, both held
        let both = |k: usize| {
            (0..400).map(move |n| {
                let mut p = probe(0.9, 0.0, [0.0, 0.3, 1.0], 0.0);
                p.obj.push(if n < k {
                    [0.0, -0.3, 1.0]
                } else {
                    [2.0, 0.0, 0.1]
                });
                p.obj_vel.push([0.0; 3]);
                p
            })
        };
        assert!(judge(Rule::MultiPour, both(50)));
        assert!(!judge(Rule::MultiPour, both(20)));
    }

    #[test]
    fn skills_map_to_rules() {
        assert_eq!(Rule::of_skill("lrun", 0.0), Some(Rule::Run));
        assert_eq!(Rule::of_skill("pick_40", 0.0), Some(Rule::Pickup));
        assert_eq!(
            Rule::of_skill("shot_style1", 2.0),
            Some(Rule::Shot { target_z: 2.0 })
        );
        assert_eq!(
            Rule::of_skill("place_pan", 0.0),
            Some(Rule::Place { thr: 0.35 })
        );
        assert_eq!(Rule::of_skill("turnhook", 0.0), None);
        assert_eq!(Rule::Drink.trial_steps(), 200);
    }
}
