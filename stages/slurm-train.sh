#!/usr/bin/env bash
# Data-parallel training of one skillaug recipe on a Slurm cluster (README,
# "Training on a cluster"). Submit with: sbatch stages/slurm-train.sh
#
# Every task is one MPI rank that simulates train.num_envs / (number of
# tasks) environments with its own random stream; the ranks average their
# gradients after every minibatch, so all of them hold the same weights.
# train.num_envs and train.ppo.minibatch must be multiples of the number of
# tasks. Rank 0 alone writes the run folder, which every node must see (a
# shared file system), as it must see the input run folder and the data.
#
# Build once, on a node with the cluster's MPI (Open MPI here; libclang is
# needed at build time only):
#   cargo build --release --features mpi
#
#SBATCH --job-name=skillaug-train
#SBATCH --nodes=4                 # machines
#SBATCH --ntasks-per-node=8       # MPI ranks per machine
#SBATCH --cpus-per-task=4         # threads per rank (physics and matmul)
#SBATCH --time=24:00:00
#SBATCH --output=skillaug-train-%j.log

set -euo pipefail
cd "${SLURM_SUBMIT_DIR:-.}"

RANKS=$SLURM_NTASKS   # 32
# 64 environments per rank: 2,048 in all, the paper preset's count (Table 6)
ENVS=$((64 * RANKS))

# srun starts the ranks through PMIx; with Open MPI's own launcher give each
# rank its cores (Open MPI binds a rank to one core by default):
#   mpirun -np "$RANKS" --map-by ppr:8:node:PE="$SLURM_CPUS_PER_TASK" ...
srun --mpi=pmix --cpu-bind=cores \
    target/release/skillaug train \
    --from runs/bp --out runs/df-cluster \
    --recipe stages/df-skill.toml \
    --set train.preset=paper \
    --set train.num_envs="$ENVS" \
    --set train.samples=1300000000 \
    --threads "$SLURM_CPUS_PER_TASK" \
    --seed 0

# After a node failure, the same command with --resume continues from the
# last checkpoint (same number of ranks), exactly as if nothing had happened.
