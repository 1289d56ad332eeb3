//! `skillaug report`: one or more `eval_summary.parquet` files as tables
//! shaped like the paper's (methods as rows; per skill an
//! "SR / εNSR / NR" cell; Avg.; TSR columns and their average), printed and
//! optionally written as Markdown. `--with-reference` adds the paper's rows
//! (the paper's Tables 1, 2 and 5) beside ours.

use anyhow::{bail, Result};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The paper's cells: (method, per-skill (skill, SR %, εNSR %, NR), TSR
/// ((from, to), %)).
pub struct PaperRow {
    /// Method as the paper names it.
    pub method: &'static str,
    /// Per skill: (skill id, SR %, εNSR %, NR).
    pub cells: &'static [(&'static str, f64, f64, f64)],
    /// Transitions: (from, to, TSR %).
    pub tsr: &'static [(&'static str, &'static str, f64)],
    /// The paper's Avg. cell (SR, εNSR, NR) and TSR Avg., as printed (NaN
    /// where the table prints none: Table 5).
    pub avg: (f64, f64, f64, Option<f64>),
}

/// Table 1 (BallPlay).
pub const TABLE1: &[PaperRow] = &[
    PaperRow {
        method: "DM",
        cells: &[
            ("run", 89.2, 38.5, 0.09),
            ("lrun", 70.4, 24.5, 0.10),
            ("rrun", 87.5, 26.8, 0.06),
            ("layup", 0.0, 0.0, 0.18),
            ("shot", 0.0, 0.0, 0.12),
        ],
        tsr: &[
            ("lrun", "rrun", 1.6),
            ("run", "rrun", 17.1),
            ("run", "shot", 0.0),
            ("layup", "run", 50.2),
        ],
        avg: (49.4, 18.0, 0.11, Some(17.2)),
    },
    PaperRow {
        method: "DM+eNSI",
        cells: &[
            ("run", 96.2, 56.3, 0.10),
            ("lrun", 76.5, 38.7, 0.11),
            ("rrun", 81.8, 29.5, 0.06),
            ("layup", 1.0, 0.5, 0.20),
            ("shot", 0.0, 0.0, 0.11),
        ],
        tsr: &[
            ("lrun", "rrun", 2.9),
            ("run", "rrun", 14.0),
            ("run", "shot", 0.0),
            ("layup", "run", 46.1),
        ],
        avg: (51.1, 25.0, 0.12, Some(15.8)),
    },
    PaperRow {
        method: "DM+Ours",
        cells: &[
            ("run", 88.6, 53.8, 0.08),
            ("lrun", 89.4, 55.9, 0.08),
            ("rrun", 92.6, 54.2, 0.10),
            ("layup", 99.1, 50.9, 0.12),
            ("shot", 0.0, 0.0, 0.06),
        ],
        tsr: &[
            ("lrun", "rrun", 93.6),
            ("run", "rrun", 87.0),
            ("run", "shot", 0.0),
            ("layup", "run", 72.1),
        ],
        avg: (73.9, 43.0, 0.088, Some(63.2)),
    },
    PaperRow {
        method: "SM",
        cells: &[
            ("run", 97.3, 40.3, 0.64),
            ("lrun", 71.9, 29.4, 0.49),
            ("rrun", 97.8, 22.9, 0.35),
            ("layup", 0.0, 0.0, 0.64),
            ("shot", 2.9, 1.3, 0.48),
        ],
        tsr: &[
            ("lrun", "rrun", 1.4),
            ("run", "rrun", 28.0),
            ("run", "shot", 0.8),
            ("layup", "run", 31.2),
        ],
        avg: (54.0, 18.8, 0.52, Some(15.4)),
    },
    PaperRow {
        method: "SM+eNSI",
        cells: &[
            ("run", 98.1, 61.2, 0.38),
            ("lrun", 98.7, 59.8, 0.51),
            ("rrun", 97.1, 44.9, 0.36),
            ("layup", 23.1, 12.1, 0.62),
            ("shot", 0.0, 0.0, 0.39),
        ],
        tsr: &[
            ("lrun", "rrun", 37.2),
            ("run", "rrun", 77.3),
            ("run", "shot", 0.0),
            ("layup", "run", 49.3),
        ],
        avg: (63.4, 35.6, 0.45, Some(41.0)),
    },
    PaperRow {
        method: "SM+Ours",
        cells: &[
            ("run", 99.8, 62.7, 0.37),
            ("lrun", 100.0, 42.2, 0.42),
            ("rrun", 99.7, 42.0, 0.34),
            ("layup", 96.6, 58.5, 0.57),
            ("shot", 100.0, 56.0, 0.46),
        ],
        tsr: &[
            ("lrun", "rrun", 100.0),
            ("run", "rrun", 99.7),
            ("run", "shot", 99.8),
            ("layup", "run", 99.8),
        ],
        avg: (99.2, 52.3, 0.43, Some(99.8)),
    },
];

