//! Communication between the processes of a data-parallel training run.
//!
//! `skillaug train` runs as one process ([`Solo`]) or, built with the `mpi`
//! cargo feature and started by `mpirun`/`srun`, as R MPI ranks
//! (`Mpi`, on the `mpi` crate over the system's MPI library). Every rank
//! simulates its share of the environments; the trainer sums what the
//! ranks must agree on through the [`Comm`] trait: gradients after each
//! minibatch (the MPI Adam of DeepMimic, `xbpeng/DeepMimic`
//! `learning/solvers/mpi_solver.py`, and of OpenAI Baselines,
//! `openai/baselines` `baselines/common/mpi_adam.py`), the normalisers'
//! batch moments, advantage statistics, the approximate KL, the ATS records
//! and the iteration's metrics. With [`Solo`] every call is the identity, so
//! a one-process run computes exactly what it did before ranks existed.
//!
//! Determinism: a sum over ranks is `MPI_Allreduce` with `MPI_SUM`, whose
//! result Open MPI's algorithms give identically on every rank for a fixed
//! rank count and message size; the trainer checks it after every update
//! by comparing a hash of the weights across ranks
//! ([`Comm::check_identical`]).

use anyhow::{bail, Result};

/// What the ranks of a run exchange. Every method is collective: all ranks
/// call it in the same order with buffers of the same length.
pub trait Comm {
    /// This process's rank, `0..size`.
    fn rank(&self) -> usize;
    /// Number of ranks.
    fn size(&self) -> usize;
    /// Element-wise sum over ranks, in place; the same values on every rank.
    fn sum_f32(&self, buf: &mut [f32]) -> Result<()>;
    /// Element-wise sum over ranks, in place; the same values on every rank.
    fn sum_f64(&self, buf: &mut [f64]) -> Result<()>;
    /// Every rank's `bytes`, in rank order, on every rank.
    fn all_gather(&self, bytes: &[u8]) -> Result<Vec<Vec<u8>>>;
    /// Every rank's `bytes`, in rank order, on rank 0 (`None` elsewhere).
    fn gather(&self, bytes: &[u8]) -> Result<Option<Vec<Vec<u8>>>>;

    /// End the whole job after `err` on this rank, so that the other ranks
    /// do not wait for it in a collective: with several ranks, print the
    /// error with this rank's number and abort every rank (`MPI_Abort`).
    /// With one process, nothing: the caller reports the error.
    fn abort_on_error(&self, _err: &anyhow::Error) {}

    /// Whether this rank writes the run's outputs (rank 0).
    fn is_root(&self) -> bool {
        self.rank() == 0
    }

    /// Fail on every rank when `value` (a hash of the weights, say) is not
    /// the same on all of them; `what` names it in the error.
    fn check_identical(&self, value: u64, what: &str) -> Result<()> {
        if self.size() == 1 {
            return Ok(());
        }
        let all = self.all_gather(&value.to_le_bytes())?;
        let first = &all[0];
        if let Some(r) = all.iter().position(|v| v != first) {
            bail!(
                "{what} differ between rank 0 ({:016x}) and rank {r} ({:016x}) of {}",
                u64::from_le_bytes(first[..8].try_into()?),
                u64::from_le_bytes(all[r][..8].try_into()?),
                self.size()
            );
        }
        Ok(())
    }
}

/// One process: every collective is the identity.
#[derive(Clone, Copy, Debug, Default)]
pub struct Solo;

impl Comm for Solo {
    fn rank(&self) -> usize {
        0
    }
    fn size(&self) -> usize {
        1
    }
    fn sum_f32(&self, _: &mut [f32]) -> Result<()> {
        Ok(())
    }
    fn sum_f64(&self, _: &mut [f64]) -> Result<()> {
        Ok(())
    }
    fn all_gather(&self, bytes: &[u8]) -> Result<Vec<Vec<u8>>> {
        Ok(vec![bytes.to_vec()])
    }
    fn gather(&self, bytes: &[u8]) -> Result<Option<Vec<Vec<u8>>>> {
        Ok(Some(vec![bytes.to_vec()]))
    }
}

