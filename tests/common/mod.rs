//! Helpers shared by the integration tests: the real binary, temporary run
//! folders, and a writer of PyTorch-style `.pt` files for hand-made clips.
#![allow(dead_code)]

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The shipped data beside the checkout.
pub fn data_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/datasets")
}

/// Run the real binary with `args` in the checkout.
pub fn skillaug(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_skillaug"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env_remove("SKILLAUG_DATA")
        .output()
        .expect("run skillaug")
}

/// Start the real binary with `args`, wait until `ready()` holds, then
/// kill it with SIGKILL. Fails if the process ends first or `ready` takes
/// longer than `limit_s` seconds (`what` names the awaited state).
pub fn kill_when(args: &[&str], ready: impl Fn() -> bool, limit_s: u64, what: &str) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_skillaug"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env_remove("SKILLAUG_DATA")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("start skillaug");
    let t = std::time::Instant::now();
    while !ready() {
        assert!(
            child.try_wait().unwrap().is_none(),
            "the run ended before it could be killed"
        );
        assert!(t.elapsed().as_secs() < limit_s, "{what} after {limit_s} s");
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
}

/// The ball flights of BallPlay's DF clips (clip, release frame, catch
/// frame) that `train.reference_ball = "simulated"` replaces
/// (`skillaug::sim::ball_path::flight_frames`).
pub const DF_FLIGHTS: [(&str, usize, usize); 3] = [
    ("013_018pickle_run2_5", 3, 14),
    ("013_018pickle_run2_5", 56, 72),
    ("013_018pickle_run_4", 13, 34),
];

/// `--set` flags of a tiny training run: 4 environments x 8 steps, one
/// 16-unit hidden layer.
pub const TINY_TRAIN: &[&str] = &[
    "--set",
    "train.num_envs=4",
    "--set",
    "train.horizon=8",
    "--set",
    "train.ppo.hidden=[16]",
    "--set",
    "train.ppo.minibatch=16",
];

/// Pre-train a tiny history encoder (8-8-4 convolutions, 16-unit
/// predictor, batches of 8) for `steps` steps into run folder `out`.
pub fn tiny_encoder(out: &str, steps: u32) {
    let steps = format!("pretrain-he.steps={steps}");
    ok(&[
        "pretrain-he",
        "--out",
        out,
        "-q",
        "--set",
        &steps,
        "--set",
        "pretrain-he.conv=[8, 8, 4]",
        "--set",
        "pretrain-he.predictor_hidden=[16]",
        "--set",
        "pretrain-he.batch_size=8",
    ]);
}

/// `skillaug eval` of `policy` on run folder `from` into `out`, quiet,
/// with `extra` flags; returns stdout.
pub fn eval_quiet(from: &str, policy: &Path, out: &Path, extra: &[&str]) -> String {
    let mut a = vec![
        "eval",
        "--from",
        from,
        "--policy",
        policy.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "-q",
    ];
    a.extend_from_slice(extra);
    ok(&a)
}

