//! Memory budget: what a computation will need, what the machine can give, and fallible buffers.
//!
//! Running out of memory inside Rust aborts the process, so every large computation first
//! estimates its peak memory from the problem's size and refuses with [`Error::Memory`] when the
//! estimate exceeds the limit: the caller's `max_memory`, or by default [`DEFAULT_FRACTION`] of
//! what the machine has available ([`available`]). The big buffers are then allocated with
//! [`try_filled`], which reports a failed allocation as the same error instead of aborting.
//!
//! The estimate of a reconstruction's peak memory is beside its options
//! ([`crate::options::check_memory`]); this module is the ground floor below every other one:
//! the limit, the probe and the fallible buffers.

use crate::error::{Error, Result};

/// Share of the available memory a computation may use when no limit is given.
pub const DEFAULT_FRACTION: f64 = crate::error::DEFAULT_MEMORY_FRACTION;

/// Bytes of memory this process can still use: the least of the system's available memory
/// (`MemAvailable`), the free part of the cgroup's limit, and the free part of the address-space
/// limit (`RLIMIT_AS`, measured against the current `VmSize`). `None` where none of them can be
/// read (systems other than Linux).
pub fn available() -> Option<u64> {
    let mut best: Option<u64> = None;
    let mut take = |v: Option<u64>| {
        if let Some(v) = v {
            best = Some(best.map_or(v, |b| b.min(v)));
        }
    };
    take(meminfo_available());
    take(cgroup_free());
    take(address_space_free());
    best
}

/// The limit in bytes that applies: `max_memory` when given, else [`DEFAULT_FRACTION`] of
/// [`available`]; `None` means no limit is known.
pub fn limit(max_memory: Option<f64>) -> Option<f64> {
    match max_memory {
        Some(m) => Some(m),
        None => available().map(|a| a as f64 * DEFAULT_FRACTION),
    }
}

/// Refuses with [`Error::Memory`] when `needed` bytes exceed the limit of `max_memory` (see
/// [`limit`]); `what` describes the computation for the message.
///
/// Within the limit (whatever `max_memory` says, even when it is infinite) the estimate is then
/// [`probe`]d: a process that cannot get `needed` bytes now (an address-space limit, or more
/// than the kernel grants) is refused with [`Error::Memory`] too, before any large buffer.
pub fn check(what: impl FnOnce() -> String, needed: f64, max_memory: Option<f64>) -> Result<()> {
    match limit(max_memory) {
        Some(limit) if needed > limit => Err(Error::Memory {
            what: what(),
            needed,
            limit,
            explicit: max_memory.is_some(),
        }),
        _ => probe(what, needed),
    }
}

/// A vector of `len` copies of `value`, or [`Error::Memory`] when the allocation fails (instead
/// of aborting the process).
pub fn try_filled<T: Clone>(len: usize, value: T, what: &str) -> Result<Vec<T>> {
    let mut v = try_with_capacity(len, what)?;
    v.resize(len, value);
    Ok(v)
}

/// Values whose bytes all zero are a valid value (zero), which [`try_zeros`] hands out.
///
/// # Safety
///
/// Only for types of which the all-zero byte pattern is a valid value.
pub(crate) unsafe trait Zeroable: Clone {
    /// The zero value.
    const ZERO: Self;
}
// SAFETY: zero bytes are 0, 0.0 and arrays of 0.0.
unsafe impl Zeroable for u8 {
    const ZERO: Self = 0;
}
// SAFETY: as above.
unsafe impl Zeroable for f64 {
    const ZERO: Self = 0.0;
}
// SAFETY: as above.
unsafe impl Zeroable for [f64; 4] {
    const ZERO: Self = [0.0; 4];
}
// SAFETY: as above.
unsafe impl Zeroable for [f64; 3] {
    const ZERO: Self = [0.0; 3];
}
// SAFETY: zero bytes are 0.
unsafe impl Zeroable for u32 {
    const ZERO: Self = 0;
}
// SAFETY: zero bytes are 0.0.
unsafe impl Zeroable for f32 {
    const ZERO: Self = 0.0;
}

