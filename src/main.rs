mod cli;

fn main() {
    keep_freed_memory();
    std::process::exit(cli::main());
}

/// Lets glibc's malloc keep freed memory for reuse instead of handing it back to the kernel.
///
/// Training allocates and frees the same large buffers every iteration (activated surfels,
/// projected splats, per-(tile, surfel) gradient slots: tens to hundreds of MB on a room).
/// glibc serves every block over 32 MB with a fresh `mmap` and trims its heap top on free, so
/// each iteration faulted its buffers in again, page by zeroed page. On the kitchen preset
/// (0.80 M surfels, 320x240, `reconstruct --iterations 400`, `/usr/bin/time -v`): 31.8 M minor
/// faults and 51.5 s of system time in 384 s; with big blocks taken from the heap and the heap
/// not trimmed, 0.70 M faults, 6.2 s of system time, 358 s wall (training 236 s -> 210 s), and
/// identical results. (jemalloc, tried as the global allocator, made it worse: 57.9 M faults,
/// 418 s.) The price is memory the heap keeps: re-measured once the checkpoint was streamed and
/// the gradients no longer copied, 1.32 GB peak RSS against glibc's default 0.87 GB (0.52 M
/// against 55.7 M faults, 6.8 s against 108.5 s of system time, 338 s against 432 s), below
/// the 1.36 GB the stage peaked at before either change. A user who sets glibc's own malloc
/// variables keeps them.
fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let user_set = [
            "GLIBC_TUNABLES",
            "MALLOC_MMAP_MAX_",
            "MALLOC_TRIM_THRESHOLD_",
        ]
        .iter()
        .any(|v| std::env::var_os(v).is_some());
        if !user_set {
            // SAFETY: mallopt only sets malloc's parameters; called before any thread starts.
            unsafe {
                libc::mallopt(libc::M_MMAP_MAX, 0);
                libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
            }
        }
    }
}