/// The number of processes a launcher announces in the environment (Open
/// MPI's `mpirun`: `OMPI_COMM_WORLD_SIZE`; PMI: `PMI_SIZE`; Slurm's `srun`:
/// `SLURM_STEP_NUM_TASKS`; MPICH's Hydra: `MPI_LOCALNRANKS`), or `None` for a
/// process started alone. Read without initialising MPI, so that a build
/// without the `mpi` feature can refuse a parallel launch.
pub fn launcher_size() -> Option<usize> {
    [
        "OMPI_COMM_WORLD_SIZE",
        "PMI_SIZE",
        "SLURM_STEP_NUM_TASKS",
        "MPI_LOCALNRANKS",
    ]
    .iter()
    .find_map(|k| std::env::var(k).ok()?.trim().parse::<usize>().ok())
}

/// A hash of the bit patterns of `values` (a fingerprint of the weights for
/// [`Comm::check_identical`]): std's `DefaultHasher` with its fixed keys,
/// the same on every rank of one binary.
pub fn fingerprint<'a>(values: impl IntoIterator<Item = &'a [f32]>) -> u64 {
    use std::hash::Hasher;
    let mut h = std::hash::DefaultHasher::new();
    for v in values {
        for x in v {
            h.write_u32(x.to_bits());
        }
    }
    h.finish()
}

/// The ranks of this process: MPI when a launcher started it and the `mpi`
/// feature is built, else one process ([`Solo`]).
///
/// # Errors
/// A launch as one of several processes by a build without the `mpi`
/// feature, or MPI that cannot be initialised.
pub fn world() -> Result<Box<dyn Comm>> {
    let launched = launcher_size();
    refuse_launch(launched, cfg!(feature = "mpi"))?;
    #[cfg(feature = "mpi")]
    if launched.is_some() {
        return Ok(Box::new(Mpi::init()?));
    }
    Ok(Box::new(Solo))
}

/// Refuse a launch as one of several processes (`launched`, from
/// [`launcher_size`]) by a build without MPI: each process
/// would train alone and all would write the same folder.
fn refuse_launch(launched: Option<usize>, built_with_mpi: bool) -> Result<()> {
    if let Some(n) = launched.filter(|n| *n > 1 && !built_with_mpi) {
        bail!(
            "train: started as one of {n} processes (mpirun or srun), but this skillaug was \
             built without MPI; build it with `cargo build --release --features mpi` \
             (README, \"Training on a cluster\") or start one process"
        );
    }
    Ok(())
}

#[cfg(feature = "mpi")]
pub use self::mpi_impl::Mpi;

#[cfg(feature = "mpi")]
mod mpi_impl {
    use super::Comm;
    use anyhow::{ensure, Context, Result};
    use mpi::collective::SystemOperation;
    use mpi::datatype::PartitionMut;
    use mpi::topology::SimpleCommunicator;
    use mpi::traits::*;
    use mpi::Count;

    /// The world communicator of an MPI job; MPI is finalised when it drops.
    pub struct Mpi {
        world: SimpleCommunicator,
        // kept for its Drop (MPI_Finalize), after `world`
        _universe: mpi::environment::Universe,
    }

    impl Mpi {
        /// Initialise MPI (once per process).
        pub fn init() -> Result<Mpi> {
            let universe = mpi::initialize()
                .context("MPI is already initialised in this process (one training per process)")?;
            let world = universe.world();
            Ok(Mpi {
                world,
                _universe: universe,
            })
        }

        /// Element-wise `MPI_SUM` over the ranks, in place.
        fn sum<T: Equivalence + Clone>(&self, buf: &mut [T]) -> Result<()> {
            if buf.is_empty() {
                return Ok(());
            }
            let send = buf.to_vec();
            self.world
                .all_reduce_into(&send[..], buf, SystemOperation::sum());
            Ok(())
        }

