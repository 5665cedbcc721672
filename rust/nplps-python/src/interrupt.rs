//! Ctrl-C during a long computation.
//!
//! Python runs signal handlers only on its main thread, and only when that thread runs Python
//! code. A computation that keeps the calling thread busy in Rust therefore delays Ctrl-C until
//! it returns. [`interruptible`] instead runs the computation on a helper thread while the
//! calling thread waits without the GIL and checks for signals every [`POLL`]; on a signal it
//! cancels the computation's [`nplps::Cancel`] token (checked every few facets and at every
//! conjugate-gradient iteration, see `nplps::cancel`) and raises the signal's exception
//! (`KeyboardInterrupt`) once the computation has stopped.

use std::sync::mpsc::{channel, RecvTimeoutError};
use std::time::Duration;

use pyo3::prelude::*;

use crate::errors::to_py;

/// How often the waiting thread checks for signals.
const POLL: Duration = Duration::from_millis(20);

/// Stack of the helper thread (the size of a main thread's on Linux).
const STACK: usize = 8 << 20;

/// Runs `work` on a helper thread, cancelling `cancel` when a signal handler raises (see the
/// module documentation). Errors of `work` are converted with [`to_py`]; a signal's exception
/// takes precedence over the result.
pub fn interruptible<T: Send>(
    py: Python<'_>,
    cancel: &nplps::Cancel,
    work: impl FnOnce() -> nplps::Result<T> + Send,
) -> PyResult<T> {
    let mut signal: Option<PyErr> = None;
    let result = py.detach(|| {
        std::thread::scope(|scope| {
            let (done, finished) = channel::<()>();
            let task = move || {
                let out = work();
                let _ = done.send(());
                out
            };
            let handle = match std::thread::Builder::new()
                .name("nplps".into())
                .stack_size(STACK)
                .spawn_scoped(scope, task)
            {
                Ok(handle) => handle,
                // No thread to spare (a process limit on threads).
                Err(_) => {
                    return Err(nplps::Error::Solver(
                        "cannot start a worker thread (is the process at its thread limit?)"
                            .to_string(),
                    ))
                }
            };
            loop {
                match finished.recv_timeout(POLL) {
                    Ok(()) | Err(RecvTimeoutError::Disconnected) => break,
                    Err(RecvTimeoutError::Timeout) if signal.is_none() => {
                        if let Err(e) = Python::attach(|py| py.check_signals()) {
                            signal = Some(e);
                            cancel.cancel();
                        }
                    }
                    Err(RecvTimeoutError::Timeout) => {}
                }
            }
            handle.join().unwrap_or_else(|_| {
                Err(nplps::Error::Solver(
                    "internal error (please report it): the worker thread panicked".to_string(),
                ))
            })
        })
    });
    if let Some(e) = signal {
        return Err(e);
    }
    result.map_err(to_py)
}
