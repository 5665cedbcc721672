//! Fork safety. rayon's global thread pool does not survive `fork()`: its worker threads exist
//! only in the parent, so in a forked child (`os.fork`, `multiprocessing` with the "fork" start
//! method) any parallel work queued on it waits forever. The module remembers the process id it
//! was loaded in; in any other process (a forked child) every call runs on a fresh pool of its
//! own, which dies with the call.

use std::sync::OnceLock;

static MODULE_PID: OnceLock<u32> = OnceLock::new();

/// Records the process the module was loaded in (called once, at module initialisation).
pub fn remember_process() {
    MODULE_PID.get_or_init(std::process::id);
}

/// Whether this process is a fork of the one that loaded the module.
pub fn forked() -> bool {
    MODULE_PID
        .get()
        .is_some_and(|&pid| pid != std::process::id())
}

/// Runs `f` where its parallel work can run: directly (rayon's global pool) in the process that
/// loaded the module, on a fresh pool of `available_parallelism` workers in a forked child.
pub fn fork_safe<T: Send>(f: impl FnOnce() -> T + Send) -> Result<T, String> {
    if !forked() {
        return Ok(f());
    }
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map(|pool| pool.install(f))
        .map_err(|e| format!("cannot start worker threads in this (forked) process: {e}"))
}