        fn counts(&self, len: usize) -> Result<(Vec<Count>, Vec<Count>)> {
            let n = self.world.size() as usize;
            let mut lens = vec![0u64; n];
            self.world.all_gather_into(&(len as u64), &mut lens[..]);
            let mut counts = Vec::with_capacity(n);
            let mut displs = Vec::with_capacity(n);
            let mut at: u64 = 0;
            for l in lens {
                ensure!(
                    at + l <= i32::MAX as u64,
                    "MPI gather: {} bytes in all exceed MPI's 2 GiB count",
                    at + l
                );
                counts.push(l as Count);
                displs.push(at as Count);
                at += l;
            }
            Ok((counts, displs))
        }
    }

    /// Each rank's message with its leading byte (see [`framed`]) dropped.
    fn split(buf: &[u8], counts: &[Count], displs: &[Count]) -> Vec<Vec<u8>> {
        counts
            .iter()
            .zip(displs)
            .map(|(&c, &d)| buf[d as usize + 1..(d + c) as usize].to_vec())
            .collect()
    }

    /// `bytes` behind one leading byte, so that no buffer handed to MPI is
    /// empty: an empty Rust slice's address is 0x1 for bytes, which Open
    /// MPI reads as `MPI_IN_PLACE` (seen as `MPI_ERR_ARG` in
    /// `MPI_Allgatherv`).
    fn framed(bytes: &[u8]) -> Vec<u8> {
        let mut v = Vec::with_capacity(bytes.len() + 1);
        v.push(0);
        v.extend_from_slice(bytes);
        v
    }

    impl Comm for Mpi {
        fn rank(&self) -> usize {
            self.world.rank() as usize
        }
        fn size(&self) -> usize {
            self.world.size() as usize
        }
        fn sum_f32(&self, buf: &mut [f32]) -> Result<()> {
            self.sum(buf)
        }
        fn sum_f64(&self, buf: &mut [f64]) -> Result<()> {
            self.sum(buf)
        }
        fn all_gather(&self, bytes: &[u8]) -> Result<Vec<Vec<u8>>> {
            let bytes = &framed(bytes)[..];
            let (counts, displs) = self.counts(bytes.len())?;
            let total = counts.iter().map(|&c| c as usize).sum();
            let mut buf = vec![0u8; total];
            {
                let mut part = PartitionMut::new(&mut buf[..], &counts[..], &displs[..]);
                self.world.all_gather_varcount_into(bytes, &mut part);
            }
            Ok(split(&buf, &counts, &displs))
        }
        fn abort_on_error(&self, err: &anyhow::Error) {
            use std::io::Write;
            if self.world.size() > 1 {
                // An error of the settings or the inputs is met by every
                // rank at once: rank 0 reports it and aborts, which ends the
                // others before their own reports (they wait 0.5 s); a rank
                // that fails alone reports after that wait.
                if self.world.rank() > 0 {
                    std::thread::sleep(std::time::Duration::from_millis(500));
                }
                let line = format!(
                    "error: rank {} of {}: {err:#}\n",
                    self.world.rank(),
                    self.world.size()
                );
                // one write, so that two ranks' lines do not interleave
                let _ = std::io::stderr().lock().write_all(line.as_bytes());
                self.world.abort(1)
            }
        }
        fn gather(&self, bytes: &[u8]) -> Result<Option<Vec<Vec<u8>>>> {
            let bytes = &framed(bytes)[..];
            let (counts, displs) = self.counts(bytes.len())?;
            let root = self.world.process_at_rank(0);
            if self.world.rank() == 0 {
                let total = counts.iter().map(|&c| c as usize).sum();
                let mut buf = vec![0u8; total];
                {
                    let mut part = PartitionMut::new(&mut buf[..], &counts[..], &displs[..]);
                    root.gather_varcount_into_root(bytes, &mut part);
                }
                Ok(Some(split(&buf, &counts, &displs)))
            } else {
                root.gather_varcount_into(bytes);
                Ok(None)
            }
        }
    }
}

