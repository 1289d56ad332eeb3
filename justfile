# Common tasks. `just` is optional: each recipe is one plain command.

# The main job on the default data: ingest the five BallPlay skills.
main:
    cargo run --release -- ingest --dataset ballplay --recipe stages/ballplay.toml --out runs/ballplay

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
    for t in clips frames stg_edges stg_summary stf_samples he_loss he_embeddings; do cargo run --release -q -- schema $t > schemas/$t.txt; done

# Ingest every shipped dataset and time it.
bench-ingest:
    cargo build --release
    for d in ballplay ballplay-m locomotion parahome; do ./target/release/skillaug ingest --dataset $d --out runs/bench-$d; done