/// Table 5 (Locomotion).
pub const TABLE5: &[PaperRow] = &[
    PaperRow {
        method: "DM",
        cells: &[
            ("getup", 24.4, 24.9, 0.64),
            ("run_no_object", 46.5, 22.2, 0.73),
        ],
        tsr: &[
            ("getup", "run_no_object", 0.2),
            ("run_no_object", "getup", 22.4),
        ],
        avg: (f64::NAN, f64::NAN, f64::NAN, None),
    },
    PaperRow {
        method: "DM+eNSI",
        cells: &[
            ("getup", 96.9, 97.9, 0.47),
            ("run_no_object", 93.2, 84.9, 0.65),
        ],
        tsr: &[
            ("getup", "run_no_object", 62.6),
            ("run_no_object", "getup", 5.7),
        ],
        avg: (f64::NAN, f64::NAN, f64::NAN, None),
    },
    PaperRow {
        method: "DM+Ours",
        cells: &[
            ("getup", 98.5, 98.2, 0.54),
            ("run_no_object", 97.1, 81.5, 0.64),
        ],
        tsr: &[
            ("getup", "run_no_object", 67.2),
            ("run_no_object", "getup", 96.2),
        ],
        avg: (f64::NAN, f64::NAN, f64::NAN, None),
    },
    PaperRow {
        method: "SM",
        cells: &[
            ("getup", 69.2, 66.0, 0.80),
            ("run_no_object", 74.0, 36.4, 0.78),
        ],
        tsr: &[
            ("getup", "run_no_object", 10.5),
            ("run_no_object", "getup", 44.9),
        ],
        avg: (f64::NAN, f64::NAN, f64::NAN, None),
    },
    PaperRow {
        method: "SM+eNSI",
        cells: &[
            ("getup", 97.8, 97.3, 0.66),
            ("run_no_object", 99.4, 91.8, 0.77),
        ],
        tsr: &[
            ("getup", "run_no_object", 93.4),
            ("run_no_object", "getup", 12.7),
        ],
        avg: (f64::NAN, f64::NAN, f64::NAN, None),
    },
    PaperRow {
        method: "SM+Ours",
        cells: &[
            ("getup", 99.1, 98.0, 0.64),
            ("run_no_object", 99.9, 91.0, 0.71),
        ],
        tsr: &[
            ("getup", "run_no_object", 97.9),
            ("run_no_object", "getup", 100.0),
        ],
        avg: (f64::NAN, f64::NAN, f64::NAN, None),
    },
];

