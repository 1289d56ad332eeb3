//! Quaternion and exponential-map maths used by the data stages.
//!
//! Quaternions are stored **(x, y, z, w)** everywhere in skillaug, the order of
//! the reference data and code (Ingrid789/SkillMimic-V2
//! `skillmimic/utils/torch_utils.py`). An exp-map (rotation vector) is axis x
//! angle in radians. The small-angle rules follow `exp_map_to_quat` and
//! `quat_to_exp_map` of that file: below 1e-5 rad an exp-map maps to the
//! identity, and a quaternion whose vector part has a sine below 1e-5 maps
//! to the zero exp-map.

/// A quaternion in (x, y, z, w) order.
pub type Quat = [f64; 4];
/// A 3-vector.
pub type Vec3 = [f64; 3];

/// The identity rotation.
pub const IDENTITY: Quat = [0.0, 0.0, 0.0, 1.0];

const SMALL: f64 = 1e-5;

/// Unit quaternion of the rotation vector `e` (`exp_map_to_quat` in
/// Ingrid789/SkillMimic-V2 `skillmimic/utils/torch_utils.py`).
pub fn from_expmap(e: Vec3) -> Quat {
    let angle = norm(e);
    if angle <= SMALL {
        return IDENTITY;
    }
    let s = (0.5 * angle).sin() / angle;
    [e[0] * s, e[1] * s, e[2] * s, (0.5 * angle).cos()]
}

/// Rotation vector of the unit quaternion `q`, with the angle wrapped to
/// [-pi, pi] (`quat_to_exp_map` in Ingrid789/SkillMimic-V2
/// `skillmimic/utils/torch_utils.py`), so `q` and `-q` give the same exp-map.
pub fn to_expmap(q: Quat) -> Vec3 {
    let w = q[3].clamp(-1.0, 1.0);
    let mut angle = 2.0 * w.acos();
    if angle > std::f64::consts::PI {
        angle -= 2.0 * std::f64::consts::PI;
    }
    let sin_half = (1.0 - w * w).max(0.0).sqrt();
    if sin_half <= SMALL {
        return [0.0; 3];
    }
    let k = angle / sin_half;
    [q[0] * k, q[1] * k, q[2] * k]
}

/// The rotation vector of `e`'s rotation nearest to `like`: the same axis
/// with the angle moved by a multiple of 2 pi (k in -2..=2), so
/// `e - 2 pi e/|e|` and `e` compare as equal rotations.
pub fn nearest_expmap(e: Vec3, like: [f32; 3]) -> Vec3 {
    let th = norm(e);
    if th < 1e-12 {
        return e;
    }
    let axis = e.map(|v| v / th);
    let tau = 2.0 * std::f64::consts::PI;
    let mut best = (f64::INFINITY, e);
    for k in -2..=2 {
        let a = th + tau * k as f64;
        let v = axis.map(|x| x * a);
        let d: f64 = (0..3).map(|i| (v[i] - like[i] as f64).powi(2)).sum();
        if d < best.0 {
            best = (d, v);
        }
    }
    best.1
}

/// Hamilton product `a * b` (apply `b`, then `a`).
pub fn mul(a: Quat, b: Quat) -> Quat {
    let [ax, ay, az, aw] = a;
    let [bx, by, bz, bw] = b;
    [
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ]
}

/// Conjugate (the inverse of a unit quaternion).
pub fn conj(q: Quat) -> Quat {
    [-q[0], -q[1], -q[2], q[3]]
}

/// Four-component dot product.
pub fn dot(a: Quat, b: Quat) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]
}

/// Negated quaternion (the same rotation).
pub fn neg(q: Quat) -> Quat {
    [-q[0], -q[1], -q[2], -q[3]]
}

/// Euclidean norm of a 3-vector.
pub fn norm(v: Vec3) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

/// Rotate the vector `v` by the unit quaternion `q`.
pub fn rotate(q: Quat, v: Vec3) -> Vec3 {
    let p = mul(mul(q, [v[0], v[1], v[2], 0.0]), conj(q));
    [p[0], p[1], p[2]]
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn close(a: &[f64], b: &[f64], tol: f64) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
    }

    #[test]
    fn quarter_turn_about_z_rotates_x_to_y() {
        let q = from_expmap([0.0, 0.0, std::f64::consts::FRAC_PI_2]);
        assert!(close(&rotate(q, [1.0, 0.0, 0.0]), &[0.0, 1.0, 0.0], 1e-12));
    }

    #[test]
    fn tiny_expmap_is_identity() {
        assert_eq!(from_expmap([1e-6, 0.0, 0.0]), IDENTITY);
        assert_eq!(to_expmap(IDENTITY), [0.0; 3]);
    }

    proptest! {
        #[test]
        fn expmap_round_trips_below_pi(x in -1.8f64..1.8, y in -1.8f64..1.8, z in -1.8f64..1.8) {
            let e = [x, y, z];
            prop_assume!(norm(e) < std::f64::consts::PI - 1e-6 && norm(e) > 1e-4);
            let q = from_expmap(e);
            prop_assert!((dot(q, q) - 1.0).abs() < 1e-12);
            prop_assert!(close(&to_expmap(q), &e, 1e-9));
            // -q is the same rotation and must give the same exp-map
            prop_assert!(close(&to_expmap(neg(q)), &e, 1e-9));
        }

        #[test]
        fn product_composes_rotations(a in prop::array::uniform3(-2.0f64..2.0), b in prop::array::uniform3(-2.0f64..2.0), v in prop::array::uniform3(-1.0f64..1.0)) {
            let (qa, qb) = (from_expmap(a), from_expmap(b));
            let lhs = rotate(mul(qa, qb), v);
            let rhs = rotate(qa, rotate(qb, v));
            prop_assert!(close(&lhs, &rhs, 1e-9));
        }
    }
}
