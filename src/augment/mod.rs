//! The paper's data augmentation (Sections 4.3-4.5, Appendix B.4): the
//! Stitched Trajectory Graph ([`stg`]), State Transition Field sampling
//! ([`stf`]) and Adaptive Trajectory Sampling ([`ats`]). Pure code over a
//! [`crate::motion::MotionLib`]; the stages write their results as tables.

pub mod ats;
pub mod seam;
pub mod settings;
pub mod stf;
pub mod stg;

use serde::{Deserialize, Serialize};

/// How the number of masked states follows from a similarity beta.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MaskRule {
    /// Paper Eq. 20 as printed: N = min(-ceil(log10 beta), N_max).
    #[default]
    Paper,
    /// Reference code (Ingrid789/SkillMimic-V2
    /// `skillmimic/env/tasks/skillmimic1_rand.py`): N = 0 if beta > 0.5, else
    /// min(-floor(log10 beta), N_max).
    Reference,
}

/// Number of masked states between a start whose similarity to its nearest
/// reference frame is `beta` and that frame (Eq. 20); `None` when
/// `beta <= tau` (no connection).
pub fn n_masked(beta: f64, tau: f64, n_max: u32, rule: MaskRule) -> Option<u32> {
    if beta.is_nan() || beta <= tau {
        return None;
    }
    let l = beta.min(1.0).log10();
    let n = match rule {
        MaskRule::Paper => -(l.ceil()),
        MaskRule::Reference if beta > 0.5 => 0.0,
        MaskRule::Reference => -(l.floor()),
    };
    Some((n.max(0.0) as u32).min(n_max))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eq20_on_a_table_of_betas() {
        let t = 1e-10;
        // beta, paper N, reference N
        let table: [(f64, Option<u32>, Option<u32>); 10] = [
            (1.0, Some(0), Some(0)),
            (0.7, Some(0), Some(0)),
            (0.5, Some(0), Some(1)),
            (0.1, Some(1), Some(1)),
            (0.05, Some(1), Some(2)),
            (1e-3, Some(3), Some(3)),
            (2e-4, Some(3), Some(4)),
            (1.1e-10, Some(9), Some(10)),
            (1e-10, None, None),
            (1e-12, None, None),
        ];
        for (beta, paper, reference) in table {
            assert_eq!(n_masked(beta, t, 10, MaskRule::Paper), paper, "beta {beta}");
            assert_eq!(
                n_masked(beta, t, 10, MaskRule::Reference),
                reference,
                "beta {beta}"
            );
        }
        assert_eq!(n_masked(1e-9, 1e-12, 5, MaskRule::Paper), Some(5));
        assert_eq!(n_masked(f64::NAN, t, 10, MaskRule::Paper), None);
    }
}