/// `len` zeros, or [`Error::Memory`], allocated zeroed instead of filled: the operating system
/// hands out zero pages as they are first touched, so a large buffer is not written serially
/// before the (parallel) code that fills it does.
pub(crate) fn try_zeros<T: Zeroable>(len: usize, what: &str) -> Result<Vec<T>> {
    let Ok(layout) = std::alloc::Layout::array::<T>(len) else {
        return try_vec(len, T::ZERO, what);
    };
    if layout.size() == 0 {
        return try_vec(len, T::ZERO, what);
    }
    // SAFETY: the layout has a non-zero size; the memory comes from the global allocator with
    // `T`'s layout for `len` values, which are valid zeros (`Zeroable`), so it is a vector of
    // length and capacity `len`.
    unsafe {
        let data = std::alloc::alloc_zeroed(layout).cast::<T>();
        if data.is_null() {
            // Out of memory: the fallible path reports it.
            return try_vec(len, T::ZERO, what);
        }
        Ok(Vec::from_raw_parts(data, len, len))
    }
}

/// `len` triples on the memory of `spare`, a buffer of quadruples no longer needed, when it
/// holds at least `3 len` values (else [`try_zeros`]): for a map whose every entry is written
/// before it is read, which then lands on pages already touched instead of fresh ones (the
/// kernel zeroes each fresh page as it is first touched: 70 k page faults for the normal map
/// of 12 MP). The entries hold `spare`'s old bits (or zeros) until written. `spare`'s
/// allocation is shrunk to the triples' size (in place: glibc gives the tail's pages back).
pub(crate) fn triples_on(spare: Vec<[f64; 4]>, len: usize, what: &str) -> Result<Vec<[f64; 3]>> {
    let mut flat = spare.into_flattened();
    let values = len.saturating_mul(3);
    if len == 0 || values > flat.capacity() {
        drop(flat);
        return try_zeros(len, what);
    }
    // (within the capacity: truncates, or writes zeros after the old values)
    flat.resize(values, 0.0);
    flat.shrink_to_fit();
    if flat.capacity() != values {
        drop(flat);
        return try_zeros(len, what);
    }
    let mut flat = std::mem::ManuallyDrop::new(flat);
    // SAFETY: `flat` owns an allocation of exactly `3 len` f64 from the global allocator (its
    // length and capacity), whose layout (`24 len` bytes, aligned as f64) is that of `len`
    // `[f64; 3]`; every bit pattern is a valid f64. `flat` is not dropped, so the new vector
    // is the allocation's only owner.
    Ok(unsafe { Vec::from_raw_parts(flat.as_mut_ptr().cast::<[f64; 3]>(), len, len) })
}

/// `len` quadruples on the memory of `values`, a buffer that was a vector of quadruples (made
/// flat by `Vec::into_flattened`, e.g. to be lent, see
/// [`MultigridSystem::lend`](crate::multigrid::MultigridSystem::lend)): None when its capacity
/// is not a multiple of 4 or holds fewer than `4 len` values. The quadruples hold the buffer's
/// values, or zeros past them; no allocation.
pub(crate) fn quads_on(mut values: Vec<f64>, len: usize) -> Option<Vec<[f64; 4]>> {
    let capacity = values.capacity();
    if !capacity.is_multiple_of(4) || len.checked_mul(4)? > capacity {
        return None;
    }
    // (within the capacity: truncates, or writes zeros after the old values)
    values.resize(4 * len, 0.0);
    debug_assert_eq!(values.capacity(), capacity);
    let mut values = std::mem::ManuallyDrop::new(values);
    // SAFETY: `values` owns an allocation of `capacity` f64 from the global allocator, whose
    // layout (`8 capacity` bytes, aligned as f64) is that of `capacity / 4` `[f64; 4]`; its
    // first `4 len` values are initialised, and every bit pattern is a valid f64. `values` is
    // not dropped, so the new vector is the allocation's only owner.
    Some(unsafe { Vec::from_raw_parts(values.as_mut_ptr().cast::<[f64; 4]>(), len, capacity / 4) })
}

/// `len` values on the memory of one of the `spare` buffers (no longer needed: the first
/// whose capacity holds `len`, taken out of `spare` and shrunk to `len`), else [`try_zeros`]:
/// as [`triples_on`], for a map whose every entry is written before it is read (the entries
/// hold the buffer's old values, or zeros, until then).
pub(crate) fn values_on(spare: &mut Vec<Vec<f64>>, len: usize, what: &str) -> Result<Vec<f64>> {
    let Some(i) = spare.iter().position(|v| len > 0 && v.capacity() >= len) else {
        return try_zeros(len, what);
    };
    let mut values = spare.remove(i);
    // (within the capacity: truncates, or writes zeros after the old values)
    values.resize(len, 0.0);
    values.shrink_to_fit();
    Ok(values)
}

/// Buffers of a stage that are no longer needed, for maps written whole after it (see
/// [`triples_on`] and [`values_on`]).
#[derive(Default)]
pub(crate) struct Spare {
    /// One quadruple a facet (the solver's targets).
    pub quads: Vec<[f64; 4]>,
    /// Vectors of values (the global step's work vectors).
    pub values: Vec<Vec<f64>>,
}

