//! Guards for running the CLI in-process under fuzzing: a counting global
//! allocator that refuses, while a fuzz case runs, any single allocation
//! or live heap beyond what a small case could need, and a watchdog that
//! ends the process when a case runs too long.
//!
//! In-process, a refused allocation or a hang cannot be reported as a
//! proptest failure (Rust aborts on a failed allocation, and a running
//! call cannot be stopped), so both abort the test binary after writing
//! the running cases (arguments and the folder holding their input files,
//! which an abort leaves behind) to standard error. That is what a
//! subprocess under an address-space limit did per case, at a fraction of
//! the cost.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

/// A single allocation above this while a fuzz case runs is refused: the
/// cases are kept small (at most 2²⁵ pixels), so only a size taken from
/// unchecked input gets here.
pub const SINGLE_ALLOCATION_LIMIT: usize = 1 << 30;
/// Live heap of the whole test binary above this while a fuzz case runs is
/// refused (the same bound as the old per-process address-space limit).
pub const LIVE_HEAP_LIMIT: usize = 4 << 30;
/// Time a case may take; accepted cases take milliseconds, the largest a
/// few seconds, ten times that on a loaded machine at a low priority.
pub const TIME_LIMIT: Duration = Duration::from_secs(60);

/// The test binary's allocator: the system allocator, counting live bytes.
pub struct CountingAllocator;

static LIVE_BYTES: AtomicUsize = AtomicUsize::new(0);
/// How many fuzz cases are running (the limits apply only then).
static GUARDED: AtomicUsize = AtomicUsize::new(0);

/// A running case: an id, when it started, what it is.
struct Running {
    id: u64,
    started: Instant,
    description: String,
}

static RUNNING: Mutex<Vec<Running>> = Mutex::new(Vec::new());
static NEXT_ID: AtomicU64 = AtomicU64::new(0);

/// Writes `bytes` to file descriptor 2 without allocating.
fn write_stderr(bytes: &[u8]) {
    // SAFETY: writing a valid buffer to a file descriptor.
    unsafe {
        libc::write(2, bytes.as_ptr().cast(), bytes.len());
    }
}

/// Writes the running cases to standard error. `try_lock`: the allocator
/// may be called while this thread holds the lock.
fn write_running_cases() {
    if let Ok(running) = RUNNING.try_lock() {
        for case in running.iter() {
            write_stderr(b"fuzz case running: ");
            write_stderr(case.description.as_bytes());
            write_stderr(b"\n");
        }
    } else {
        write_stderr(b"(the running cases could not be listed)\n");
    }
}

/// Whether an allocation of `size` more bytes may go ahead.
fn admit(size: usize) -> bool {
    if GUARDED.load(Ordering::Relaxed) == 0 {
        return true;
    }
    let live = LIVE_BYTES.load(Ordering::Relaxed);
    if size <= SINGLE_ALLOCATION_LIMIT && live.saturating_add(size) <= LIVE_HEAP_LIMIT {
        return true;
    }
    write_stderr(b"fuzz guard: refused an allocation beyond the per-case limits (1 GiB at once, 4 GiB live)\n");
    write_running_cases();
    false
}

// SAFETY: every call forwards to the system allocator with the same
// layout; the counters only observe.
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if !admit(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: the caller's layout, forwarded.
        let pointer = unsafe { System.alloc(layout) };
        if !pointer.is_null() {
            LIVE_BYTES.fetch_add(layout.size(), Ordering::Relaxed);
        }
        pointer
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if !admit(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: the caller's layout, forwarded.
        let pointer = unsafe { System.alloc_zeroed(layout) };
        if !pointer.is_null() {
            LIVE_BYTES.fetch_add(layout.size(), Ordering::Relaxed);
        }
        pointer
    }

    unsafe fn dealloc(&self, pointer: *mut u8, layout: Layout) {
        // SAFETY: the caller's pointer and layout, forwarded.
        unsafe { System.dealloc(pointer, layout) };
        LIVE_BYTES.fetch_sub(layout.size(), Ordering::Relaxed);
    }

    unsafe fn realloc(&self, pointer: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if new_size > layout.size() && !admit(new_size) {
            return std::ptr::null_mut();
        }
        // SAFETY: the caller's pointer, layout and size, forwarded.
        let moved = unsafe { System.realloc(pointer, layout, new_size) };
        if !moved.is_null() {
            LIVE_BYTES.fetch_sub(layout.size(), Ordering::Relaxed);
            LIVE_BYTES.fetch_add(new_size, Ordering::Relaxed);
        }
        moved
    }
}

/// Ends the process when a case has run longer than [`TIME_LIMIT`]; started
/// once, by the first case.
fn start_watchdog() {
    static WATCHDOG: OnceLock<()> = OnceLock::new();
    WATCHDOG.get_or_init(|| {
        std::thread::Builder::new()
            .name("fuzz watchdog".into())
            .spawn(|| {
                loop {
                    std::thread::sleep(Duration::from_millis(250));
                    let running = RUNNING.lock().unwrap_or_else(|e| e.into_inner());
                    if let Some(stuck) = running.iter().find(|c| c.started.elapsed() > TIME_LIMIT) {
                        eprintln!(
                            "fuzz guard: a case took over {TIME_LIMIT:?}: {}",
                            stuck.description
                        );
                        std::process::abort();
                    }
                }
            })
            .expect("start the fuzz watchdog");
    });
}

/// A fuzz case under the guards, from creation until dropped.
pub struct Case {
    id: u64,
}

impl Case {
    /// Starts guarding a case; `description` is written out if the case
    /// is refused memory or runs too long.
    pub fn enter(description: String) -> Case {
        start_watchdog();
        let id = NEXT_ID.fetch_add(1, Ordering::Relaxed);
        RUNNING
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(Running {
                id,
                started: Instant::now(),
                description,
            });
        GUARDED.fetch_add(1, Ordering::SeqCst);
        Case { id }
    }
}

impl Drop for Case {
    fn drop(&mut self) {
        GUARDED.fetch_sub(1, Ordering::SeqCst);
        RUNNING
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .retain(|c| c.id != self.id);
    }
}
