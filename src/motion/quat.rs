//! Quaternion and exponential-map maths used by the data stages, and the one
//! exp-map of skillaug (the simulator's `sim::rot` calls the same generic
//! functions in `f32`).
//!
//! Quaternions are stored **(x, y, z, w)** everywhere in skillaug, the order of
//! the reference data and code (Ingrid789/SkillMimic-V2
//! `skillmimic/utils/torch_utils.py`). An exp-map (rotation vector) is axis x
//! angle in radians. Below 1e-5 rad an exp-map maps to the identity, as
//! `exp_map_to_quat` of that file does. The inverse takes the angle as
//! `2 atan2(|v|, w)` of the quaternion with `w >= 0` (angle in [0, pi]) and
//! maps a vector part below 1e-5 to `2 v` (its small-angle limit), where the
//! reference's `quat_to_exp_map` uses `2 acos(w)` and returns zero: `acos`
//! near 1 loses half the digits: in `f32` a 2.3 % error at 1e-3 rad and
//! zero for every angle below 2.4e-4 rad (docs/method.md, departures).

use num_traits::Float;

/// A quaternion in (x, y, z, w) order.
pub type Quat = [f64; 4];
/// A 3-vector.
pub type Vec3 = [f64; 3];

/// The identity rotation.
pub const IDENTITY: Quat = [0.0, 0.0, 0.0, 1.0];

/// Unit quaternion of the rotation vector `e` (identity at or below
/// 1e-5 rad), in `f32` or `f64`: `exp_map_to_quat` in
/// Ingrid789/SkillMimic-V2 `skillmimic/utils/torch_utils.py`.
pub fn expmap_to_quat<T: Float>(e: [T; 3]) -> [T; 4] {
    let angle = (e[0] * e[0] + e[1] * e[1] + e[2] * e[2]).sqrt();
    if angle <= small() {
        return [T::zero(), T::zero(), T::zero(), T::one()];
    }
    let half = half::<T>() * angle;
    let s = half.sin() / angle;
    [e[0] * s, e[1] * s, e[2] * s, half.cos()]
}

/// Rotation vector of the unit quaternion `q`, angle in [0, pi] (`q` and
/// `-q` give the same result), in `f32` or `f64`; a vector part at or below
/// 1e-5 maps to `2 v`.
pub fn quat_to_expmap<T: Float>(q: [T; 4]) -> [T; 3] {
    let [x, y, z, w] = if q[3] < T::zero() { q.map(|c| -c) } else { q };
    let s = (x * x + y * y + z * z).sqrt();
    let two = T::one() + T::one();
    if s <= small() {
        return [two * x, two * y, two * z];
    }
    let k = two * s.atan2(w) / s;
    [x * k, y * k, z * k]
}

fn small<T: Float>() -> T {
    T::from(1e-5).expect("1e-5 is a float")
}

fn half<T: Float>() -> T {
    T::from(0.5).expect("0.5 is a float")
}

/// Unit quaternion of the rotation vector `e` ([`expmap_to_quat`] in f64).
pub fn from_expmap(e: Vec3) -> Quat {
    expmap_to_quat(e)
}

/// Rotation vector of the unit quaternion `q` ([`quat_to_expmap`] in f64),
/// so `q` and `-q` give the same exp-map.
pub fn to_expmap(q: Quat) -> Vec3 {
    quat_to_expmap(q)
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

/// `q` divided by its norm (no guard: a zero `q` gives NaNs).
pub fn normalize(q: Quat) -> Quat {
    let n = dot(q, q).sqrt();
    q.map(|v| v / n)
}

/// `q` or `-q` (the same rotation), whichever is nearer `like`: `-q` when
/// the four-component dot product of `like` and `q` is negative, in `f32`
/// or `f64` (the sign smoothing of clips, object rewards and animation keys).
pub fn sign_like<T: Float>(q: [T; 4], like: [T; 4]) -> [T; 4] {
    let d = like[0] * q[0] + like[1] * q[1] + like[2] * q[2] + like[3] * q[3];
    if d < T::zero() {
        q.map(|c| -c)
    } else {
        q
    }
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

/// Heading of a root quaternion: atan2 of the rotated x-axis (`calc_heading`
/// in Ingrid789/SkillMimic-V2 `skillmimic/utils/torch_utils.py`).
pub fn heading(q: [f32; 4]) -> f64 {
    let q = q.map(|v| v as f64);
    let x = rotate(q, [1.0, 0.0, 0.0]);
    x[1].atan2(x[0])
}

/// `a` wrapped to [-pi, pi), rad.
pub fn wrap_angle(a: f64) -> f64 {
    let tau = 2.0 * std::f64::consts::PI;
    let mut a = (a + std::f64::consts::PI) % tau;
    if a < 0.0 {
        a += tau;
    }
    a - std::f64::consts::PI
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
    fn one_exp_map_serves_both_precisions() {
        for e in [
            [0.3, -0.2, 1.0],
            [0.0, 3.0, 0.1],
            [2e-4, -1e-4, 0.0],
            [-2.0, 1.5, 0.5],
        ] {
            let back64 = to_expmap(from_expmap(e));
            let back32 = quat_to_expmap(expmap_to_quat(e.map(|v| v as f32)));
            let tol = 1e-12 * (1.0 + norm(e));
            assert!(close(&back64, &e, tol), "{e:?} -> {back64:?}");
            assert!(
                close(&back32.map(f64::from), &e, 2e-6 * (1.0 + norm(e))),
                "{back32:?}"
            );
        }
        // below a 1e-5 sine the vector part maps to 2v (its limit), not zero
        assert_eq!(to_expmap([4e-6, 0.0, 0.0, 1.0]), [8e-6, 0.0, 0.0]);
        // in f32 a 1e-4 rad turn survives (2 acos(w) of its f32 w is 0)
        let e = quat_to_expmap(expmap_to_quat([1e-4f32, 0.0, 0.0]));
        assert!((e[0] - 1e-4).abs() < 1e-9, "{e:?}");
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

    #[test]
    fn sign_like_flips_only_against_a_negative_dot_product() {
        let q = [0.1f64, -0.2, 0.3, 0.9];
        assert_eq!(sign_like(q, [0.0, 0.0, 0.0, 1.0]), q);
        assert_eq!(sign_like(q, [0.0, 0.0, 0.0, -1.0]), neg(q));
        let q32 = q.map(|v| v as f32);
        assert_eq!(sign_like(q32, [0.0, 0.0, 0.0, -1.0]), q32.map(|v| -v));
        // a zero dot product keeps q
        assert_eq!(sign_like(q, [0.0, 0.0, 0.0, 0.0]), q);
    }

    #[test]
    fn wrap_angle_is_the_euclidean_remainder_bit_for_bit() {
        // the STG's own copy was written with rem_euclid
        let tau = 2.0 * std::f64::consts::PI;
        for k in -2000..=2000 {
            let a = k as f64 * 0.01234567 + 1e-3 * (k as f64).sin();
            let want = (a + std::f64::consts::PI).rem_euclid(tau) - std::f64::consts::PI;
            assert_eq!(wrap_angle(a).to_bits(), want.to_bits(), "{a}");
        }
    }

    #[test]
    fn normalize_gives_a_unit_quaternion() {
        let q = normalize([1.0, 2.0, -2.0, 4.0]);
        assert!((dot(q, q) - 1.0).abs() < 1e-15);
        assert!(close(&q, &[0.2, 0.4, -0.4, 0.8], 1e-15));
    }
}
