//! The worker threads of a run: a rayon pool of the requested size and faer's parallelism.

use faer::Par;

use crate::error::{Error, Result};

/// Runs `f` on a rayon pool of `threads` workers (0: the global pool).
pub(crate) fn with_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> Result<T> {
    if threads == 0 {
        return Ok(f());
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Error::Unusable(format!("cannot start {threads} worker threads: {e}")))?;
    Ok(pool.install(f))
}

/// faer parallelism: sequential, or the current rayon pool when `parallel` is set.
pub(crate) fn sparse_par(parallel: bool) -> Par {
    match rayon::current_num_threads() {
        n if parallel && n > 1 => Par::rayon(n),
        _ => Par::Seq,
    }
}
