//! Rotation helpers for the simulator, in `f32` on glam types (the types of
//! rapier3d 0.36): exp-maps, their Jacobians, and the conversion from an
//! exp-map drive target to the per-axis angles that a spherical joint's
//! motors measure.
//!
//! Joint coordinates are exp-maps (docs/simulation.md; Ingrid789/SkillMimic-V2
//! `skillmimic/env/tasks/skillmimic1.py`, `_reset_humanoid`): a joint's local
//! rotation is `exp(e)`. Their time derivatives `de/dt` (the data's DoF
//! velocities, backward differences of the triples) relate to the relative
//! angular velocity `w` expressed in the parent frame by the left Jacobian of
//! SO(3): `w = J_l(e) de/dt`, `de/dt = J_l(e)^-1 w`.

use crate::motion::quat;
use rapier3d::math::{Rotation, Vector};

/// Unit quaternion of a rotation vector (identity at or below 1e-5 rad):
/// [`crate::motion::quat::expmap_to_quat`] in f32.
pub fn from_expmap(e: Vector) -> Rotation {
    let [x, y, z, w] = quat::expmap_to_quat([e.x, e.y, e.z]);
    Rotation::from_xyzw(x, y, z, w)
}

/// Rotation vector of a unit quaternion, angle in [0, pi] (`q` and `-q`
/// give the same result): [`crate::motion::quat::quat_to_expmap`] in f32.
pub fn to_expmap(q: Rotation) -> Vector {
    let [x, y, z] = quat::quat_to_expmap([q.x, q.y, q.z, q.w]);
    Vector::new(x, y, z)
}

fn skew_mul(e: Vector, v: Vector) -> Vector {
    e.cross(v)
}

/// `J_l(e) v`: the parent-frame angular velocity of a joint whose exp-map
/// changes at rate `v`.
pub fn jl_mul(e: Vector, v: Vector) -> Vector {
    let t2 = e.length_squared();
    let (a, b) = if t2 < 1e-6 {
        (0.5 - t2 / 24.0, 1.0 / 6.0 - t2 / 120.0)
    } else {
        let t = t2.sqrt();
        ((1.0 - t.cos()) / t2, (t - t.sin()) / (t2 * t))
    };
    let kv = skew_mul(e, v);
    v + a * kv + b * skew_mul(e, kv)
}

/// `J_l(e)^-1 w`: the exp-map rate of a joint turning at parent-frame
/// angular velocity `w`. Near an angle of pi the inverse is singular; the
/// coefficient is bounded there.
pub fn jl_inv_mul(e: Vector, w: Vector) -> Vector {
    let t2 = e.length_squared();
    let c = if t2 < 1e-6 {
        1.0 / 12.0 + t2 / 720.0
    } else {
        let t = t2.sqrt();
        let s = t.sin().max(1e-3);
        1.0 / t2 - (1.0 + t.cos()) / (2.0 * t * s)
    };
    let kw = skew_mul(e, w);
    w - 0.5 * kw + c * skew_mul(e, kw)
}

/// The three motor angles of a spherical joint whose target is the local
/// rotation `exp(e)`: rapier measures axis `i` as `2 asin(q.imag[i])` of the
/// relative rotation taken with `w >= 0`.
pub fn motor_angles(e: Vector) -> [f32; 3] {
    let q = from_expmap(e);
    let q = if q.w < 0.0 { -q } else { q };
    [q.x, q.y, q.z].map(|c| 2.0 * c.clamp(-1.0, 1.0).asin())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn vec3() -> impl Strategy<Value = Vector> {
        prop::array::uniform3(-1.7f32..1.7).prop_map(|a| Vector::new(a[0], a[1], a[2]))
    }

    proptest! {
        #[test]
        fn expmap_round_trips(e in vec3()) {
            prop_assume!(e.length() < 3.0);
            let back = to_expmap(from_expmap(e));
            prop_assert!((back - e).length() < 1e-4, "{e:?} -> {back:?}");
        }

        #[test]
        fn jacobian_and_inverse_cancel(e in vec3(), v in vec3()) {
            prop_assume!(e.length() < 2.8);
            let back = jl_inv_mul(e, jl_mul(e, v));
            prop_assert!((back - v).length() < 1e-3 * (1.0 + v.length()), "{v:?} -> {back:?}");
        }

        #[test]
        fn jacobian_matches_finite_differences(e in vec3(), v in vec3()) {
            // w = J_l(e) de/dt is the angular velocity of exp(e(t)) in the
            // parent frame: exp(e + h v) ~ exp(h w) exp(e).
            prop_assume!(e.length() < 2.8 && e.length() > 0.05);
            let h = 1e-3;
            let q0 = from_expmap(e);
            let q1 = from_expmap(e + h * v);
            let w_fd = to_expmap(q1 * q0.inverse()) / h;
            let w = jl_mul(e, v);
            prop_assert!((w - w_fd).length() < 2e-2 * (1.0 + v.length()), "{w:?} vs {w_fd:?}");
        }
    }

    #[test]
    fn motor_angles_of_single_axis_rotation_are_the_angle() {
        let a = motor_angles(Vector::new(0.0, 0.7, 0.0));
        assert!((a[1] - 0.7).abs() < 1e-5 && a[0].abs() < 1e-6 && a[2].abs() < 1e-6);
    }
}