/// [`try_filled`] under the short name the modules use for their O(pixels) buffers.
pub(crate) fn try_vec<T: Clone>(len: usize, value: T, what: &str) -> Result<Vec<T>> {
    try_filled(len, value, what)
}

/// As [`try_vec`], written by the worker threads in parallel: a large buffer's first touch
/// (the kernel zeroing each fresh page) and its fill are split over the cores instead of
/// running on the calling thread alone. The same values.
pub(crate) fn try_par_vec<T: Clone + Send + Sync>(
    len: usize,
    value: T,
    what: &str,
) -> Result<Vec<T>> {
    use rayon::prelude::*;
    try_par_collect((0..len).into_par_iter().map(|_| value.clone()), what)
}

/// An empty vector with room for exactly `len` values, or [`Error::Memory`].
pub(crate) fn try_with_capacity<T>(len: usize, what: &str) -> Result<Vec<T>> {
    let mut v = Vec::new();
    v.try_reserve_exact(len)
        .map_err(|_| allocation_failed(what, len as f64 * std::mem::size_of::<T>() as f64))?;
    Ok(v)
}

/// The values of an exact-size iterator in a vector allocated fallibly (the reservation is
/// exact, so collecting does not reallocate).
pub(crate) fn try_collect<I>(iter: I, what: &str) -> Result<Vec<I::Item>>
where
    I: ExactSizeIterator,
{
    let mut v = try_with_capacity(iter.len(), what)?;
    v.extend(iter);
    Ok(v)
}

/// The values of an indexed parallel iterator in a vector allocated fallibly (rayon's
/// `collect_into_vec` then finds the room reserved).
pub(crate) fn try_par_collect<I>(iter: I, what: &str) -> Result<Vec<I::Item>>
where
    I: rayon::iter::IndexedParallelIterator,
{
    let mut v = try_with_capacity(iter.len(), what)?;
    iter.collect_into_vec(&mut v);
    Ok(v)
}

/// A copy of `values` allocated fallibly.
pub(crate) fn try_copy<T: Clone>(values: &[T], what: &str) -> Result<Vec<T>> {
    let mut v = try_with_capacity(values.len(), what)?;
    v.extend_from_slice(values);
    Ok(v)
}

/// The error of a failed allocation of `bytes` for `what`.
pub(crate) fn allocation_failed(what: &str, bytes: f64) -> Error {
    Error::Memory {
        what: what.to_string(),
        needed: bytes,
        limit: f64::NAN,
        explicit: false,
    }
}

/// Asks the allocator for `bytes` at once and gives them back: fails with [`Error::Memory`]
/// when the process cannot get that much memory now (its address-space limit, or an
/// allocation above what the kernel's overcommit heuristic grants). Large allocations are
/// mapped lazily and unmapped on release, so the probe touches no page. It is a guard before a
/// computation whose estimated peak is `bytes`, so that exhaustion is reported before the
/// first large buffer rather than part-way (where a small allocation could abort); under an
/// overcommitting kernel without limits it cannot see the physical memory.
pub(crate) fn probe(what: impl FnOnce() -> String, bytes: f64) -> Result<()> {
    let fail = |what: String| Error::Memory {
        what,
        needed: bytes,
        limit: f64::NAN,
        explicit: false,
    };
    if bytes.is_nan() || bytes >= isize::MAX as f64 {
        return Err(fail(what()));
    }
    let mut v: Vec<u8> = Vec::new();
    match v.try_reserve_exact(bytes.max(0.0) as usize) {
        Ok(()) => Ok(()),
        Err(_) => Err(fail(what())),
    }
}

/// A `key: value kB` field of a /proc file, in bytes.
fn proc_field(path: &str, key: &str) -> Option<u64> {
    let text = std::fs::read_to_string(path).ok()?;
    let line = text.lines().find(|l| l.starts_with(key))?;
    let kb: u64 = line[key.len()..]
        .trim_start_matches(':')
        .split_whitespace()
        .next()?
        .parse()
        .ok()?;
    kb.checked_mul(1024)
}

fn meminfo_available() -> Option<u64> {
    proc_field("/proc/meminfo", "MemAvailable")
}

