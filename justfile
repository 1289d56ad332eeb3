# Common tasks. `just` is optional: each recipe is one plain command.

# The README's main job: train the pickup skill and evaluate and report it.
main:
    cargo run --release -- run stages/quickstart.toml --out runs/quickstart

# The whole test suite (what CI runs).
test:
    cargo test --release

# Everything CI checks, plus lints.
ci:
    cargo fmt --all -- --check
    cargo clippy --release --all-targets -- -D warnings
    bash .ci/run

# Re-bless the schema golden files after an intended change.
bless-schemas:
    for t in clips frames stg_edges stg_summary he_loss he_embeddings stf_samples train_metrics eval_trials eval_summary eval_rollouts; do cargo run --release -q -- schema $t > schemas/$t.txt; done

# Ingest every shipped dataset and time it.
bench-ingest:
    cargo build --release
    for d in ballplay ballplay-m locomotion parahome; do ./target/release/skillaug ingest --dataset $d --out runs/bench-$d; done