/// [`Comm::gather`] of messages of any size: every rank's `bytes`, in rank
/// order, on rank 0 (`None` elsewhere), sent in as many rounds as it takes
/// to keep each round's total over the ranks within `max_round` bytes (an
/// MPI gather counts its bytes in an `i32`, 2 GiB in all: [`gather_large`]
/// passes 1 GiB). The ranks first share their lengths, so every rank takes
/// part in the same rounds even when the lengths differ.
///
/// # Errors
/// A collective that fails.
pub fn gather_in_rounds(
    comm: &dyn Comm,
    bytes: &[u8],
    max_round: usize,
) -> Result<Option<Vec<Vec<u8>>>> {
    let lens = comm.all_gather(&(bytes.len() as u64).to_le_bytes())?;
    let longest = lens
        .iter()
        .map(|b| u64::from_le_bytes(b[..8].try_into().expect("8 bytes")) as usize)
        .max()
        .unwrap_or(0);
    let piece = (max_round / comm.size().max(1)).max(1);
    let rounds = longest.div_ceil(piece).max(1);
    let mut out: Option<Vec<Vec<u8>>> = None;
    for k in 0..rounds {
        let part = &bytes[(k * piece).min(bytes.len())..((k + 1) * piece).min(bytes.len())];
        if let Some(got) = comm.gather(part)? {
            match &mut out {
                None => out = Some(got),
                Some(all) => {
                    for (a, g) in all.iter_mut().zip(got) {
                        a.extend(g);
                    }
                }
            }
        }
    }
    Ok(out)
}

/// [`gather_in_rounds`] with rounds of at most 1 GiB in all.
///
/// # Errors
/// A collective that fails.
pub fn gather_large(comm: &dyn Comm, bytes: &[u8]) -> Result<Option<Vec<Vec<u8>>>> {
    gather_in_rounds(comm, bytes, 1 << 30)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn large_gathers_go_in_rounds_and_arrive_whole() {
        let mine: Vec<u8> = (0..1000u32).map(|i| (i % 251) as u8).collect();
        // 64 bytes per round: 16 rounds, put back together in order
        assert_eq!(
            gather_in_rounds(&Solo, &mine, 64).unwrap(),
            Some(vec![mine.clone()])
        );
        assert_eq!(gather_large(&Solo, &mine).unwrap(), Some(vec![mine]));
        assert_eq!(gather_in_rounds(&Solo, &[], 8).unwrap(), Some(vec![vec![]]));
    }

    #[test]
    fn solo_collectives_are_the_identity() {
        let mut a = [1.5f32, -2.0];
        Solo.sum_f32(&mut a).unwrap();
        assert_eq!(a, [1.5, -2.0]);
        let mut b = [3.0f64];
        Solo.sum_f64(&mut b).unwrap();
        assert_eq!(b, [3.0]);
        assert_eq!(Solo.all_gather(b"xy").unwrap(), vec![b"xy".to_vec()]);
        assert_eq!(Solo.gather(b"z").unwrap(), Some(vec![b"z".to_vec()]));
        Solo.check_identical(7, "weights").unwrap();
    }

    #[test]
    fn the_fingerprint_sees_one_bit() {
        let a = [1.0f32, 2.0, 3.0];
        let mut b = a;
        b[2] = f32::from_bits(b[2].to_bits() ^ 1);
        assert_ne!(fingerprint([&a[..]]), fingerprint([&b[..]]));
        assert_eq!(fingerprint([&a[..]]), fingerprint([&a[..]]));
        // -0.0 and 0.0 compare equal but are different weights
        assert_ne!(fingerprint([&[0.0f32][..]]), fingerprint([&[-0.0f32][..]]));
    }

    #[test]
    fn a_parallel_launch_of_a_build_without_mpi_is_refused() {
        let e = refuse_launch(Some(4), false).unwrap_err().to_string();
        assert!(e.contains("one of 4 processes"), "{e}");
        assert!(e.contains("--features mpi"), "{e}");
        refuse_launch(Some(4), true).unwrap();
        refuse_launch(Some(1), false).unwrap();
        refuse_launch(None, false).unwrap();
    }
}
