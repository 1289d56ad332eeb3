use super::*;
use crate::motion::Skeleton;
use proptest::prelude::*;

const SK: Skeleton = Skeleton::MocapHumanoid;

/// A plausible BallPlay state from a seed: every field filled (also the
/// fixture of the STG's tests).
pub(crate) fn state(seed: u64) -> State {
    let mut x = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    let mut next = move || {
        x ^= x >> 33;
        x = x.wrapping_mul(0xff51afd7ed558ccd);
        x ^= x >> 33;
        ((x >> 11) as f64 / (1u64 << 53) as f64) as f32 - 0.5
    };
    let mut v = |n: usize, s: f32| (0..n).map(|_| s * next()).collect::<Vec<f32>>();
    let rq = quat::from_expmap([0.3, -0.2, 1.0]).map(|v| v as f32);
    State {
        root_pos: [1.0, -2.0, 0.9],
        root_rot: rq,
        root_rot_expmap: [0.3, -0.2, 1.0],
        root_linvel: [0.5, 0.1, 0.0],
        root_angvel: [0.0, 0.0, 0.3],
        joint_rot: v(156, 1.0),
        joint_vel: v(156, 2.0),
        body_pos: v(159, 2.0),
        body_vel: v(159, 1.0),
        obj_pos: vec![1.2, -1.8, 0.5],
        obj_rot: vec![0.0, 0.0, 0.0, 1.0],
        obj_linvel: vec![0.0, 0.0, -1.0],
        obj_angvel: vec![0.0; 3],
        contact: true,
    }
}

#[test]
fn a_state_is_fully_similar_to_itself_and_scores_full_reward() {
    let s = state(1);
    let w = Weights::sm(DatasetKind::BallPlay);
    assert!((similarity(&s, &s, SK, &w, Align::default()) - 1.0).abs() < 1e-9);
    let c = Contacts::of_reference(&s);
    let r = sm_reward(&s, &s, &c, SK, &w, &RewardOptions::default(), None);
    assert!((r.total - 1.0).abs() < 1e-12, "{r:?}");
    let dm = dm_reward(
        &s,
        &s,
        SK,
        &Weights::dm(DatasetKind::BallPlay),
        RootRot::Raw,
    );
    assert!((dm - 4.0).abs() < 1e-12);
    assert!(
        (dm_reward(
            &s,
            &s,
            SK,
            &Weights::dm(DatasetKind::Locomotion),
            RootRot::Raw
        ) - 3.0)
            .abs()
            < 1e-12
    );
}

#[test]
fn weights_follow_tables_8_and_9() {
    let b = Weights::sm(DatasetKind::BallPlay);
    assert_eq!(
        (b.p, b.r, b.pv, b.rv, b.op, b.rel, b.cg),
        (20.0, 20.0, 0.0, 0.0, 1.0, 20.0, [5.0; 3])
    );
    let l = Weights::sm(DatasetKind::Locomotion);
    assert_eq!((l.op, l.rel, l.cg), (0.0, 0.0, [0.0; 3]));
    let p = Weights::sm(DatasetKind::ParaHome);
    assert_eq!((p.op, p.rel, p.cg), (1.0, 20.0, [0.0; 3]));
    let d = Weights::dm(DatasetKind::BallPlay);
    assert_eq!((d.p, d.r, d.rv, d.op), (40.0, 2.0, 0.1, 40.0));
    assert_eq!(Weights::dm(DatasetKind::Locomotion).op, 0.0);
}

#[test]
fn terms_follow_the_exponential_of_the_weighted_mse() {
    let a = state(2);
    let mut b = a.clone();
    for k in 0..3 {
        b.root_pos[k] += 0.1; // the root point only: the bodies stay
    }
    let w = Weights::sm(DatasetKind::BallPlay);
    let e = errors(&b, &a, SK);
    // only the root point (3 of 54 numbers) moved by 0.1
    assert!((e.p - 0.03 / 54.0).abs() < 1e-9);
    let r = sm_reward(
        &b,
        &a,
        &Contacts::of_reference(&a),
        SK,
        &w,
        &RewardOptions::default(),
        None,
    );
    assert!((r.body - (-20.0 * e.p).exp()).abs() < 1e-12);
    assert!((r.rel - (-20.0 * e.rel).exp()).abs() < 1e-12);
    // a missed ball-hands contact costs exp(-5)
    let none = Contacts::default();
    let r2 = sm_reward(&a, &a, &none, SK, &w, &RewardOptions::default(), None);
    assert!((r2.cg - (-5.0f64).exp()).abs() < 1e-12);
}

