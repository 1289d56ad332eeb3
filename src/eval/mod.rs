//! Evaluation: the evaluator of `skillaug eval` ([`evaluator`]), success
//! rules ([`rules`]), the per-cell summary with its Wilson intervals
//! ([`summary`]) and the paper-shaped tables of `skillaug report`
//! ([`report`]).

pub mod evaluator;
pub mod report;
pub mod rules;
pub mod summary;

use crate::rl::config::Switches;
use anyhow::{bail, Result};

/// The label of a policy from its switches: "SM", "DM+eNSI", "SM+STG+STF+ATS+HE", ...
/// ("+Res" and "+RefObs" for residual actions and the reference observation).
pub fn method_label(t: &crate::rl::config::TrainConfig) -> String {
    let mut s = match t.method {
        crate::rl::humanoid::Method::Sm => "SM".to_string(),
        crate::rl::humanoid::Method::Dm => "DM".to_string(),
    };
    for (on, name) in [
        (t.nsi && !t.stf, "eNSI"),
        (t.stg, "STG"),
        (t.stf, "STF"),
        (t.ats, "ATS"),
        (t.he, "HE"),
        (t.residual_action, "Res"),
        (t.reference_obs, "RefObs"),
    ] {
        if on {
            s.push('+');
            s.push_str(name);
        }
    }
    s
}

/// The switches of a method label ([`method_label`]'s output, `Ours` for
/// STG + STF + ATS + HE, without STG for ParaHome), as `[run] methods`
/// names them.
pub fn parse_method(label: &str, parahome: bool) -> Result<Switches> {
    use crate::rl::humanoid::Method;
    let mut parts = label.split('+').map(str::trim);
    let method = match parts.next().unwrap_or("").to_ascii_uppercase().as_str() {
        "SM" => Method::Sm,
        "DM" => Method::Dm,
        other => bail!("run.methods: `{label}`: `{other}` is not SM or DM"),
    };
    let mut sw = Switches {
        method: Some(method),
        ..Default::default()
    };
    for p in parts {
        match p.to_ascii_uppercase().as_str() {
            "ENSI" | "NSI" => sw.nsi = true,
            "STG" => sw.stg = true,
            "STF" => sw.stf = true,
            "ATS" => sw.ats = true,
            "HE" => sw.he = true,
            "RES" => sw.residual_action = true,
            "REFOBS" => sw.reference_obs = true,
            "OURS" => {
                sw.stg = !parahome;
                sw.stf = true;
                sw.ats = true;
                sw.he = true;
            }
            other => bail!(
                "run.methods: `{label}`: unknown component `{other}` (eNSI, STG, STF, ATS, HE, Res, RefObs, Ours)"
            ),
        }
    }
    Ok(sw)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn method_labels_parse_into_switches() {
        let s = parse_method("SM+Ours", false).unwrap();
        assert!(s.stg && s.stf && s.ats && s.he && !s.nsi);
        let p = parse_method("SM+Ours", true).unwrap();
        assert!(!p.stg && p.stf && p.ats && p.he);
        let d = parse_method("DM+eNSI", false).unwrap();
        assert_eq!(d.method, Some(crate::rl::humanoid::Method::Dm));
        assert!(d.nsi && !d.stf);
        assert!(parse_method("XM", false).is_err());
        assert!(parse_method("SM+Magic", false).is_err());
    }

    #[test]
    fn every_method_label_parses_back_into_its_switches() {
        use crate::rl::config::TrainConfig;
        use crate::rl::humanoid::Method;
        // every combination of the labelled switches (eNSI shows only
        // without STF), on both methods
        for bits in 0u32..(1 << 8) {
            let on = |k: u32| bits & (1 << k) != 0;
            let cfg = TrainConfig {
                method: if on(0) { Method::Dm } else { Method::Sm },
                nsi: on(1),
                stg: on(2),
                stf: on(3),
                ats: on(4),
                he: on(5),
                residual_action: on(6),
                reference_obs: on(7),
                ..Default::default()
            };
            let label = method_label(&cfg);
            let mut back = TrainConfig::default();
            parse_method(&label, false).unwrap().apply(&mut back);
            assert_eq!(method_label(&back), label);
            assert_eq!(
                (back.method, back.stg, back.stf, back.ats, back.he),
                (cfg.method, cfg.stg, cfg.stf, cfg.ats, cfg.he),
                "{label}"
            );
            assert_eq!(
                (back.residual_action, back.reference_obs),
                (cfg.residual_action, cfg.reference_obs),
                "{label}"
            );
        }
    }
}
