//! Cache-line-aligned heap memory for every buffer of a program that opts in.
//!
//! The kernels move data in 64-byte AVX-512 vectors. The system allocator returns large blocks
//! 16 bytes past a page (glibc's chunk header), so every vector of a tensor, a weight matrix or
//! a scratch buffer straddled two cache lines: each load or store touched two lines, and a
//! store that splits costs two. This allocator asks the system for 64-byte alignment for every
//! block of at least 1 KiB (small ones, strings and the like, keep the system's), so every
//! `Vec<f32>` the kernels stream over starts on a cache line and its vectors lie inside lines.
//!
//! The library does not set the program's allocator: a program that links `invaders` keeps its
//! own. The `invaders` binary, the benchmarks and the examples opt in, each with
//!
//! ```ignore
//! #[global_allocator]
//! static GLOBAL: invaders::CacheAligned = invaders::CacheAligned;
//! ```
//!
//! Without it everything computes the same values (the kernels use unaligned loads and stores
//! and assume no alignment), only slower where a vector straddles two cache lines.

use std::alloc::{GlobalAlloc, Layout, System};

/// The system allocator with blocks of 1 KiB or more aligned to 64 bytes.
pub struct CacheAligned;

/// Blocks from this size up are cache-line aligned.
const LARGE: usize = 1024;

/// The layout actually requested from the system for `layout`.
#[inline]
fn aligned(layout: Layout) -> Layout {
    if layout.size() >= LARGE && layout.align() < 64 {
        // 64 is a power of two and the size is unchanged, so this cannot fail.
        layout.align_to(64).unwrap_or(layout)
    } else {
        layout
    }
}

// SAFETY: every call forwards to `System` with `aligned(layout)`, a layout of the same size and
// a stricter alignment, and `dealloc`/`realloc` recompute the same `aligned(layout)` from the
// layout the block was allocated with, as `GlobalAlloc` requires them to be given.
unsafe impl GlobalAlloc for CacheAligned {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        System.alloc(aligned(layout))
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        System.alloc_zeroed(aligned(layout))
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, aligned(layout))
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let new = Layout::from_size_align(new_size, layout.align()).expect("valid layout");
        if aligned(layout) == layout && aligned(new) == new {
            // Small before and after: the system's own realloc.
            return System.realloc(ptr, layout, new_size);
        }
        // Otherwise a fresh aligned block and a copy (buffers here are sized once and reused).
        let fresh = self.alloc(new);
        if !fresh.is_null() {
            std::ptr::copy_nonoverlapping(ptr, fresh, layout.size().min(new_size));
            self.dealloc(ptr, layout);
        }
        fresh
    }
}

/// The library's own unit tests run with it, as the binaries do.
#[cfg(test)]
#[global_allocator]
static GLOBAL: CacheAligned = CacheAligned;

#[cfg(test)]
mod tests {
    /// Buffers of 1 KiB or more start on a cache line, also after growing from small ones (the
    /// `realloc` path), and keep their contents.
    #[test]
    fn large_buffers_are_cache_aligned() {
        for n in [256usize, 1000, 8192, 100_000, 1_000_000] {
            let v = vec![1.5f32; n];
            assert_eq!(v.as_ptr() as usize % 64, 0, "vec of {n}");
            let w: Vec<f64> = Vec::with_capacity(n);
            assert_eq!(w.as_ptr() as usize % 64, 0, "capacity {n}");
        }
        let mut grown = Vec::new();
        for i in 0..50_000u32 {
            grown.push(i as f32);
            if grown.capacity() * 4 >= super::LARGE {
                assert_eq!(grown.as_ptr() as usize % 64, 0, "grown to {}", grown.len());
            }
        }
        assert!(grown.iter().enumerate().all(|(i, &v)| v == i as f32));
        let mut shrunk = grown;
        shrunk.truncate(10);
        shrunk.shrink_to_fit();
        assert_eq!(shrunk, (0..10).map(|i| i as f32).collect::<Vec<_>>());
    }
}