#[test]
fn the_energy_term_scores_the_bounce_bought_not_the_phase() {
    // reference ball: 0.5 m high, falling at 1 m/s: E = 9.81 * 0.5 + 0.5
    let r = state(3);
    let e_ref = GRAVITY * 0.5 + 0.5;
    // the same flight a moment later: 0.2 m lower and as much faster as
    // free fall makes it, so its energy is the reference's
    let mut later = r.clone();
    later.obj_pos[2] = 0.3;
    let vz = -(1.0 + 2.0 * GRAVITY * 0.2).sqrt();
    later.obj_linvel[2] = vz as f32;
    let e = errors(&later, &r, SK);
    // the position term sees the phase, the energy term does not
    assert!(e.op > 0.01, "{e:?}");
    assert!(e.oe < 1e-6, "{e:?}");
    // a ball pushed too softly: the same place, 1 m/s slower down
    let mut soft = r.clone();
    soft.obj_linvel[2] = 0.0;
    let e = errors(&soft, &r, SK);
    assert!(
        (e.oe - (e_ref - GRAVITY * 0.5).powi(2)).abs() < 1e-9,
        "{e:?}"
    );
    // two objects: the mean of their squared gaps (the second one exact)
    let mut two_ref = r.clone();
    two_ref.obj_pos.extend([0.0, 0.0, 1.0]);
    two_ref.obj_linvel.extend([0.0, 2.0, 0.0]);
    let mut two = soft.clone();
    two.obj_pos.extend([5.0, 5.0, 1.0]);
    two.obj_linvel.extend([2.0, 0.0, 0.0]);
    let e2 = errors(&two, &two_ref, SK);
    assert!((e2.oe - e.oe / 2.0).abs() < 1e-9, "{e2:?}");
    // weight 0 (every preset) gives the same reward bit for bit; a weight
    // lowers the object factor by exp(-w * oe)
    let c = Contacts::of_reference(&r);
    let o = RewardOptions::default();
    let paper = Weights::sm(DatasetKind::BallPlay);
    assert_eq!(paper.oe, 0.0);
    let with = |w: f64| {
        let ws = WeightOverrides {
            oe: Some(w),
            ..Default::default()
        }
        .apply(paper);
        sm_reward(&soft, &r, &c, SK, &ws, &o, None)
    };
    let a = sm_reward(&soft, &r, &c, SK, &paper, &o, None);
    assert_eq!(with(0.0), a);
    let b = with(0.04);
    assert!((b.object / a.object - (-0.04 * e.oe).exp()).abs() < 1e-12);
    assert!(b.total < a.total);
    // a negative weight is refused with its key
    let bad = WeightOverrides {
        oe: Some(-1.0),
        ..Default::default()
    };
    let err = bad.check("train").unwrap_err().to_string();
    assert!(err.contains("train.reward_weights.oe"), "{err}");
}

#[test]
fn the_energy_bonus_pays_its_weight_for_the_reference_bounce_and_less_for_a_softer_one() {
    // reference ball: 0.5 m high, falling at 1 m/s (E = 9.81 * 0.5 + 0.5)
    let r = state(3);
    let w = 0.25;
    let k = ENERGY_BONUS_SCALE;
    // a ball on the reference's flight: the whole weight
    let mut later = r.clone();
    later.obj_pos[2] = 0.3;
    later.obj_linvel[2] = -(1.0 + 2.0 * GRAVITY * 0.2).sqrt() as f32;
    let full = energy_bonus(&errors(&later, &r, SK), w, k);
    assert!((full - w).abs() < 1e-6, "{full}");
    // a ball pushed too softly (at rest at the same height, 0.5 J/kg
    // short): w exp(-k 0.25), and less the softer it is
    let mut soft = r.clone();
    soft.obj_linvel[2] = 0.0;
    let e = errors(&soft, &r, SK);
    let b = energy_bonus(&e, w, k);
    assert!((b - w * (-k * 0.25).exp()).abs() < 1e-9, "{b}");
    let mut low = soft.clone();
    low.obj_pos[2] = 0.12;
    let lower = energy_bonus(&errors(&low, &r, SK), w, k);
    assert!(0.0 < lower && lower < b && b < full, "{lower} {b} {full}");
    // 5 J/kg short (the reference's velocity, 5 / g m lower): exp(-0.5)
    // of the weight at the default scale
    let mut low = r.clone();
    low.obj_pos[2] = (0.5 - 5.0 / GRAVITY) as f32;
    let five = energy_bonus(&errors(&low, &r, SK), w, k);
    assert!((five - w * (-0.5f64).exp()).abs() < 1e-6, "{five}");
    // weight 0: nothing
    assert_eq!(energy_bonus(&e, 0.0, k), 0.0);
}

#[test]
fn alignment_removes_horizontal_offsets_and_turns() {
    let a = state(3);
    // Move b by (3, -1) and turn it by 0.7 rad about a's root.
    let b = apply_alignment(
        &a,
        0.7,
        [a.root_pos[0] as f64, a.root_pos[1] as f64],
        [a.root_pos[0] as f64 + 3.0, a.root_pos[1] as f64 - 1.0],
    );
    let w = Weights::sm(DatasetKind::BallPlay);
    let s = similarity(&a, &b, SK, &w, Align::default());
    assert!(s > 1.0 - 1e-4, "aligned similarity {s}");
    let xy_only = similarity(
        &a,
        &b,
        SK,
        &w,
        Align {
            xy: true,
            yaw: false,
        },
    );
    assert!(
        xy_only < 0.5,
        "without yaw alignment the turn must cost: {xy_only}"
    );
    let none = similarity(
        &a,
        &b,
        SK,
        &w,
        Align {
            xy: false,
            yaw: false,
        },
    );
    assert!(none < xy_only);
    let back = align_to(&a, &b, Align::default());
    assert!((quat::heading(back.root_rot) - quat::heading(a.root_rot)).abs() < 1e-5);
    assert!(
        (back.obj_pos[2] - a.obj_pos[2]).abs() < 1e-6,
        "heights are kept"
    );
}

