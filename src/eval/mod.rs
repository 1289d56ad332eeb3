//! Evaluation: the evaluator of `skillaug eval` ([`evaluator`]), success
//! rules ([`rules`]), the per-cell summary with its Wilson intervals
//! ([`summary`]) and the paper-shaped tables of `skillaug report`
//! ([`report`]).

pub mod evaluator;
pub mod report;
pub mod rules;
pub mod summary;

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
