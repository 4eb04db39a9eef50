//! The process allocator of the `paraformer` command and the Python module (feature
//! `mimalloc`): mimalloc by default, the system allocator with `PARAFORMER_ALLOCATOR=system`.
//!
//! glibc serves the matcher's large buffers (the 2049 × 2049 couplings, the attention's
//! packed operands) with `mmap` and hands them back to the kernel when freed, so every call
//! faults them in again; mimalloc keeps freed pages for reuse. Rust programs choose their own
//! allocator and can install this one: `#[global_allocator] static A: ProcessAllocator =
//! ProcessAllocator;`.

use std::alloc::{GlobalAlloc, Layout, System};
use std::ffi::CStr;
use std::sync::atomic::{AtomicU8, Ordering};

use mimalloc::MiMalloc;

/// The environment variable that selects the allocator: `mimalloc` (the default) or `system`.
pub const ENV: &str = "PARAFORMER_ALLOCATOR";

const UNSET: u8 = 0;
const MIMALLOC: u8 = 1;
const SYSTEM: u8 = 2;
static CHOICE: AtomicU8 = AtomicU8::new(UNSET);

/// A global allocator that is mimalloc or the system's, chosen once per process from
/// [`ENV`] at the first allocation, so every block is freed by the allocator that made it.
pub struct ProcessAllocator;

/// The value of [`ENV`] read without allocating (this runs inside the allocator).
fn env_value() -> Option<&'static [u8]> {
    // SAFETY: a NUL-terminated name; getenv returns null or a NUL-terminated string that
    // stays valid while the environment is not modified, and it is only read here.
    unsafe {
        let p = libc::getenv(c"PARAFORMER_ALLOCATOR".as_ptr());
        (!p.is_null()).then(|| CStr::from_ptr(p).to_bytes())
    }
}

fn choice() -> u8 {
    let c = CHOICE.load(Ordering::Relaxed);
    if c != UNSET {
        return c;
    }
    let want = if env_value() == Some(b"system") { SYSTEM } else { MIMALLOC };
    // The first caller decides; a racing caller takes its decision.
    match CHOICE.compare_exchange(UNSET, want, Ordering::AcqRel, Ordering::Acquire) {
        Ok(_) => want,
        Err(decided) => decided,
    }
}

/// The allocator this process uses: `"mimalloc"` or `"system"` (deciding it if no
/// allocation has yet).
pub fn name() -> &'static str {
    if choice() == SYSTEM {
        "system"
    } else {
        "mimalloc"
    }
}

/// An error naming [`ENV`] when it is set to anything but `mimalloc` or `system` (the
/// allocator itself cannot report it: it treats such a value as the default).
pub fn check_env() -> crate::Result<()> {
    match std::env::var_os(ENV) {
        None => Ok(()),
        Some(v) if v == "mimalloc" || v == "system" => Ok(()),
        Some(v) => Err(crate::Error::InvalidInput {
            argument: ENV.into(),
            reason: format!("{v:?}: expected \"mimalloc\" or \"system\""),
        }),
    }
}

// SAFETY: every method forwards to one allocator, the same for the whole process.
unsafe impl GlobalAlloc for ProcessAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if choice() == SYSTEM {
            System.alloc(layout)
        } else {
            MiMalloc.alloc(layout)
        }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if choice() == SYSTEM {
            System.alloc_zeroed(layout)
        } else {
            MiMalloc.alloc_zeroed(layout)
        }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        if choice() == SYSTEM {
            System.dealloc(ptr, layout)
        } else {
            MiMalloc.dealloc(ptr, layout)
        }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if choice() == SYSTEM {
            System.realloc(ptr, layout, new_size)
        } else {
            MiMalloc.realloc(ptr, layout, new_size)
        }
    }
}