/// Run and require success, returning stdout.
pub fn ok(args: &[&str]) -> String {
    let o = skillaug(args);
    assert!(
        o.status.success(),
        "skillaug {args:?} failed:\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Run and require exit code 1, returning stderr.
pub fn fails(args: &[&str]) -> String {
    let o = skillaug(args);
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(
        o.status.code(),
        Some(1),
        "skillaug {args:?}: expected exit 1, stderr:\n{err}"
    );
    err
}

/// A temporary folder with `dataset` ingested into its `run/` subfolder.
pub fn ingested(dataset: &str) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    ok(&[
        "ingest",
        "--dataset",
        dataset,
        "--out",
        out.to_str().unwrap(),
        "-q",
    ]);
    (dir, out)
}

/// Names of the entries in `dir` (empty if it does not exist).
pub fn entries(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .map(|r| {
            r.filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// Pickle opcodes used below (protocol 2, as torch.save writes them).
fn global(out: &mut Vec<u8>, module: &str, name: &str) {
    out.push(b'c');
    out.extend_from_slice(format!("{module}\n{name}\n").as_bytes());
}
fn unicode(out: &mut Vec<u8>, s: &str) {
    out.push(b'X');
    out.extend_from_slice(&(s.len() as u32).to_le_bytes());
    out.extend_from_slice(s.as_bytes());
}
fn int(out: &mut Vec<u8>, v: i32) {
    out.push(b'J');
    out.extend_from_slice(&v.to_le_bytes());
}

/// The pickle torch.save writes for one tensor of `shape` and `stride` over a
/// storage of class `storage` (e.g. FloatStorage) holding `numel` elements.
pub fn tensor_pickle(storage: &str, numel: usize, shape: &[usize], stride: &[usize]) -> Vec<u8> {
    let mut p = vec![0x80, 2];
    global(&mut p, "torch._utils", "_rebuild_tensor_v2");
    p.push(b'(');
    p.push(b'(');
    unicode(&mut p, "storage");
    global(&mut p, "torch", storage);
    unicode(&mut p, "0");
    unicode(&mut p, "cpu");
    int(&mut p, numel as i32);
    p.push(b't');
    p.push(b'Q');
    int(&mut p, 0);
    p.push(b'(');
    for s in shape {
        int(&mut p, *s as i32);
    }
    p.push(b't');
    p.push(b'(');
    for s in stride {
        int(&mut p, *s as i32);
    }
    p.push(b't');
    p.push(0x89); // NEWFALSE: requires_grad
    global(&mut p, "collections", "OrderedDict");
    p.push(b')');
    p.push(b'R');
    p.push(b't');
    p.push(b'R');
    p.push(b'.');
    p
}

/// A torch-style zip archive with `data.pkl`, `data/0` and `version`.
pub fn pt_archive(pickle: &[u8], storage: &[u8]) -> Vec<u8> {
    let mut buf = std::io::Cursor::new(Vec::new());
    {
        let mut z = zip::ZipWriter::new(&mut buf);
        let opt = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored);
        for (name, bytes) in [
            ("archive/data.pkl", pickle),
            ("archive/data/0", storage),
            ("archive/version", b"3\n".as_slice()),
        ] {
            z.start_file(name, opt).unwrap();
            z.write_all(bytes).unwrap();
        }
        z.finish().unwrap();
    }
    buf.into_inner()
}

/// A `.pt` file of a float32 `[rows, cols]` matrix.
pub fn f32_pt(rows: usize, cols: usize, data: &[f32]) -> Vec<u8> {
    assert_eq!(data.len(), rows * cols);
    let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
    pt_archive(
        &tensor_pickle("FloatStorage", rows * cols, &[rows, cols], &[cols, 1]),
        &bytes,
    )
}

/// The values of a real clip, read with the project's reader.
pub fn read_clip(path: &Path) -> (usize, usize, Vec<f32>) {
    let m = skillaug::pt::read_f32_matrix(&std::fs::read(path).unwrap()).unwrap();
    (m.rows, m.cols, m.data)
}

/// A Python 3 that imports `packages` (PyPI names that are also module
/// names): the system one if it has them (`.ci/run` installs them), else a
/// virtual environment under target/ made on first use.
pub fn python_with(packages: &[&str]) -> PathBuf {
    let import = format!("import {}", packages.join(", "));
    let has = |py: &Path| {
        Command::new(py)
            .args(["-c", &import])
            .output()
            .is_ok_and(|o| o.status.success())
    };
    let system = Path::new("python3");
    if has(system) {
        return system.into();
    }
    let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/test-venv");
    let py = venv.join("bin/python");
    if !has(&py) {
        let made = (py.exists()
            || Command::new("python3")
                .args(["-m", "venv"])
                .arg(&venv)
                .status()
                .is_ok_and(|s| s.success()))
            && Command::new(&py)
                .args(["-m", "pip", "install", "--quiet"])
                .args(packages)
                .status()
                .is_ok_and(|s| s.success());
        assert!(
            made,
            "this test needs Python 3 with {}: `pip install {}` (bash .ci/run does)",
            packages.join(", "),
            packages.join(" ")
        );
    }
    py
}

/// `skillaug sample-stf` of 20 trajectories into run folder `from` with
/// neighbourhood starts only and wide joint radii (seed 3), so that some
/// trajectories have masked states and missing reference frames.
pub fn sample_masked_stf(from: &str) {
    ok(&[
        "sample-stf",
        "--out",
        from,
        "-q",
        "--seed",
        "3",
        "--set",
        "sample-stf.p_e=0",
        "--set",
        "sample-stf.p_n=1.0",
        "--set",
        "sample-stf.eps.dof=0.5",
        "--set",
        "sample-stf.trajectories=20",
    ]);
}

/// The environment set-up of `cfg` on run folder `run` as `skillaug train
/// --from RUN` builds it without a recipe or overrides: default
/// `[sample-stf]` settings, the shipped data root.
pub fn setup_for(
    run: &Path,
    cfg: &skillaug::rl::config::TrainConfig,
) -> skillaug::rl::trainer::Setup {
    skillaug::rl::trainer::Setup::load(
        run,
        Some(&data_root()),
        cfg,
        &skillaug::augment::settings::StfConfig::default(),
    )
    .unwrap()
}

/// Column `name` of `b` as a primitive array of `T` (panics naming the
/// column when it is missing or of another type).
pub fn prim<'a, T: arrow::datatypes::ArrowPrimitiveType>(
    b: &'a arrow::record_batch::RecordBatch,
    name: &str,
) -> &'a arrow::array::PrimitiveArray<T> {
    use arrow::array::AsArray;
    b.column_by_name(name)
        .unwrap_or_else(|| panic!("no column `{name}`"))
        .as_primitive_opt::<T>()
        .unwrap_or_else(|| panic!("column `{name}` is not of the expected type"))
}

/// Every Float64 column of train_metrics.parquet except the timings, by name.
pub fn metrics(dir: &Path) -> Vec<(String, Vec<f64>)> {
    let t = skillaug::table::io::read_parquet(&dir.join("train_metrics.parquet")).unwrap();
    let b = &t.batches[0];
    let mut v = Vec::new();
    for f in b.schema().fields() {
        use arrow::array::AsArray;
        let name = f.name().clone();
        if ["samples_per_s", "sim_s", "act_s", "update_s"].contains(&name.as_str()) {
            continue;
        }
        if let Some(a) = b
            .column_by_name(&name)
            .unwrap()
            .as_primitive_opt::<arrow::datatypes::Float64Type>()
        {
            v.push((name, a.values().to_vec()));
        }
    }
    v
}

/// Every f32 tensor of a safetensors file, by name.
pub fn weights(path: &Path) -> Vec<(String, Vec<f32>)> {
    let m = candle_core::safetensors::load(path, &candle_core::Device::Cpu).unwrap();
    let mut v: Vec<(String, Vec<f32>)> = m
        .into_iter()
        .filter(|(_, t)| t.dtype() == candle_core::DType::F32)
        .map(|(k, t)| (k, t.flatten_all().unwrap().to_vec1::<f32>().unwrap()))
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

/// The iteration of the checkpoint in `out` (None: none yet).
pub fn checkpoint_iteration(out: &Path) -> Option<u64> {
    let text = std::fs::read_to_string(out.join("checkpoint/state.json")).ok()?;
    let v: serde_json::Value = serde_json::from_str(&text).ok()?;
    v["iteration"].as_u64()
}