/// Table 2 (ParaHome).
pub const TABLE2: &[PaperRow] = &[
    PaperRow {
        method: "SM",
        cells: &[
            ("place_pan", 38.4, 1.0, 0.92),
            ("place_kettle", 0.0, 0.0, 0.51),
            ("place_book", 0.0, 0.0, 0.53),
            ("drink_cup", 0.0, 0.0, 0.39),
            ("pour_kettle", 0.0, 0.0, 0.84),
            ("getup_chair", 0.0, 0.0, 0.55),
            ("pour_kettlecup", 0.0, 0.0, 0.79),
        ],
        tsr: &[],
        avg: (5.5, 0.1, 0.65, None),
    },
    PaperRow {
        method: "SM+eNSI",
        cells: &[
            ("place_pan", 100.0, 16.2, 0.88),
            ("place_kettle", 0.0, 0.0, 0.53),
            ("place_book", 0.0, 0.0, 0.32),
            ("drink_cup", 0.0, 0.0, 0.42),
            ("pour_kettle", 0.0, 0.0, 0.67),
            ("getup_chair", 0.0, 0.0, 0.55),
            ("pour_kettlecup", 0.0, 0.0, 0.74),
        ],
        tsr: &[],
        avg: (14.3, 2.3, 0.59, None),
    },
    PaperRow {
        method: "SM+T",
        cells: &[
            ("place_pan", 51.6, 12.6, 0.93),
            ("place_kettle", 0.0, 0.0, 0.30),
            ("place_book", 100.0, 12.1, 0.85),
            ("drink_cup", 99.9, 20.3, 0.84),
            ("pour_kettle", 100.0, 21.5, 0.95),
            ("getup_chair", 0.0, 0.0, 0.63),
            ("pour_kettlecup", 48.1, 8.0, 0.86),
        ],
        tsr: &[],
        avg: (57.1, 15.6, 0.77, None),
    },
    PaperRow {
        method: "SM+Ours",
        cells: &[
            ("place_pan", 100.0, 22.2, 0.86),
            ("place_kettle", 100.0, 49.9, 0.52),
            ("place_book", 100.0, 82.4, 0.86),
            ("drink_cup", 100.0, 33.9, 0.89),
            ("pour_kettle", 99.9, 22.5, 0.93),
            ("getup_chair", 100.0, 46.6, 0.74),
            ("pour_kettlecup", 100.0, 23.1, 0.87),
        ],
        tsr: &[],
        avg: (100.0, 40.1, 0.81, None),
    },
];

/// Column names the paper uses for skill ids.
pub fn display_name(skill: &str) -> String {
    match skill {
        "run" => "DF".into(),
        "lrun" => "DL".into(),
        "rrun" => "DR".into(),
        "layup" => "Layup".into(),
        "shot" => "Shot".into(),
        "getup" => "Getup".into(),
        "run_no_object" => "Run".into(),
        "getup_chair" => "Stand-Chair".into(),
        other => other
            .split('_')
            .map(|w| {
                let mut c = w.chars();
                c.next()
                    .map_or(String::new(), |f| f.to_uppercase().chain(c).collect())
            })
            .collect::<Vec<_>>()
            .join("-"),
    }
}

/// One method's numbers: per skill (SR, εNSR, NR) in % / % / reward, and
/// TSR per pair in %.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MethodRow {
    /// Label.
    pub label: String,
    /// skill -> (SR, εNSR, NR), NaN where not evaluated.
    pub cells: BTreeMap<String, (f64, f64, f64)>,
    /// (from, to) -> TSR %.
    pub tsr: BTreeMap<(String, String), f64>,
    /// Rule skill -> the longest trial length of its success-rate cells,
    /// policy steps.
    pub trial_steps: BTreeMap<String, u32>,
    /// Whether the summary recorded trial lengths (those written before
    /// the `trial_steps` column did not).
    pub trial_steps_recorded: bool,
}

/// The rows of one summary file (polars), one per label.
pub fn load(path: &Path) -> Result<Vec<MethodRow>> {
    use crate::table::eval::summary_frame;
    use crate::table::io::{frame_f64s, frame_strs};
    let df = summary_frame(path)?;
    let s = |c: &str| frame_strs(&df, c);
    let (label, metric, from, to) = (s("label")?, s("metric")?, s("from_skill")?, s("to_skill")?);
    let values = frame_f64s(&df, "value")?;
    // summaries written before the column have no trial length
    let steps = if df
        .get_column_names()
        .iter()
        .any(|c| c.as_str() == "trial_steps")
    {
        crate::table::io::frame_u32s(&df, "trial_steps")?
    } else {
        Vec::new()
    };
    let mut rows: Vec<MethodRow> = Vec::new();
    for i in 0..df.height() {
        let v = values[i];
        let r = match rows.iter_mut().position(|r| r.label == label[i]) {
            Some(k) => &mut rows[k],
            None => {
                rows.push(MethodRow {
                    label: label[i].clone(),
                    trial_steps_recorded: !steps.is_empty(),
                    ..Default::default()
                });
                rows.last_mut().unwrap()
            }
        };
        let m = metric[i].as_str();
        if let (Some(&n), true) = (steps.get(i), m != "nr") {
            let e = r.trial_steps.entry(to[i].clone()).or_insert(0);
            *e = (*e).max(n);
        }
        if m == "tsr" {
            r.tsr.insert((from[i].clone(), to[i].clone()), 100.0 * v);
            continue;
        }
        let cell = r
            .cells
            .entry(from[i].clone())
            .or_insert((f64::NAN, f64::NAN, f64::NAN));
        match m {
            "sr" => cell.0 = 100.0 * v,
            "nsr" => cell.1 = 100.0 * v,
            "nr" => cell.2 = v,
            other => bail!("{}: unknown metric `{other}`", path.display()),
        }
    }
    Ok(rows)
}

