//! Column layouts of the clip tensors and the two humanoid skeletons.
//!
//! A clip is a `[frames, D]` float32 tensor. Three layouts exist (the loaders
//! of Ingrid789/SkillMimic-V2: `skillmimic/utils/motion_data_handler.py`,
//! `_process_sequence`, for D = 337; `paramotion_data_handler.py` and
//! `paramotion_data_handler_multiobj.py` for ParaHome, whose clips are written
//! by `skillmimic/data/motions/ParaHome/pt_data_from_parahome.py`):
//!
//! | D | datasets | columns |
//! |---|---|---|
//! | 337 | BallPlay, BallPlay-M, Locomotion | root pos 0:3, root exp-map 3:6, a copy of it 6:9, 52x3 joint exp-maps 9:165, 53x3 body positions 165:324, ball pos 324:327, ball rotation (stored negated) 327:330, ball velocities 330:336 (always zero, unused), contact 336 |
//! | 409 | ParaHome, one object | root pos 0:3, root rotation vector 3:6, zeros 6:9, 60x3 joint exp-maps 9:189, 71x3 position slots 189:402 (slots 61..70 unused), object pos 402:405, object rotation vector 405:408, contact 408 |
//! | 415 | ParaHome, two objects | as 409, then object 1 pos 408:411 and rotation 411:414, contact 414 |
//!
//! Body order is MJCF depth-first order (Ingrid789/SkillMimic-V2
//! `skillmimic/data/assets/mjcf/mocap_humanoid.xml`,
//! `mocap_parahome_boxhand.xml`); joint `j` (0-based) drives body `j + 1`.

use std::fmt;

/// The humanoid a clip is captured for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Skeleton {
    /// `mocap_humanoid.xml`: 53 bodies, 52 three-DoF joints (BallPlay, Locomotion).
    MocapHumanoid,
    /// `mocap_parahome_boxhand.xml`: 61 bodies, 60 three-DoF joints (ParaHome).
    ParaHome,
}

impl Skeleton {
    /// The name used in manifests, table metadata and MJCF file names.
    pub fn name(self) -> &'static str {
        match self {
            Skeleton::MocapHumanoid => "mocap_humanoid",
            Skeleton::ParaHome => "mocap_parahome_boxhand",
        }
    }

    /// Parse a manifest's `skeleton` value.
    pub fn from_name(name: &str) -> Option<Skeleton> {
        match name {
            "mocap_humanoid" => Some(Skeleton::MocapHumanoid),
            "mocap_parahome_boxhand" => Some(Skeleton::ParaHome),
            _ => None,
        }
    }

    /// Body names in body order (body 0 is the root).
    pub fn body_names(self) -> &'static [&'static str] {
        match self {
            Skeleton::MocapHumanoid => &BALLPLAY_BODIES,
            Skeleton::ParaHome => &PARAHOME_BODIES,
        }
    }

    /// Number of rigid bodies.
    pub fn n_bodies(self) -> usize {
        self.body_names().len()
    }

    /// Number of three-DoF joints (every body but the root).
    pub fn n_joints(self) -> usize {
        self.n_bodies() - 1
    }

    /// The 17 key bodies of the reward and the similarity (body indices, in
    /// key-body slot order: head, knees, elbows, ankles, then the left and
    /// right fingertips; the `keyBodies` lists of Ingrid789/SkillMimic-V2
    /// `skillmimic/data/cfg/skillmimic.yaml` and `skillmimic_parahome.yaml`).
    pub fn key_bodies(self) -> &'static [usize; 17] {
        match self {
            Skeleton::MocapHumanoid => &[
                14, 2, 6, 17, 36, 3, 7, 21, 24, 27, 30, 33, 40, 43, 46, 49, 52,
            ],
            Skeleton::ParaHome => &[
                6, 58, 54, 32, 9, 59, 55, 36, 40, 44, 48, 52, 13, 17, 21, 25, 29,
            ],
        }
    }

    /// The bodies of the SM reward's body-contact penalty (hard-coded in
    /// Ingrid789/SkillMimic-V2 `skillmimic/env/tasks/skillmimic1.py`).
    pub fn contact_penalty_bodies(self) -> &'static [usize] {
        match self {
            Skeleton::MocapHumanoid => {
                &[0, 1, 2, 5, 6, 9, 10, 11, 12, 13, 14, 15, 16, 17, 34, 35, 36]
            }
            Skeleton::ParaHome => &[],
        }
    }
}

impl fmt::Display for Skeleton {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A clip tensor layout, identified by its column count.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Layout {
    /// D = 337: BallPlay, BallPlay-M and Locomotion.
    BallPlay337,
    /// D = 409: ParaHome with one object.
    ParaHome409,
    /// D = 415: ParaHome with two objects.
    ParaHome415,
}

/// Where one object's columns lie in a row.
#[derive(Clone, Copy, Debug)]
pub struct ObjectColumns {
    /// First column of the world position (3 values).
    pub pos: usize,
    /// First column of the rotation vector (3 values).
    pub rot: usize,
}

impl Layout {
    /// Every layout, for messages.
    pub const ALL: [Layout; 3] = [
        Layout::BallPlay337,
        Layout::ParaHome409,
        Layout::ParaHome415,
    ];

