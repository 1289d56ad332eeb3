//! The humanoid model against the real clips.

mod common;

use common::*;

#[test]
fn forward_kinematics_of_the_mjcf_reproduces_the_stored_body_positions() {
    // Exp-map FK of the MJCF: about 3.5 mm on ParaHome, 3-5 cm on BallPlay and
    // Locomotion (the capture skeleton's limb lengths differ from the model's).
    for (dataset, limit_cm) in [("parahome", 1.0), ("ballplay", 5.0), ("locomotion", 5.0)] {
        let out = ok(&["check-fk", "--dataset", dataset]);
        let rows: Vec<&str> = out
            .lines()
            .filter(|l| {
                l.starts_with(|c: char| c.is_ascii_digit()) && l.split_whitespace().count() == 4
            })
            .collect();
        assert!(!rows.is_empty(), "{out}");
        for r in rows {
            let mean: f64 = r.split_whitespace().nth(2).unwrap().parse().unwrap();
            assert!(mean <= limit_cm, "{dataset}: {r}");
            assert!(mean > 0.0, "{dataset}: zero error is suspicious: {r}");
        }
    }
}

#[test]
fn joint_noise_moves_the_child_bodies_through_forward_kinematics() {
    use skillaug::augment::stf::refresh_bodies;
    use skillaug::sim::mjcf::Model;
    let (_dir, out) = ingested("ballplay");
    let lib = skillaug::table::load_library(&out).unwrap();
    let model = Model::load(&data_root().join("assets/mjcf/mocap_humanoid.xml")).unwrap();
    assert_eq!(model.bodies.len(), 53);
    assert_eq!(model.bodies[2].hinges[0].stiffness, 500.0);
    assert!(model.bodies[3]
        .geoms
        .iter()
        .any(|g| g.kind == "box" && g.density.is_none()));
    let s = lib.state(0, 50).unwrap();
    let mut o = s.clone();
    refresh_bodies(&s, &mut o, &model);
    assert_eq!(o.body_pos, s.body_pos, "no noise, no change");
    o.joint_rot[0] += 0.3; // L_Hip x
    refresh_bodies(&s, &mut o, &model);
    let moved = |b: usize| {
        (0..3)
            .map(|k| (o.body_pos[3 * b + k] - s.body_pos[3 * b + k]).powi(2))
            .sum::<f32>()
            .sqrt()
    };
    assert!(moved(2) > 0.05, "L_Knee should move: {}", moved(2));
    assert!(moved(4) > 0.05, "L_Toe should move");
    assert!(
        moved(0) < 1e-6 && moved(6) < 1e-6 && moved(14) < 1e-6,
        "pelvis, R_Knee, head stay"
    );
}