/// A paper row as a [`MethodRow`] labelled "paper: METHOD".
pub fn paper_row(p: &PaperRow) -> MethodRow {
    MethodRow {
        label: format!("paper: {}", p.method),
        cells: p
            .cells
            .iter()
            .map(|(s, a, b, c)| (s.to_string(), (*a, *b, *c)))
            .collect(),
        tsr: p
            .tsr
            .iter()
            .map(|(a, b, v)| ((a.to_string(), b.to_string()), *v))
            .collect(),
        trial_steps: BTreeMap::new(),
        trial_steps_recorded: false,
    }
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let v: Vec<f64> = v.filter(|x| !x.is_nan()).collect();
    if v.is_empty() {
        f64::NAN
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

/// The per-skill average cell (SR, εNSR, NR) and the TSR average of a row
/// over `skills` and `pairs`.
pub fn averages(
    r: &MethodRow,
    skills: &[String],
    pairs: &[(String, String)],
) -> (f64, f64, f64, f64) {
    let cell = |s: &String| {
        r.cells
            .get(s)
            .copied()
            .unwrap_or((f64::NAN, f64::NAN, f64::NAN))
    };
    (
        mean(skills.iter().map(|s| cell(s).0)),
        mean(skills.iter().map(|s| cell(s).1)),
        mean(skills.iter().map(|s| cell(s).2)),
        mean(
            pairs
                .iter()
                .map(|p| r.tsr.get(p).copied().unwrap_or(f64::NAN)),
        ),
    )
}

fn pct(v: f64) -> String {
    if v.is_nan() {
        "-".into()
    } else {
        format!("{v:.1}")
    }
}

fn nr(v: f64) -> String {
    if v.is_nan() {
        "-".into()
    } else {
        format!("{v:.2}")
    }
}

/// Render rows as (header, body rows) of text cells.
pub fn table(rows: &[MethodRow]) -> (Vec<String>, Vec<Vec<String>>) {
    let order = [
        "run",
        "lrun",
        "rrun",
        "layup",
        "shot",
        "getup",
        "run_no_object",
        "place_pan",
        "place_kettle",
        "place_book",
        "drink_cup",
        "pour_kettle",
        "getup_chair",
        "pour_kettlecup",
    ];
    let mut skills: Vec<String> = Vec::new();
    let mut pairs: Vec<(String, String)> = Vec::new();
    for r in rows.iter().filter(|r| !r.label.starts_with("paper: ")) {
        for s in r.cells.keys() {
            if !skills.contains(s) {
                skills.push(s.clone());
            }
        }
        for p in r.tsr.keys() {
            if !pairs.contains(p) {
                pairs.push(p.clone());
            }
        }
    }
    let rank = |s: &String| order.iter().position(|o| o == s).unwrap_or(order.len());
    skills.sort_by_key(|s| (rank(s), s.clone()));
    // the paper's column order
    let pair_order = [
        ("lrun", "rrun"),
        ("run", "rrun"),
        ("run", "shot"),
        ("layup", "run"),
        ("getup", "run_no_object"),
        ("run_no_object", "getup"),
    ];
    let prank = |p: &(String, String)| {
        pair_order
            .iter()
            .position(|(a, b)| *a == p.0 && *b == p.1)
            .unwrap_or(pair_order.len())
    };
    pairs.sort_by_key(|p| (prank(p), rank(&p.0), rank(&p.1)));
    let mut header = vec!["Method".to_string()];
    header.extend(skills.iter().map(|s| display_name(s)));
    header.push("Avg.".into());
    header.extend(
        pairs
            .iter()
            .map(|(a, b)| format!("TSR {}-{}", display_name(a), display_name(b))),
    );
    if !pairs.is_empty() {
        header.push("TSR Avg.".into());
    }
    let body = rows
        .iter()
        .map(|r| {
            let mut v = vec![r.label.clone()];
            for s in &skills {
                let c = r
                    .cells
                    .get(s)
                    .copied()
                    .unwrap_or((f64::NAN, f64::NAN, f64::NAN));
                v.push(format!("{} / {} / {}", pct(c.0), pct(c.1), nr(c.2)));
            }
            let (a, b, c, t) = averages(r, &skills, &pairs);
            v.push(format!("{} / {} / {}", pct(a), pct(b), nr(c)));
            for p in &pairs {
                v.push(pct(r.tsr.get(p).copied().unwrap_or(f64::NAN)));
            }
            if !pairs.is_empty() {
                v.push(pct(t));
            }
            v
        })
        .collect();
    (header, body)
}

/// Lines saying how long the trials were, and which skills' trials were
/// too short for their success rule to reach a verdict (scored as
/// failures, [`crate::eval::rules::Rule::min_steps`]).
pub fn trial_notes(rows: &[MethodRow]) -> Vec<String> {
    use crate::eval::rules::Rule;
    let mut notes = Vec::new();
    for r in rows.iter().filter(|r| !r.label.starts_with("paper: ")) {
        if !r.trial_steps_recorded {
            notes.push(format!(
                "{}: trial length not recorded (a summary written before the `trial_steps` column)",
                r.label
            ));
            continue;
        }
        let mut lengths: Vec<u32> = r.trial_steps.values().copied().collect();
        lengths.sort_unstable();
        lengths.dedup();
        if !lengths.is_empty() {
            let l: Vec<String> = lengths.iter().map(u32::to_string).collect();
            notes.push(format!(
                "{}: trials of {} policy steps",
                r.label,
                l.join(" / ")
            ));
        }
        for (skill, &n) in &r.trial_steps {
            if let Some(rule) = Rule::of_skill(skill, 0.0) {
                if (n as usize) < rule.min_steps() {
                    notes.push(format!(
                        "{}: {} trials of {n} steps are shorter than its success rule needs ({}): \
                         every one is scored as a failure",
                        r.label,
                        display_name(skill),
                        rule.min_steps()
                    ));
                }
            }
        }
    }
    notes
}

/// Markdown text of a table.
pub fn markdown(header: &[String], body: &[Vec<String>]) -> String {
    let mut s = format!(
        "| {} |\n|{}|\n",
        header.join(" | "),
        vec!["---"; header.len()].join("|")
    );
    for r in body {
        s += &format!("| {} |\n", r.join(" | "));
    }
    s
}

/// Aligned terminal text of a table.
pub fn text(header: &[String], body: &[Vec<String>]) -> String {
    let w: Vec<usize> = (0..header.len())
        .map(|i| {
            body.iter()
                .map(|r| r[i].len())
                .chain([header[i].len()])
                .max()
                .unwrap_or(0)
        })
        .collect();
    let line = |r: &[String]| {
        r.iter()
            .enumerate()
            .map(|(i, c)| {
                if i == 0 {
                    format!("{c:<w$}", w = w[i])
                } else {
                    format!("{c:>w$}", w = w[i])
                }
            })
            .collect::<Vec<_>>()
            .join("  ")
            + "\n"
    };
    let mut s = line(header);
    s += &(w
        .iter()
        .map(|n| "-".repeat(*n))
        .collect::<Vec<_>>()
        .join("  ")
        + "\n");
    for r in body {
        s += &line(r);
    }
    s
}

/// Which paper table matches these skills.
fn paper_table(rows: &[MethodRow]) -> &'static [PaperRow] {
    let has = |s: &str| rows.iter().any(|r| r.cells.contains_key(s));
    if has("getup") || has("run_no_object") {
        TABLE5
    } else if has("place_pan")
        || has("drink_cup")
        || has("pour_kettle")
        || has("getup_chair")
        || has("place_kettle")
        || has("place_book")
        || has("pour_kettlecup")
    {
        TABLE2
    } else {
        TABLE1
    }
}

/// Run the command: read `inputs` (files or folders with eval_summary.parquet).
pub fn run(inputs: &[PathBuf], with_reference: bool, markdown_out: Option<&Path>) -> Result<()> {
    if inputs.is_empty() {
        bail!("report: give at least one eval_summary.parquet or eval folder");
    }
    // rows of one label from several files (per-skill policies) merge
    let mut rows: Vec<MethodRow> = Vec::new();
    for p in inputs {
        let f = if p.is_dir() {
            p.join("eval_summary.parquet")
        } else {
            p.clone()
        };
        for r in load(&f)? {
            match rows.iter_mut().find(|x| x.label == r.label) {
                Some(x) => {
                    x.cells.extend(r.cells);
                    x.tsr.extend(r.tsr);
                    x.trial_steps.extend(r.trial_steps);
                    x.trial_steps_recorded &= r.trial_steps_recorded;
                }
                None => rows.push(r),
            }
        }
    }
    if with_reference {
        rows.extend(paper_table(&rows).iter().map(paper_row));
    }
    let (h, b) = table(&rows);
    print!("{}", text(&h, &b));
    println!("cells: SR % / eps-NSR % / NR; TSR in %");
    let notes = trial_notes(&rows);
    for n in &notes {
        println!("{n}");
    }
    if let Some(m) = markdown_out {
        let mut md = markdown(&h, &b);
        md.push_str("\nCells: SR % / eps-NSR % / NR; TSR in %.\n");
        for n in &notes {
            md.push_str(&format!("\n- {n}"));
        }
        if !notes.is_empty() {
            md.push('\n');
        }
        let mut staged = crate::table::io::Staged::new();
        staged.text(m, &md)?;
        staged.commit()?;
        println!("wrote {}", m.display());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn skills_of(t: &[PaperRow]) -> Vec<String> {
        t[0].cells.iter().map(|c| c.0.to_string()).collect()
    }

    #[test]
    fn averaging_the_paper_cells_reproduces_its_avg_cells() {
        for t in [TABLE1, TABLE2, TABLE5] {
            let skills = skills_of(t);
            for p in t {
                let r = paper_row(p);
                let pairs: Vec<(String, String)> = r.tsr.keys().cloned().collect();
                let (a, b, c, d) = averages(&r, &skills, &pairs);
                if p.avg.0.is_nan() {
                    continue; // Table 5 prints no Avg.
                }
                assert!(
                    (a - p.avg.0).abs() <= 0.051,
                    "{}: SR avg {a} vs {}",
                    p.method,
                    p.avg.0
                );
                // Table 2's SM+T eNSR Avg. (15.6) is not the mean of its cells
                // (10.64): a known inconsistency of the paper (Table 2 as printed)
                if !(p.method == "SM+T" && std::ptr::eq(t, TABLE2)) {
                    assert!(
                        (b - p.avg.1).abs() <= 0.051,
                        "{}: eNSR avg {b} vs {}",
                        p.method,
                        p.avg.1
                    );
                } else {
                    assert!((b - 10.64).abs() < 0.01);
                }
                // NR is printed to two decimals (three for DM+Ours)
                assert!(
                    (c - p.avg.2).abs() <= 0.0051,
                    "{}: NR avg {c} vs {}",
                    p.method,
                    p.avg.2
                );
                if let Some(tsr) = p.avg.3 {
                    assert!(
                        (d - tsr).abs() <= 0.051,
                        "{}: TSR avg {d} vs {tsr}",
                        p.method
                    );
                }
            }
        }
    }

    #[test]
    fn display_names_follow_the_paper() {
        assert_eq!(display_name("run"), "DF");
        assert_eq!(display_name("place_pan"), "Place-Pan");
        assert_eq!(display_name("pour_kettlecup"), "Pour-Kettlecup");
    }
}
