fn main() {
    keep_freed_memory();
    std::process::exit(lightfuse::cli::main());
}

/// Lets glibc's malloc keep freed memory for reuse instead of handing it back to the kernel.
///
/// Training allocates and frees the same large buffers every iteration (activated surfels,
/// projected splats, per-(tile, surfel) gradient slots: tens to hundreds of MB on a room).
/// glibc serves every block over 32 MB with a fresh `mmap` and trims its heap top on free, so
/// each iteration faulted its buffers in again, page by zeroed page. On the kitchen preset
/// (0.80 M surfels, 320x240, `reconstruct --iterations 400`, `/usr/bin/time -v`): 31.8 M minor
/// faults and 51.5 s of system time in 384 s; with big blocks taken from the heap and the heap
/// not trimmed, 0.70 M faults, 6.2 s of system time, 358 s wall (training 236 s -> 210 s), for
/// a peak RSS of 1.56 GB instead of 1.36 GB, and identical results. (jemalloc, tried as the
/// global allocator, made it worse: 57.9 M faults, 418 s.) A user who sets glibc's own malloc
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