#[test]
fn the_reference_contact_rule_penalises_body_contacts() {
    let a = state(4);
    let w = Weights::sm(DatasetKind::BallPlay);
    let opts = RewardOptions {
        contacts: ContactRule::Reference,
        ..RewardOptions::default()
    };
    let touching = Contacts {
        ball_hands: true,
        penalty_bodies: true,
        ..Contacts::default()
    };
    let r = sm_reward(&a, &a, &touching, SK, &w, &opts, None);
    assert!((r.cg - (-5.0f64).exp()).abs() < 1e-12);
}

#[test]
fn the_root_rotation_is_compared_on_the_nearest_branch_unless_raw() {
    // A heading near 180 degrees stored on the other branch: the same rotation.
    let mut reference = state(6);
    let e = [0.0f64, 0.0, 3.1];
    reference.root_rot = quat::from_expmap(e).map(|v| v as f32);
    reference.root_rot_expmap = e.map(|v| v as f32);
    let mut sim = reference.clone();
    let other = 3.1 - 2.0 * std::f64::consts::PI;
    sim.root_rot_expmap = [0.0, 0.0, other as f32];
    let w = Weights::sm(DatasetKind::BallPlay);
    let c = Contacts::of_reference(&reference);
    let near = sm_reward(
        &sim,
        &reference,
        &c,
        SK,
        &w,
        &RewardOptions::default(),
        None,
    );
    assert!((near.body - 1.0).abs() < 1e-6, "{near:?}");
    let raw_opts = RewardOptions {
        root_rot: RootRot::Raw,
        ..RewardOptions::default()
    };
    let raw = sm_reward(&sim, &reference, &c, SK, &w, &raw_opts, None);
    // (2 pi)^2 / 159 components, times w_r = 20
    let want = (-20.0 * (2.0 * std::f64::consts::PI).powi(2) / 159.0).exp();
    assert!((raw.body - want).abs() < 1e-4, "{raw:?} vs {want}");
    let dm_near = dm_reward(
        &sim,
        &reference,
        SK,
        &Weights::dm(DatasetKind::BallPlay),
        RootRot::Nearest,
    );
    assert!((dm_near - 4.0).abs() < 1e-6);
}

#[test]
fn smoothness_is_off_by_default_and_penalises_jerk_on_still_joints() {
    let a = state(5);
    let mut b = a.clone();
    let w = Weights::sm(DatasetKind::BallPlay);
    let prev: Vec<f32> = a.joint_vel.iter().map(|v| v + 1.0).collect();
    let off = sm_reward(
        &b,
        &a,
        &Contacts::of_reference(&a),
        SK,
        &w,
        &RewardOptions::default(),
        Some(&prev),
    );
    assert!((off.total - 1.0).abs() < 1e-12);
    b.joint_vel = a.joint_vel.clone();
    let mut reference = a.clone();
    reference.joint_vel[0] = 0.0; // a joint the reference holds still
    b.joint_vel[0] = 0.0;
    let opts = RewardOptions {
        smoothness: true,
        ..RewardOptions::default()
    };
    let on = sm_reward(
        &b,
        &reference,
        &Contacts::of_reference(&a),
        SK,
        &w,
        &opts,
        Some(&prev),
    );
    // Only the still joint counts: its denominator is 1e12 * 1e-12 = 1.
    let d = (prev[0] as f64).powi(2);
    let want = (-0.1 * d / 156.0).exp();
    assert!(
        on.body < 1.0 && (on.body - want).abs() < 1e-6,
        "{on:?} vs {want}"
    );
}

proptest! {
    #[test]
    fn similarity_and_rewards_stay_in_range(s1 in 0u64..1000, s2 in 0u64..1000) {
        let (a, b) = (state(s1), state(s2));
        for kind in [DatasetKind::BallPlay, DatasetKind::Locomotion, DatasetKind::ParaHome] {
            let w = Weights::sm(kind);
            let s = similarity(&a, &b, SK, &w, Align::default());
            prop_assert!(s > 0.0 && s <= 1.0, "{s}");
            let r = sm_reward(&a, &b, &Contacts::default(), SK, &w, &RewardOptions::default(), None);
            prop_assert!(r.total >= 0.0 && r.total <= 1.0);
            let d = dm_reward(&a, &b, SK, &Weights::dm(kind), RootRot::Raw);
            prop_assert!((0.0..=4.0).contains(&d));
        }
    }
}