    /// The layout with `d` columns, if any.
    pub fn from_columns(d: usize) -> Option<Layout> {
        Layout::ALL.into_iter().find(|l| l.columns() == d)
    }

    /// Columns per frame (D).
    pub fn columns(self) -> usize {
        match self {
            Layout::BallPlay337 => 337,
            Layout::ParaHome409 => 409,
            Layout::ParaHome415 => 415,
        }
    }

    /// Short name used in tables ("D337", ...).
    pub fn name(self) -> &'static str {
        match self {
            Layout::BallPlay337 => "D337",
            Layout::ParaHome409 => "D409",
            Layout::ParaHome415 => "D415",
        }
    }

    /// The skeleton the clip is captured for.
    pub fn skeleton(self) -> Skeleton {
        match self {
            Layout::BallPlay337 => Skeleton::MocapHumanoid,
            _ => Skeleton::ParaHome,
        }
    }

    /// Frame rate of the published clips, Hz (the `dataFPS` of
    /// Ingrid789/SkillMimic-V2 `skillmimic/data/cfg/skillmimic.yaml` and
    /// `skillmimic_parahome.yaml`).
    pub fn default_fps(self) -> f64 {
        match self {
            Layout::BallPlay337 => 60.0,
            _ => 30.0,
        }
    }

    /// First column of the joint exp-maps.
    pub const JOINTS: usize = 9;

    /// First column of the body world positions.
    pub fn body_pos(self) -> usize {
        Self::JOINTS + 3 * self.skeleton().n_joints()
    }

    /// Object columns stored in the tensor.
    pub fn objects(self) -> &'static [ObjectColumns] {
        const BALL: [ObjectColumns; 1] = [ObjectColumns { pos: 324, rot: 327 }];
        const ONE: [ObjectColumns; 1] = [ObjectColumns { pos: 402, rot: 405 }];
        const TWO: [ObjectColumns; 2] = [
            ObjectColumns { pos: 402, rot: 405 },
            ObjectColumns { pos: 408, rot: 411 },
        ];
        match self {
            Layout::BallPlay337 => &BALL,
            Layout::ParaHome409 => &ONE,
            Layout::ParaHome415 => &TWO,
        }
    }

    /// Whether the object rotation is stored negated (BallPlay only:
    /// Ingrid789/SkillMimic-V2 `skillmimic/utils/motion_data_handler.py`
    /// negates it, `paramotion_data_handler.py` does not).
    pub fn object_rotation_negated(self) -> bool {
        self == Layout::BallPlay337
    }

    /// The contact-flag column (the last one).
    pub fn contact(self) -> usize {
        self.columns() - 1
    }

    /// What column `c` holds, for error messages.
    pub fn field_of(self, c: usize) -> String {
        let sk = self.skeleton();
        let body_end = self.body_pos()
            + 3 * if sk == Skeleton::ParaHome {
                71
            } else {
                sk.n_bodies()
            };
        match c {
            0..=2 => "root position".into(),
            3..=5 => "root rotation".into(),
            6..=8 => "columns 6:9 (unused)".into(),
            _ if c < self.body_pos() => {
                let j = (c - Self::JOINTS) / 3;
                format!("joint {} ({})", j, sk.body_names()[j + 1])
            }
            _ if c < body_end => {
                let b = (c - self.body_pos()) / 3;
                let name = sk.body_names().get(b).copied().unwrap_or("unused slot");
                format!("body position {b} ({name})")
            }
            _ if c == self.contact() => "contact flag".into(),
            _ => {
                for (i, o) in self.objects().iter().enumerate() {
                    if (o.pos..o.pos + 3).contains(&c) {
                        return format!("object {i} position");
                    }
                    if (o.rot..o.rot + 3).contains(&c) {
                        return format!("object {i} rotation");
                    }
                }
                "object velocity (unused)".into()
            }
        }
    }
}