/// `memory.max - memory.current` of this process's cgroup (v2), when a limit is set.
fn cgroup_free() -> Option<u64> {
    let cgroups = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    let path = cgroups.lines().find_map(|l| l.strip_prefix("0::"))?;
    let dir = format!("/sys/fs/cgroup{}", path.trim_end_matches('/'));
    let read = |name: &str| std::fs::read_to_string(format!("{dir}/{name}")).ok();
    let max: u64 = read("memory.max")?.trim().parse().ok()?; // "max" (no limit) fails to parse
    let current: u64 = read("memory.current")?.trim().parse().ok()?;
    Some(max.saturating_sub(current))
}

/// Gives the free memory of the allocator's arenas back to the system (glibc's `malloc_trim`;
/// nothing elsewhere). Buffers below glibc's mmap threshold (which grows to 32 MB) come from
/// its arenas and, once freed, stay resident there unless they are at an arena's top: the
/// buffers of a pyramid's coarse levels (a quarter of the pixels and less) otherwise stay in
/// the resident memory through the full-resolution level (about 15 bytes a pixel at 4 MP).
pub(crate) fn give_back() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only reorganizes the allocator's free memory.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Diagnostic: with `NPLPS_MEMTRACE` set in the environment, prints to stderr `label`, the
/// resident memory now and its peak since the last trace (Linux: `VmRSS`, `VmHWM`; the peak is
/// reset after reading it through `/proc/self/clear_refs`), in MiB. Nothing otherwise.
#[doc(hidden)]
pub fn trace(label: &str) {
    use std::sync::OnceLock;
    static ON: OnceLock<Option<std::time::Instant>> = OnceLock::new();
    let Some(start) =
        ON.get_or_init(|| std::env::var_os("NPLPS_MEMTRACE").map(|_| std::time::Instant::now()))
    else {
        return;
    };
    let mib = |key| proc_field("/proc/self/status", key).map_or(f64::NAN, |b| b as f64 / 1048576.0);
    let (rss, hwm) = (mib("VmRSS"), mib("VmHWM"));
    let _ = std::fs::write("/proc/self/clear_refs", "5");
    // Minor page faults so far (field 10 of /proc/self/stat): fresh pages touched; the
    // process's user and system time (fields 14 and 15, in clock ticks of 1/100 s on Linux).
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let field = |n: usize| -> u64 {
        stat.rfind(')')
            .and_then(|at| stat.get(at + 2..))
            .and_then(|rest| rest.split_whitespace().nth(n)?.parse::<u64>().ok())
            .unwrap_or(0)
    };
    let (faults, cpu) = (field(7), (field(11) + field(12)) as f64 / 100.0);
    eprintln!(
        "memtrace {:8.3}s cpu {cpu:8.2}s rss {rss:8.1} peak-since-last {hwm:8.1} MiB faults \
         {faults:9}  {label}",
        start.elapsed().as_secs_f64()
    );
}

/// `RLIMIT_AS - VmSize` when an address-space limit is set.
#[cfg(unix)]
fn address_space_free() -> Option<u64> {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit only writes the struct we pass.
    if unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut limit) } != 0
        || limit.rlim_cur == libc::RLIM_INFINITY
    {
        return None;
    }
    let used = proc_field("/proc/self/status", "VmSize")?;
    Some(limit.rlim_cur.saturating_sub(used))
}

