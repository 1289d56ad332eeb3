use clap::Parser;

fn main() {
    keep_freed_memory();
    // a command-line error exits 1 like every other error (clap's own exit
    // code for it is 2); help and version exit 0
    let cli = skillaug::cli::Cli::try_parse().unwrap_or_else(|e| {
        let _ = e.print();
        std::process::exit(if e.use_stderr() { 1 } else { 0 })
    });
    if let Err(e) = skillaug::run(cli) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// Let glibc's allocator keep freed memory instead of handing it back to
/// the kernel. candle allocates a fresh buffer for every tensor it computes,
/// and the PPO update's buffers (a minibatch of activations: megabytes) were
/// mapped for each tensor and unmapped when it was freed, or trimmed off the
/// top of the heap, so every one was faulted in again page by page (measured
/// with `perf stat` on `skillaug bench train`: docs/training.md, "A learner
/// that keeps up"). Every allocation now comes from the heap (no mmap) and up
/// to 1 GiB of free heap is kept. Results do not depend on it.
fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; it is called before
    // any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
    }
}