impl fmt::Display for Layout {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Bodies of `mocap_humanoid.xml` (Ingrid789/SkillMimic-V2
/// `skillmimic/data/assets/mjcf/`) in body order.
pub const BALLPLAY_BODIES: [&str; 53] = [
    "Pelvis",
    "L_Hip",
    "L_Knee",
    "L_Ankle",
    "L_Toe",
    "R_Hip",
    "R_Knee",
    "R_Ankle",
    "R_Toe",
    "Torso",
    "Spine",
    "Spine2",
    "Chest",
    "Neck",
    "Head",
    "L_Thorax",
    "L_Shoulder",
    "L_Elbow",
    "L_Wrist",
    "L_Index1",
    "L_Index2",
    "L_Index3",
    "L_Middle1",
    "L_Middle2",
    "L_Middle3",
    "L_Pinky1",
    "L_Pinky2",
    "L_Pinky3",
    "L_Ring1",
    "L_Ring2",
    "L_Ring3",
    "L_Thumb1",
    "L_Thumb2",
    "L_Thumb3",
    "R_Thorax",
    "R_Shoulder",
    "R_Elbow",
    "R_Wrist",
    "R_Index1",
    "R_Index2",
    "R_Index3",
    "R_Middle1",
    "R_Middle2",
    "R_Middle3",
    "R_Pinky1",
    "R_Pinky2",
    "R_Pinky3",
    "R_Ring1",
    "R_Ring2",
    "R_Ring3",
    "R_Thumb1",
    "R_Thumb2",
    "R_Thumb3",
];

/// Bodies of `mocap_parahome_boxhand.xml` (Ingrid789/SkillMimic-V2
/// `skillmimic/data/assets/mjcf/`) in body order.
pub const PARAHOME_BODIES: [&str; 61] = [
    "pHipOrigin",
    "jL5S1",
    "jL4L3",
    "jL1T12",
    "jT9T8",
    "jT1C7",
    "jC1Head",
    "jRightT4Shoulder",
    "jRightShoulder",
    "jRightElbow",
    "jRightWrist",
    "jRightFirstCMC",
    "jRightFirstMCP",
    "jRightIP",
    "jRightSecondCMC",
    "jRightSecondMCP",
    "jRightSecondPIP",
    "jRightSecondDIP",
    "jRightThirdCMC",
    "jRightThirdMCP",
    "jRightThirdPIP",
    "jRightThirdDIP",
    "jRightFourthCMC",
    "jRightFourthMCP",
    "jRightFourthPIP",
    "jRightFourthDIP",
    "jRightFifthCMC",
    "jRightFifthMCP",
    "jRightFifthPIP",
    "jRightFifthDIP",
    "jLeftT4Shoulder",
    "jLeftShoulder",
    "jLeftElbow",
    "jLeftWrist",
    "jLeftFirstCMC",
    "jLeftFirstMCP",
    "jLeftIP",
    "jLeftSecondCMC",
    "jLeftSecondMCP",
    "jLeftSecondPIP",
    "jLeftSecondDIP",
    "jLeftThirdCMC",
    "jLeftThirdMCP",
    "jLeftThirdPIP",
    "jLeftThirdDIP",
    "jLeftFourthCMC",
    "jLeftFourthMCP",
    "jLeftFourthPIP",
    "jLeftFourthDIP",
    "jLeftFifthCMC",
    "jLeftFifthMCP",
    "jLeftFifthPIP",
    "jLeftFifthDIP",
    "jRightHip",
    "jRightKnee",
    "jRightAnkle",
    "jRightBallFoot",
    "jLeftHip",
    "jLeftKnee",
    "jLeftAnkle",
    "jLeftBallFoot",
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn column_blocks_tile_each_layout() {
        for l in Layout::ALL {
            let sk = l.skeleton();
            assert_eq!(l.body_pos(), 9 + 3 * sk.n_joints());
            let body_slots = if sk == Skeleton::ParaHome { 71 } else { 53 };
            let first_obj = l.objects()[0].pos;
            assert_eq!(first_obj, l.body_pos() + 3 * body_slots, "{l}");
            let last = l.objects().last().unwrap();
            let tail = if l == Layout::BallPlay337 { 6 + 6 } else { 6 };
            assert_eq!(last.pos + tail, l.contact(), "{l}");
            assert_eq!(Layout::from_columns(l.columns()), Some(l));
        }
        assert_eq!(Layout::from_columns(336), None);
    }

    #[test]
    fn key_bodies_are_head_knees_elbows_ankles_fingertips() {
        let names = |sk: Skeleton| -> Vec<&str> {
            sk.key_bodies()
                .iter()
                .map(|b| sk.body_names()[*b])
                .collect()
        };
        let bp = names(Skeleton::MocapHumanoid);
        assert_eq!(
            bp[..7],
            ["Head", "L_Knee", "R_Knee", "L_Elbow", "R_Elbow", "L_Ankle", "R_Ankle"]
        );
        assert!(bp[7..].iter().all(|n| n.ends_with('3')));
        let ph = names(Skeleton::ParaHome);
        assert_eq!(
            ph[..7],
            [
                "jC1Head",
                "jLeftKnee",
                "jRightKnee",
                "jLeftElbow",
                "jRightElbow",
                "jLeftAnkle",
                "jRightAnkle"
            ]
        );
        assert!(ph[7..12].iter().all(|n| n.starts_with("jLeft")));
        assert!(ph[12..].iter().all(|n| n.starts_with("jRight")));
    }

    #[test]
    fn skeleton_sizes_match_the_models() {
        assert_eq!(Skeleton::MocapHumanoid.n_bodies(), 53);
        assert_eq!(Skeleton::ParaHome.n_joints(), 60);
    }
}