#[cfg(not(unix))]
fn address_space_free() -> Option<u64> {
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::format_bytes;

    /// Quadruples made flat and back keep their allocation and values; a buffer whose capacity
    /// is not a multiple of 4 or too small is refused.
    #[test]
    fn quads_come_back_on_their_memory() {
        let quads: Vec<[f64; 4]> = (0..10).map(|i| [i as f64, 1.0, 2.0, -0.0]).collect();
        let flat = quads.clone().into_flattened();
        let flat_at = flat.as_ptr() as usize;
        let back = quads_on(flat, 10).unwrap();
        assert_eq!(back.as_ptr() as usize, flat_at);
        assert!(back
            .iter()
            .zip(&quads)
            .all(|(a, b)| a.map(f64::to_bits) == b.map(f64::to_bits)));
        let shorter = quads_on(quads.clone().into_flattened(), 4).unwrap();
        assert_eq!((shorter.len(), shorter.capacity()), (4, 10));
        assert!(quads_on(quads.clone().into_flattened(), 11).is_none());
        assert!(quads_on(Vec::with_capacity(7), 1).is_none());
    }

    /// Zeroed allocations are vectors of zeros of the asked length, empty ones included.
    #[test]
    fn zeroed_vectors_hold_zeros() {
        assert_eq!(try_zeros::<f64>(1 << 20, "x").unwrap(), vec![0.0; 1 << 20]);
        assert_eq!(try_zeros::<[f64; 4]>(3, "x").unwrap(), vec![[0.0; 4]; 3]);
        assert!(try_zeros::<u8>(0, "x").unwrap().is_empty());
        let mut v = try_zeros::<f64>(10, "x").unwrap();
        v.push(1.0);
        assert_eq!(v.len(), 11);
    }

    /// The triples land on the spare buffer when it is large enough (its first values kept,
    /// the allocation shrunk to the triples), on fresh zeros otherwise; empty ones included.
    #[test]
    fn triples_reuse_a_large_enough_spare_buffer() {
        for (quads, len) in [(12, 16), (12, 9), (12, 1), (1 << 16, 87_381), (7, 5)] {
            let spare: Vec<[f64; 4]> = (0..quads).map(|i| [i as f64; 4]).collect();
            let at = spare.as_ptr() as usize;
            let t = triples_on(spare, len, "x").unwrap();
            assert_eq!((t.len(), t.capacity()), (len, len));
            assert_eq!(t.as_ptr() as usize, at, "{quads} {len}");
            let flat: Vec<f64> = t.iter().flatten().copied().collect();
            for (j, &v) in flat.iter().enumerate() {
                let old = if j < 4 * quads { (j / 4) as f64 } else { 0.0 };
                assert_eq!(v, old, "{quads} {len} {j}");
            }
            // (dropped with the triples' layout)
            drop(t);
        }
        for (quads, len) in [(12, 17), (0, 3), (5, 100)] {
            let spare = vec![[1.0f64; 4]; quads];
            let t = triples_on(spare, len, "x").unwrap();
            assert_eq!(t, vec![[0.0; 3]; len]);
        }
        assert!(triples_on(vec![[1.0; 4]; 4], 0, "x").unwrap().is_empty());
        let mut t = triples_on(vec![[2.0; 4]; 3], 4, "x").unwrap();
        t.push([3.0; 3]);
        assert_eq!(t.len(), 5);
    }

    /// Values land on the first spare buffer large enough (its first values kept, shrunk to
    /// the length), on fresh zeros when none is; each spare buffer is used once.
    #[test]
    fn values_reuse_the_first_large_enough_spare_buffer() {
        let mut spare = vec![
            vec![1.0; 5],
            vec![2.0; 40],
            Vec::with_capacity(30),
            vec![3.0; 30],
        ];
        let at = spare[1].as_ptr() as usize;
        let v = values_on(&mut spare, 20, "x").unwrap();
        assert_eq!((v.as_ptr() as usize, v.len(), v.capacity()), (at, 20, 20));
        assert_eq!(v, vec![2.0; 20]);
        assert_eq!(spare.len(), 3);
        let w = values_on(&mut spare, 25, "x").unwrap();
        assert_eq!(
            w,
            vec![0.0; 25],
            "the empty buffer with room for 30, zeros written"
        );
        let x = values_on(&mut spare, 30, "x").unwrap();
        assert_eq!(x, vec![3.0; 30]);
        let y = values_on(&mut spare, 6, "x").unwrap();
        assert_eq!(y, vec![0.0; 6], "no spare buffer holds 6: fresh zeros");
        assert_eq!(spare, vec![vec![1.0; 5]]);
        assert!(values_on(&mut spare, 0, "x").unwrap().is_empty());
        assert_eq!(spare.len(), 1);
    }

    #[test]
    fn a_limit_below_the_estimate_is_refused_with_both_numbers() {
        let err = check(|| "rendering".into(), 3e9, Some(1e9)).unwrap_err();
        let text = err.to_string();
        assert!(text.contains("rendering"), "{text}");
        assert!(
            text.contains("3.00 GB") && text.contains("1.00 GB"),
            "{text}"
        );
        assert!(text.contains("max_memory"), "{text}");
        assert!(check(|| "x".into(), 1e6, Some(1e9)).is_ok());
    }

    #[test]
    fn available_memory_is_known_on_linux() {
        if cfg!(target_os = "linux") {
            let a = available().expect("MemAvailable");
            assert!(a > 0);
        }
    }

    #[test]
    fn failed_allocations_are_errors() {
        let err = try_filled(usize::MAX / 2, 0u64, "a huge buffer").unwrap_err();
        assert!(matches!(err, Error::Memory { .. }));
        assert_eq!(try_filled(3, 1u8, "small").unwrap(), vec![1, 1, 1]);
    }

    #[test]
    fn bytes_print_with_three_digits() {
        assert_eq!(format_bytes(512.0), "512 B");
        assert_eq!(format_bytes(1.25e9), "1.25 GB");
        assert_eq!(format_bytes(45.6e6), "45.6 MB");
        assert_eq!(format_bytes(f64::NAN), "unknown");
    }
}
